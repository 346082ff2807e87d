"""Safe when silent: the last setpoint that reaches the autopilot leaves the vehicle safe without the companion.

ArduCopter advances a pos+vel target along its velocity until GUID_TIMEOUT (ArduCopter/mode_guided.cpp
``posvel_control_run``), PX4 settles ``|v| / MPC_XY_P`` past it (PositionControl.cpp): so the feed-forward is
bounded by ``[safety] silent_drift_m`` over ``guid_timeout_s`` and never points into a remembered obstacle. The
flight test cuts the service's link mid-flight on the bundled simulator and checks both the setpoint contents
(which bound any autopilot model that follows the velocity for GUID_TIMEOUT) and where the vehicle stopped.
"""

from __future__ import annotations

import math

import numpy as np
import pytest

from apf_companion.goal import Route
from apf_companion.navigator import State
from apf_companion.setpoint import SetpointKind, silent_safe_velocity
from tests.service.test_service_flight import GOAL, flight, service_config, sparse_world

pytestmark = pytest.mark.timeout(90)

GUID_TIMEOUT_S = 3.0  # ArduCopter's default GUID_TIMEOUT, the service's [safety] guid_timeout_s default


def test_feed_forward_is_bounded_and_stops_short_of_an_obstacle_beyond_the_target() -> None:
    target = np.array([1.0, 0.0, -5.0])
    vel = (1.0, 0.0, 0.0)
    kw = {"horizon_s": 3.0, "max_drift_m": 1.0, "clearance_m": 0.3, "dim": 2}
    free = silent_safe_velocity(target, vel, np.zeros((0, 3)), **kw)  # type: ignore[arg-type]
    assert free[0] * 3.0 == pytest.approx(1.0) and free[1] == 0.0
    ahead = np.array([[1.5, 0.1, -5.0]])  # 0.5 m past the target, 0.1 m aside: the segment may run ~0.22 m
    v = silent_safe_velocity(target, vel, ahead, **kw)  # type: ignore[arg-type]
    drift = v[0] * 3.0
    assert 0.0 < drift <= 0.5 - math.sqrt(0.3**2 - 0.1**2) + 1e-9
    at_target = np.array([[1.2, 0.0, -5.0]])  # already within clearance of the target: position only
    assert silent_safe_velocity(target, vel, at_target, **kw) == (0.0, 0.0, 0.0)  # type: ignore[arg-type]
    behind = np.array([[0.0, 0.0, -5.0]])  # behind the target: no limit from it
    assert silent_safe_velocity(target, vel, behind, **kw)[0] == pytest.approx(free[0])  # type: ignore[arg-type]


async def test_link_cut_mid_flight_stops_near_the_last_step_target() -> None:
    world = sparse_world(0)
    cfg = service_config()
    drift_m = cfg.safety.silent_drift_m
    async with flight(world, cfg, route=Route.point(*GOAL, source="test"), spawn_mode="LOITER") as (svc, sim):
        ok = await sim.wait_until(lambda s: svc.navigator.counters.planner_steps > 20, timeout_s=60.0)
        assert ok and svc.navigator.state is State.NAVIGATING
        svc.outbox.link = None  # the link is cut: nothing more reaches the vehicle
        last = svc.outbox.last_setpoint
        t_cut = sim.t_s
        assert last is not None and last.kind is SetpointKind.NAVIGATE
        # The setpoint itself: any model that follows its velocity for GUID_TIMEOUT stays within drift_m.
        speed = math.hypot(last.vel_ned_m_s[0], last.vel_ned_m_s[1])
        assert speed * GUID_TIMEOUT_S <= drift_m + 1e-9
        await sim.wait_until(lambda s: s.t_s > t_cut + GUID_TIMEOUT_S + 4.0, timeout_s=30.0)
        v = sim.vehicle
        res = sim.result()
    assert not res["collided"]
    assert float(np.hypot(*v.vel_ned_m_s[:2])) < 0.1  # stopped
    stop_m = math.dist(v.pos_ned_m[:2].tolist(), last.pos_ned_m[:2])
    assert stop_m <= drift_m + 0.3, (stop_m, last)  # the drift budget plus tracking / braking
