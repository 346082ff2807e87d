"""The service flying the bundled simulator over loopback (real UDP sockets, real zenoh sessions, one event loop).

Every flight runs the simulator ``SPEEDUP`` times faster than real time, and the service on the simulator's
own clock (``SimulatorClock``), so all limits keep their meaning in simulated seconds and a loaded machine
only makes a flight slower. Waits are in simulated seconds; wall deadlines only bound a hang.
"""

from __future__ import annotations

import asyncio
import contextlib
import math
from collections.abc import AsyncIterator, Callable
from typing import Any

import numpy as np
import pytest
from pymavlink.dialects.v20 import ardupilotmega as m

from apf_companion.autopilot import CopterMode, Px4MainMode, Px4Mode
from apf_companion.config import ServiceConfig, config_from_mapping
from apf_companion.goal import Route
from apf_companion.links import MavlinkLink
from apf_companion.navigator import State
from apf_companion.perception import GoalCommand, encode_goal_json
from apf_companion.service import CompanionService
from sim.vehicle import SimConfig, Simulator, SpawnConfig, ZenohOutput
from sim.world import World, paper_field
from tests.conftest import HANG_S, SimulatorClock, counter_advances, free_port, until, until_sim_time

pytestmark = [pytest.mark.slow, pytest.mark.timeout(600)]

SPEEDUP = 4.0
GOAL = (22.0, 22.0, -5.0)


def service_config(profile: str = "ardupilot", planner: str = "cr-bapf*", **extra: dict[str, Any]) -> ServiceConfig:
    base: dict[str, Any] = {
        "link": {"connect": "udpin:127.0.0.1:0"},
        "autopilot": {"profile": profile},
        "planner": {"name": planner, "seed": 1},
        "cycle": {
            "rate_hz": 10.0,
            "time_scale": SPEEDUP,
            "pose_max_age_s": 1.0,
            "ranges_max_age_s": 1.0,
        },
        "status": {"named_value_rate_hz": 1.0},
    }
    for key, value in extra.items():
        base[key] = base.get(key, {}) | value
    return config_from_mapping(base)


@contextlib.asynccontextmanager
async def running(svc: CompanionService, sim: Simulator) -> AsyncIterator[None]:
    """Run the service in this loop while the body runs; then stop it and close the simulator."""
    if isinstance(svc.clock, SimulatorClock):
        svc.clock.follow(sim)
    try:
        async with asyncio.TaskGroup() as tg:
            task = tg.create_task(svc.run())
            try:
                yield
            finally:
                svc.stop()
                await task
    finally:
        await sim.aclose()


@contextlib.asynccontextmanager
async def flight(
    world: World,
    cfg: ServiceConfig,
    *,
    route: Route | None = None,
    profile: str = "ardupilot",
    spawn_mode: str | None = None,
    zenoh_out: Callable[[int], ZenohOutput] | None = None,
    sensor_messages: frozenset[str] = frozenset({"obstacle_distance"}),
) -> AsyncIterator[tuple[CompanionService, Simulator]]:
    """Service (udpin, free port) and simulator (udpout to it) in this loop; yields both while they run."""
    zport = free_port()
    if zenoh_out is not None:
        zsec = {"enabled": True, "mode": "peer", "listen": [f"tcp/127.0.0.1:{zport}"]}
        cfg = config_from_mapping(_as_mapping(cfg) | {"zenoh": zsec} | {"sensors": {"mavlink": False, "zenoh": True}})
    svc = await CompanionService.open(cfg, route=route, clock=SimulatorClock(SPEEDUP))
    assert svc.link is not None and svc.link.local_address is not None
    port = svc.link.local_address[1]
    from sim.vehicle import RangeSensorConfig

    sim = await Simulator.start(
        SimConfig(
            links=[f"udpout:127.0.0.1:{port}"],
            profile=profile,
            world=world,
            speedup=SPEEDUP,
            seed=3,
            spawn=SpawnConfig(pos_ne_m=(3.0, 3.0), airborne=True, alt_m=5.0, mode=spawn_mode),
            sensor=RangeSensorConfig(messages=sensor_messages),
            zenoh=None if zenoh_out is None else zenoh_out(zport),
        )
    )
    async with running(svc, sim):
        yield svc, sim


