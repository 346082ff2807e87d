"""The service against a vehicle that starts like a real ArduCopter (issue 8), over loopback UDP, one event loop.

The simulator's ArduPilot profile has no position for 20 s after boot (EKF origin) and sends only HEARTBEAT until
streams are requested. The service must ask for every stream it needs, wait (bounded, saying why) before taking
over, then fly; send NAV_TAKEOFF once per ACK; end a run that never navigated at ``max_flight_s``; and keep its
streams coming. The simulator runs ``SPEEDUP`` times faster than real time and the service on its clock
(``SimulatorClock``): waits are in simulated seconds, wall deadlines only bound a hang.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
from collections.abc import AsyncIterator
from typing import Any

import pytest
from pymavlink.dialects.v20 import ardupilotmega as m

from apf_companion.config import ServiceConfig, config_from_mapping
from apf_companion.goal import Route
from apf_companion.navigator import State
from apf_companion.service import CompanionService
from apf_companion.streams import STREAM_RETRY_S, STREAM_STALE_S
from sim.vehicle import RangeSensorConfig, SimConfig, Simulator, SpawnConfig
from tests.conftest import HANG_S, SimulatorClock, until, until_sim_time

pytestmark = [pytest.mark.slow, pytest.mark.timeout(600)]

SPEEDUP = 10.0
ORIGIN_S = 20.0  # the simulator's SIM_EKF_ORIGIN_S default (ArduCopter SITL: about 20 s)
EKF_WAIT = "waiting for EKF origin: no position yet"


def config(**extra: dict[str, Any]) -> ServiceConfig:
    base: dict[str, Any] = {
        "link": {"connect": "udpin:127.0.0.1:0"},
        "autopilot": {"profile": "ardupilot"},
        "planner": {"name": "cr-bapf*", "seed": 1},
        "cycle": {"rate_hz": 10.0, "time_scale": SPEEDUP, "pose_max_age_s": 1.0, "ranges_max_age_s": 1.0},
    }
    for key, value in extra.items():
        base[key] = base.get(key, {}) | value
    return config_from_mapping(base)


class CommandSpy:
    """Counts the COMMAND_LONGs the simulated autopilot receives (it watches ``engine.handle``; changes nothing)."""

    def __init__(self, sim: Simulator) -> None:
        self.commands: list[tuple[float, int]] = []
        handle = sim.engine.handle

        def watched(msg: Any, link: int) -> None:
            if msg.get_type() == "COMMAND_LONG":
                self.commands.append((sim.t_s, int(msg.command)))
            handle(msg, link)

        sim.engine.handle = watched  # type: ignore[method-assign]

    def count(self, command: int) -> int:
        return sum(1 for _, c in self.commands if c == command)


@contextlib.asynccontextmanager
async def service_and_vehicle(
    cfg: ServiceConfig, route: Route, **sim: Any
) -> AsyncIterator[tuple[CompanionService, Simulator, CommandSpy]]:
    svc = await CompanionService.open(cfg, route=route, clock=SimulatorClock(SPEEDUP))
    assert svc.link is not None and svc.link.local_address is not None
    vehicle = await Simulator.start(
        SimConfig(links=[f"udpout:127.0.0.1:{svc.link.local_address[1]}"], speedup=SPEEDUP, **sim)
    )
    spy = CommandSpy(vehicle)
    assert isinstance(svc.clock, SimulatorClock)
    svc.clock.follow(vehicle)
    try:
        async with asyncio.TaskGroup() as tg:
            task = tg.create_task(svc.run())
            try:
                yield svc, vehicle, spy
            finally:
                svc.stop()
                await task
    finally:
        await vehicle.aclose()


async def test_waits_for_the_ekf_origin_says_why_then_arms_takes_off_once_and_flies() -> None:
    """Ground start, default ArduPilot startup (no fast start, no unasked streams), arducopter dynamics (the motors
    spool up for seconds after NAV_TAKEOFF is accepted: the old service resent it every second meanwhile)."""
    cfg = config(autopilot={"arm": True, "takeoff_alt_m": 3.0})
    route = Route.point(7.0, 3.0, None, source="test")
    sim_cfg: dict[str, Any] = {"spawn": SpawnConfig(pos_ne_m=(3.0, 3.0)), "dynamics": "arducopter"}
    async with service_and_vehicle(cfg, route, **sim_cfg) as (svc, sim, spy):
        await until_sim_time(svc.clock, ORIGIN_S - 5.0)
        # before the origin: holding, saying why; nothing tried that the autopilot would refuse
        assert svc.navigator.state is State.HOLDING
        assert svc.reporter.reason == EKF_WAIT
        assert not sim.vehicle.armed
        assert spy.count(m.MAV_CMD_DO_SET_MODE) == 0 and spy.count(m.MAV_CMD_COMPONENT_ARM_DISARM) == 0
        texts = [s.text for s in sim.engine.statustexts]
        assert not [t for t in texts if "failed" in t or t.startswith("PreArm")]
        # every stream the service reads was requested on its own (the vehicle streams nothing unasked)
        streams = sim.engine.telemetry.streams[0]
        for msg_id in (
            m.MAVLINK_MSG_ID_LOCAL_POSITION_NED,
            m.MAVLINK_MSG_ID_ATTITUDE,
            m.MAVLINK_MSG_ID_GLOBAL_POSITION_INT,
            m.MAVLINK_MSG_ID_EKF_STATUS_REPORT,
        ):
            assert streams[msg_id].interval_s > 0, msg_id
        # after the origin: GUIDED, arm, take off (NAV_TAKEOFF once: accepted, then climbing), fly, arrive
        await until(lambda: svc.navigator.state is State.ARRIVED, HANG_S, "arrived")
        assert sim.engine.startup.origin_t_s == pytest.approx(ORIGIN_S, abs=0.02)
        assert sim.engine.armed_t_s > ORIGIN_S
        assert spy.count(m.MAV_CMD_NAV_TAKEOFF) == 1
        assert not sim.vehicle.crashed


async def test_exit_when_done_ends_a_run_that_never_navigated_and_the_reason_follows_the_cause() -> None:
    """No ranges ever (the range sensor is off): HOLDING with the current cause, and ``max_flight_s`` ends it."""
    cfg = config_from_mapping(
        {
            **{"exit_when_done": True, "max_flight_s": 8.0},
            "link": {"connect": "udpin:127.0.0.1:0"},
            "cycle": {"rate_hz": 10.0, "time_scale": SPEEDUP},
        }
    )
    route = Route.point(8.0, 0.0, None, source="test")
    sim_cfg: dict[str, Any] = {
        "spawn": SpawnConfig(airborne=True, alt_m=5.0),
        "sensor": RangeSensorConfig(messages=frozenset()),
    }
    async with service_and_vehicle(cfg, route, **sim_cfg) as (svc, sim, _spy):
        await until(lambda: svc.reporter.reason == "no ranges yet: holding position", HANG_S, "reason: no ranges")
        assert svc.navigator.pose is not None  # the pose came (requested): the cause moved on from "no pose"
        await until(lambda: svc.result().outcome == "timeout", HANG_S, "timeout outcome")
        assert svc.result().steps == 0 and svc.result().flight_time_s == 0.0
        assert sim.t_s < 8.0 + 5.0


async def test_a_goal_at_start_beyond_max_distance_is_checked_at_the_first_pose_and_refused(
    caplog: pytest.LogCaptureFixture,
) -> None:
    """The goal at start is set at the first HEARTBEAT, before any pose: it used to skip the distance check and
    fly 3 km (``bad_goals`` 0). Now it waits for the position, is refused, and with ``exit_when_done`` the run
    ends with outcome "error"; nothing was flown."""
    cfg = config_from_mapping(
        {
            "exit_when_done": True,
            "link": {"connect": "udpin:127.0.0.1:0"},
            "autopilot": {"profile": "ardupilot"},
            "planner": {"name": "cr-bapf*", "seed": 1},
            "cycle": {"rate_hz": 10.0, "time_scale": SPEEDUP},
        }
    )
    route = Route.point(3000.0, 0.0, -5.0, source="cli")  # goal.max_distance_m: 2000 m by default
    sim_cfg: dict[str, Any] = {"spawn": SpawnConfig(airborne=True, alt_m=5.0, mode="GUIDED")}
    caplog.set_level(logging.INFO, logger="apf_companion.goaladmission")
    async with service_and_vehicle(cfg, route, **sim_cfg) as (svc, sim, _spy):
        await until(lambda: svc.result().outcome == "error", HANG_S, "error outcome")
        assert svc.navigator.pose is not None
        assert svc.counters.bad_goals == 1 and svc.counters.goals == 0
        assert svc.navigator.route is None and svc.result().steps == 0
        assert abs(float(sim.vehicle.pos_ned_m[0])) < 1.0  # never flown towards it
        events = [(r.getMessage(), getattr(r, "reason", "")) for r in caplog.records]
        assert ("goal.held", "goal waits for a position to check goal.max_distance_m") in events
        assert any(e == "goal.refused" and "goal.max_distance_m = 2000" in why for e, why in events)
        assert not any(e == "goal.set" for e, _ in events)


async def test_a_stream_that_stops_is_requested_again() -> None:
    """The autopilot stops sending ATTITUDE on the service's link (as after a reboot, which forgets every
    request): the service asks again within STREAM_STALE_S + STREAM_RETRY_S."""
    cfg = config()
    route = Route.point(3.0, 0.0, None, source="test")
    sim_cfg: dict[str, Any] = {"spawn": SpawnConfig(airborne=True, alt_m=5.0)}
    async with service_and_vehicle(cfg, route, **sim_cfg) as (svc, sim, spy):
        telemetry = sim.engine.telemetry
        await until(lambda: telemetry.interval_us(0, m.MAVLINK_MSG_ID_ATTITUDE) > 0, HANG_S, "ATTITUDE requested")
        asked = spy.count(m.MAV_CMD_SET_MESSAGE_INTERVAL)
        t_off = sim.t_s
        telemetry.set_interval(0, m.MAVLINK_MSG_ID_ATTITUDE, -1, sim.t_s)
        await until(lambda: telemetry.interval_us(0, m.MAVLINK_MSG_ID_ATTITUDE) > 0, HANG_S, "ATTITUDE again")
        assert spy.count(m.MAV_CMD_SET_MESSAGE_INTERVAL) > asked
        again = next(t for t, c in spy.commands[asked:] if c == m.MAV_CMD_SET_MESSAGE_INTERVAL)
        assert again - t_off <= STREAM_STALE_S + STREAM_RETRY_S + 1.5  # + a heartbeat period and a cycle
        assert svc.result().counters["stream_requests"] > 0
