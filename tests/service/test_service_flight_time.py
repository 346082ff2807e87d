"""The result's ``flight_time_s`` runs from the flight's first navigation setpoint to the state that ended it
(arrived, ...), not to the end of the run; to the stop only when no state ended it (no sockets: records go
straight to the handlers, the service clock is injected, the vehicle follows each setpoint at once)."""

from __future__ import annotations

from typing import Any

import pytest
from pymavlink.dialects.v20 import ardupilotmega as m

from apf_companion.config import config_from_mapping
from apf_companion.goal import Route
from apf_companion.links.messages import Attitude, Heartbeat, LocalPositionNed, Source
from apf_companion.navigator import State
from apf_companion.service import CompanionService
from apf_companion.setpoint import SetpointKind
from tests.conftest import ManualClock

AP = Source(1, 1)
PERIOD_S = 0.1


class Rig:
    """A service in GUIDED with a vehicle that is where the last navigation setpoint put it."""

    def __init__(self, **extra: Any) -> None:
        self.clock = ManualClock()
        base = {"link": {"connect": "udpin:127.0.0.1:0"}, "sensors": {"require_ranges": False}}
        cfg = config_from_mapping(base | extra)
        self.svc = CompanionService(cfg, clock=self.clock)
        self.north_m = 0.0
        self.first_nav_s: float | None = None
        self.cycle()  # heard and placed: a goal can be checked and taken

    def cycle(self) -> State:
        """One period on: a HEARTBEAT (GUIDED, armed), the pose, a cycle."""
        self.clock.t += PERIOD_S
        t, svc = self.clock.t, self.svc
        hb = Heartbeat(src=AP, type=m.MAV_TYPE_QUADROTOR, autopilot=3, base_mode=129, custom_mode=4, system_status=4)
        svc.handlers.handle(hb, t)
        ms = int(t * 1000)
        svc.handlers.handle(Attitude(src=AP, time_boot_ms=ms, roll=0.0, pitch=0.0, yaw=0.0), t)
        pose = LocalPositionNed(src=AP, time_boot_ms=ms, x=self.north_m, y=0.0, z=-5.0, vx=0, vy=0, vz=0)
        svc.handlers.handle(pose, t)
        out = svc.run_cycle(t)
        sp = out.setpoint
        if sp is not None and sp.kind is SetpointKind.NAVIGATE:
            self.first_nav_s = t if self.first_nav_s is None else self.first_nav_s
            self.north_m = float(sp.pos_ned_m[0])
        return out.state

    def fly(self, north_m: float) -> float:
        """Set a goal ``north_m`` ahead and cycle until ARRIVED; returns the time of arrival."""
        assert self.svc.admission.admit(Route.point(north_m, 0.0, -5.0, source="test"), self.clock.t)
        for _ in range(400):
            if self.cycle() is State.ARRIVED:
                return self.clock.t
        raise AssertionError(f"not arrived: {self.svc.result()}")

    def hold(self, seconds: float) -> None:
        for _ in range(round(seconds / PERIOD_S)):
            self.cycle()


def test_flight_time_ends_at_arrival_not_when_the_service_is_stopped() -> None:
    """The bug: without exit_when_done (the service's normal use) the flight time ran on while the vehicle held
    at the goal, to whenever the service was stopped (here 60 s later)."""
    rig = Rig()
    rig.hold(0.5)  # no goal yet, nothing flown
    arrived_s = rig.fly(8.0)
    assert rig.first_nav_s is not None
    flown_s = arrived_s - rig.first_nav_s
    assert flown_s > 1.0  # 8 m, a step per cycle
    rig.hold(60.0)
    result = rig.svc.result()
    assert result.outcome == "stopped" and result.state == "ARRIVED"
    assert result.flight_time_s == pytest.approx(flown_s)


def test_flight_time_of_a_run_stopped_mid_flight_runs_to_the_stop() -> None:
    rig = Rig()
    assert rig.svc.admission.admit(Route.point(30.0, 0.0, -5.0, source="test"), rig.clock.t)
    rig.hold(2.0)
    assert rig.svc.navigator.state is State.NAVIGATING and rig.first_nav_s is not None
    assert rig.svc.result().flight_time_s == pytest.approx(rig.clock.t - rig.first_nav_s)


def test_a_second_goal_after_arrival_is_a_new_flight() -> None:
    rig = Rig()
    rig.fly(2.0)
    rig.hold(20.0)
    rig.first_nav_s = None
    arrived_s = rig.fly(4.0)
    assert rig.first_nav_s is not None
    rig.hold(5.0)
    assert rig.svc.result().flight_time_s == pytest.approx(arrived_s - rig.first_nav_s)


def test_with_exit_when_done_the_arrival_ends_the_run_and_its_flight_time() -> None:
    rig = Rig(exit_when_done=True)
    arrived_s = rig.fly(3.0)
    assert rig.svc._stop.is_set() and rig.first_nav_s is not None
    rig.clock.t += 5.0  # closing the links takes a while
    result = rig.svc.result()
    assert result.outcome == "arrived" and result.flight_time_s == pytest.approx(arrived_s - rig.first_nav_s)