def _as_mapping(cfg: ServiceConfig) -> dict[str, Any]:
    """The config back as a TOML-like mapping (to add sections in a test)."""
    out: dict[str, Any] = {}
    for section in ("link", "autopilot", "planner", "cycle", "status"):
        obj = getattr(cfg, section)
        table = {}
        for name in obj.__dataclass_fields__:
            v = getattr(obj, name)
            table[name] = v.value if hasattr(v, "value") else list(v) if isinstance(v, tuple) else v
        if section == "planner":
            table["params"] = dict(cfg.planner.params)
        out[section] = table
    return out


async def wait_state(svc: CompanionService, states: set[State], within_s: float) -> State:
    """Wait until the navigator is in one of ``states``; fail if it is not within ``within_s`` SIMULATED seconds."""
    deadline_s = svc.clock.now() + within_s
    await until(
        lambda: svc.navigator.state in states or svc.clock.now() > deadline_s,
        HANG_S * 10,
        f"a state in {states} or {within_s} simulated s",
    )
    assert svc.navigator.state in states, f"not in {states} within {within_s} simulated s: {svc.result()}"
    return svc.navigator.state


def sparse_world(seed: int, n: int = 12) -> World:
    return paper_field("reference", n, np.random.default_rng(seed))


async def airborne_behind(vehicle_port: int) -> Simulator:
    """The simulator hovering at 5 m over (3, 3) in an empty world, sending to ``vehicle_port`` on loopback (a
    fault proxy's vehicle side)."""
    return await Simulator.start(
        SimConfig(
            links=[f"udpout:127.0.0.1:{vehicle_port}"],
            world=World.empty(),
            speedup=SPEEDUP,
            seed=3,
            spawn=SpawnConfig(pos_ne_m=(3.0, 3.0), airborne=True, alt_m=5.0),
        )
    )


# World 0 is no test of the paper's planners: bapf, a-bapf and cr-bapf pass cylinder 11 at 0.257-0.266 m surface
# clearance against the 0.25 m vehicle radius, so a few milliseconds of timing decide between ARRIVED and a
# crash. World 1 leaves them 0.64 m; the product planner keeps its harder worlds 0 and 5 (0.35 and 0.30 m).
@pytest.mark.parametrize(
    ("planner", "seed"),
    [("capf", 1), ("bapf", 1), ("a-bapf", 1), ("cr-bapf", 1), ("cr-bapf*", 0), ("cr-bapf*", 5)],
)
async def test_each_planner_flies_a_seeded_world(planner: str, seed: int) -> None:
    world = sparse_world(seed)
    cfg = service_config(planner=planner)
    async with flight(world, cfg, route=Route.point(*GOAL, source="test"), spawn_mode="LOITER") as (svc, sim):
        state = await wait_state(svc, {State.ARRIVED, State.STUCK}, 240.0)
        res = sim.result()
    assert state is State.ARRIVED, svc.result()
    assert not res["collided"]
    assert math.dist(res["final_pos_ned_m"][:2], GOAL[:2]) <= 0.7 + 0.3
    assert res["min_clearance_m"] is None or res["min_clearance_m"] > 0.0
    assert svc.navigator.counters.planner_steps > 40  # ~27 m in 0.4 m steps


async def test_ardupilot_takeover_confirmed_from_heartbeat() -> None:
    cfg = service_config()
    async with flight(World.empty(), cfg, route=Route.point(8.0, 3.0, -5.0, source="t"), spawn_mode="LOITER") as (
        svc,
        sim,
    ):
        assert sim.vehicle.mode == "LOITER"
        await wait_state(svc, {State.ARRIVED}, 120.0)
        assert sim.vehicle.custom_mode == CopterMode.GUIDED
        assert svc.navigator.engaged and svc.reporter.counters.mode_requests >= 1
        flown_s = svc.result().flight_time_s
        await counter_advances(lambda: svc.navigator.counters.cycles, 20, "cycles holding at the goal")
    assert 0.0 < flown_s == svc.result().flight_time_s  # the flight ended at the arrival, not when the run did


async def test_px4_offboard_after_prestream() -> None:
    cfg = service_config(profile="px4")
    async with flight(World.empty(), cfg, route=Route.point(8.0, 3.0, -5.0, source="t"), profile="px4") as (
        svc,
        sim,
    ):
        await wait_state(svc, {State.ARRIVED}, 120.0)
        assert Px4Mode.from_custom_mode(sim.vehicle.custom_mode).main == Px4MainMode.OFFBOARD
        texts = [t for _, _, t in sim.result()["statustexts"]]
        # The simulator refuses OFFBOARD without >= 1 s of setpoints ("... not available"): never happened.
        assert not any("not available" in t or "offboard signal lost" in t for t in texts), texts
        # One request sufficed: the first DO_SET_MODE came after the pre-stream.
        assert svc.reporter.counters.mode_requests == 1


@pytest.mark.parametrize("profile", ["ardupilot", "px4"])
async def test_arm_and_takeoff_from_the_ground_when_asked(profile: str) -> None:
    cfg = service_config(profile, autopilot={"arm": True, "takeoff_alt_m": 4.0})
    async with _ground_flight(cfg, Route.point(6.0, 3.0, None, source="t"), profile) as (svc, sim):
        assert not sim.vehicle.armed and sim.vehicle.on_ground
        await wait_state(svc, {State.ARRIVED}, 180.0)
        assert sim.vehicle.armed and not sim.vehicle.on_ground
        assert -sim.vehicle.pos_ned_m[2] > 3.0  # "keep altitude" kept the takeoff height, not the ground's
        if profile == "ardupilot":
            assert sim.vehicle.custom_mode == CopterMode.GUIDED
        else:
            assert Px4Mode.from_custom_mode(sim.vehicle.custom_mode).main == Px4MainMode.OFFBOARD


@contextlib.asynccontextmanager
async def _ground_flight(
    cfg: ServiceConfig, route: Route, profile: str = "ardupilot"
) -> AsyncIterator[tuple[CompanionService, Simulator]]:
    svc = await CompanionService.open(cfg, route=route, clock=SimulatorClock(SPEEDUP))
    assert svc.link is not None and svc.link.local_address is not None
    sim = await Simulator.start(
        SimConfig(
            links=[f"udpout:127.0.0.1:{svc.link.local_address[1]}"],
            profile=profile,
            speedup=SPEEDUP,
            spawn=SpawnConfig(pos_ne_m=(3.0, 3.0), airborne=False),
            fast_start=True,  # the EKF startup wait is tested in test_service_startup.py
        )
    )
    async with running(svc, sim):
        yield svc, sim


async def test_not_armed_by_default() -> None:
    cfg = service_config()
    async with _ground_flight(cfg, Route.point(6.0, 3.0, None, source="t")) as (svc, sim):
        await until_sim_time(svc.clock, svc.clock.now() + 6.0)
        assert not sim.vehicle.armed and sim.vehicle.on_ground
        assert svc.navigator.state is State.NAVIGATING  # it has a goal; it just never arms on its own


@pytest.mark.parametrize("encoding", ["json", "cdr"])
async def test_ranges_over_zenoh_instead_of_mavlink(encoding: str) -> None:
    # The sim publishes its scans only on zenoh (no range message on MAVLink): the service must see the
    # obstacles there, or it would stay in HOLDING (no fresh ranges) and never fly.
    world = sparse_world(0)
    cfg = service_config()
    async with flight(
        world,
        cfg,
        route=Route.point(*GOAL, source="t"),
        spawn_mode="LOITER",
        zenoh_out=lambda port: ZenohOutput(connect=(f"tcp/127.0.0.1:{port}",), encoding=encoding),
        sensor_messages=frozenset(),
    ) as (svc, sim):
        state = await wait_state(svc, {State.ARRIVED, State.STUCK}, 240.0)
        res = sim.result()
        remembered = svc.perception.memory.points(svc.clock.now())
    assert state is State.ARRIVED
    assert not res["collided"]
    assert svc.perception.counters.scans > 10 and svc.perception.counters.bad_scans == 0
    # The remembered points lie on real obstacles: off by the 5-degree sector quantisation (<= 0.35 m at 8 m)
    # plus the motion between measurement and placement (zenoh scans carry no boot time: stamped on receipt,
    # and at SPEEDUP x a few ms of wall latency are a few cm more).
    assert remembered.shape[0] > 0
    d = np.hypot(*(remembered[:, None, :2] - world.circles_ne_m[None, :, :]).transpose(2, 0, 1))
    err = np.min(d, axis=1)
    assert np.median(err) < 0.3 and np.max(err) < 0.8, err


async def test_goal_changed_mid_flight_by_zenoh() -> None:
    cfg = service_config()
    zport = free_port()
    cfg = config_from_mapping(_as_mapping(cfg) | {"zenoh": {"enabled": True, "listen": [f"tcp/127.0.0.1:{zport}"]}})
    from apf_companion.links.zenoh import ZenohConfig, ZenohLink

    async with (
        flight(World.empty(), cfg, route=Route.point(20.0, 3.0, -5.0, source="t"), spawn_mode="LOITER") as (
            svc,
            sim,
        ),
        await ZenohLink.open(ZenohConfig(connect=(f"tcp/127.0.0.1:{zport}",))) as zl,
    ):
        status_sub = await zl.subscribe("apf/status")
        await until(lambda: svc.navigator.counters.planner_steps >= 10, HANG_S, "10 planner steps")
        goal = GoalCommand(pos_ned_m=np.array([3.0, 12.0, -6.0]))
        async with asyncio.timeout(HANG_S):
            while svc.navigator.route is None or svc.navigator.route.source != "zenoh":
                zl.publish("apf/cmd/goal", encode_goal_json(goal))  # again: the peers may still be connecting
                await svc.clock.sleep(0.8)
        await wait_state(svc, {State.ARRIVED}, 160.0)
        sample = await status_sub.recv(timeout=HANG_S)
        import json

        status = json.loads(sample.payload)
        assert status["schema"] == "apf.status/1"
        assert status["state"] in {s.value for s in State}
        assert {"pose", "goal", "nearest_obstacle_m", "loop_latency_ms"} <= set(status)
        assert set(status["gc"]) == {"collections", "full", "max_pause_ms", "frozen"}  # the running service's
    assert math.dist(sim.result()["final_pos_ned_m"][:2], (3.0, 12.0)) <= 1.0


async def test_goal_changed_mid_flight_by_do_reposition() -> None:
    cfg = service_config()
    async with flight(World.empty(), cfg, route=Route.point(20.0, 3.0, -5.0, source="t"), spawn_mode="LOITER") as (
        svc,
        sim,
    ):
        await until(lambda: svc.navigator.counters.planner_steps >= 10, HANG_S, "10 planner steps")
        port = svc.link.local_address[1]  # type: ignore[union-attr,index]
        gcs = await MavlinkLink.open(f"udpout:127.0.0.1:{port}", source_system=255, source_component=190)
        try:
            gcs.send(gcs.mav.command_int_encode(1, 191, 1, 192, 0, 0, -1, 1, 0, math.nan, 30000, 120000, -5.0))
            ack = await gcs.recv_match(type="COMMAND_ACK", timeout=HANG_S)
            assert ack.command == 192 and ack.result == 0
        finally:
            await gcs.aclose()
        await wait_state(svc, {State.ARRIVED}, 160.0)
    assert math.dist(sim.result()["final_pos_ned_m"][:2], (3.0, 12.0)) <= 1.0


async def test_3d_planner_climbs_and_avoids() -> None:
    world = sparse_world(0)
    cfg = config_from_mapping(_as_mapping(service_config()) | {"planner": {"name": "cr-bapf*", "dim": 3}})
    async with flight(world, cfg, route=Route.point(22.0, 22.0, -8.0, source="t"), spawn_mode="LOITER") as (
        svc,
        sim,
    ):
        state = await wait_state(svc, {State.ARRIVED, State.STUCK}, 240.0)
        res = sim.result()
    assert state is State.ARRIVED
    assert not res["collided"]
    final = res["final_pos_ned_m"]
    assert math.dist(final, (22.0, 22.0, -8.0)) <= 0.7 + 0.3  # 3D arrival radius


async def test_a_pose_stream_slowed_on_the_link_is_asked_for_again() -> None:
    """A ground station on the companion's link sends REQUEST_DATA_STREAM POSITION at 2 Hz (MAVProxy's default is
    4 Hz): the simulated ArduCopter then sends LOCAL_POSITION_NED at 2 Hz on that link (GCS_Common.cpp
    handle_request_data_stream). The pose still arrives, so before session 28 nothing asked again and the service
    planned on a 2 Hz pose; now it notices within a rate window and asks for its 20 Hz again."""
    lpos = m.MAVLINK_MSG_ID_LOCAL_POSITION_NED
    async with flight(World.empty(), service_config()) as (svc, sim):
        telemetry = sim.engine.telemetry
        await until(lambda: svc.handlers.streams.measured_hz.get(lpos, 0.0) > 15.0, HANG_S, "the pose at 20 Hz")
        telemetry.set_data_stream(0, m.MAV_DATA_STREAM_POSITION, 2.0, sim.engine.t_s)  # the GCS's request
        assert telemetry.interval_us(0, lpos) == 500_000
        await until(lambda: svc.counters.slow_streams >= 1, HANG_S * 4, "the slow pose noticed")
        await until(lambda: telemetry.interval_us(0, lpos) == 50_000, HANG_S, "the pose asked for at 20 Hz again")
        await until(lambda: svc.handlers.streams.measured_hz.get(lpos, 0.0) > 15.0, HANG_S * 4, "the pose at 20 Hz")
