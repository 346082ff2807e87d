"""Goals the way ground-station users give them: a "Fly here" sent to the autopilot (here the bundled simulator)
is adopted from the autopilot's POSITION_TARGET echo and flown around an obstacle; the service's own echoes are
never taken for a new goal. Real MAVLink over loopback UDP, the simulator on its own clock."""

from __future__ import annotations

import math

import pytest
from pymavlink.dialects.v20 import ardupilotmega as mavlink

from apf_companion.adopt import SentSetpoints, is_new_target
from apf_companion.autopilot import MASK_POSITION, MASK_VELOCITY, CopterMode
from apf_companion.goal import EARTH_RADIUS_M
from apf_companion.links import MavlinkLink
from apf_companion.navigator import State
from apf_companion.service import CompanionService
from sim.vehicle import RangeSensorConfig, SimConfig, Simulator, SpawnConfig
from sim.vehicle.geo import ne_to_latlon
from sim.world import World
from tests.conftest import HANG_S, SimulatorClock, within
from tests.service import test_service_flight as flights
from tests.service.test_service_flight import running, service_config, wait_state
from tests.service.test_service_mavlink import fast_config, rig

pytestmark = pytest.mark.timeout(600)

START = (3.0, 3.0)
TARGET = (17.0, 3.0, -5.0)  # the GCS's "fly here"; a pillar stands on the straight line


def _new(target: tuple[float, float, float], mask: int, sent: list[tuple[float, float, float]]) -> bool:
    """Goal 20 m north, the vehicle at 5.5 m north, 1 m tolerance."""
    return is_new_target(
        target, mask, sent=sent, goal_ned_m=(20.0, 0.0, -5.0), pose_ned_m=(5.5, 0.0, -5.0), tolerance_m=1.0
    )


def test_own_echoes_are_not_new_goals() -> None:
    sent = SentSetpoints()
    sent.add(0.0, (5.0, 0.0, -5.0))
    sent.add(10.0, (6.0, 0.0, -5.0))
    assert not _new((6.3, 0.2, -5.0), MASK_POSITION, sent.since(9.0))  # a lagging echo of ours
    assert not _new((19.5, 0.0, -5.0), MASK_POSITION, sent.since(9.0))  # our goal
    assert not _new((5.5, 0.4, -5.0), MASK_POSITION, [])  # the autopilot holding where it is
    assert not _new((30.0, 0.0, -5.0), MASK_VELOCITY, [])  # velocity only: no position
    assert not _new((math.nan, 0.0, -5.0), MASK_POSITION, [])
    assert _new((12.0, 8.0, -5.0), MASK_POSITION, sent.since(9.0))
    assert sent.since(100.0) == [(6.0, 0.0, -5.0)]  # the autopilot holds the last one however old
    no_pose = is_new_target((12.0, 8.0, -5.0), MASK_POSITION, sent=[], goal_ned_m=None, pose_ned_m=None, tolerance_m=1)
    assert not no_pose


@pytest.mark.slow
async def test_fly_here_sent_to_the_autopilot_is_adopted_and_flown_around_an_obstacle() -> None:
    world = World.from_obstacles([[10.0, 3.0]], 1.2, name="pillar")
    cfg = service_config(planner="bapf-nav", goal={"adopt_autopilot_target": True})
    svc = await CompanionService.open(cfg, clock=SimulatorClock(flights.SPEEDUP))
    gcs = await MavlinkLink.open("udpin:127.0.0.1:0", source_system=255, source_component=190)
    assert svc.link is not None and svc.link.local_address is not None and gcs.local_address is not None
    sim = await Simulator.start(
        SimConfig(
            links=[f"udpout:127.0.0.1:{svc.link.local_address[1]}", f"udpout:127.0.0.1:{gcs.local_address[1]}"],
            profile="ardupilot",
            world=world,
            speedup=flights.SPEEDUP,
            seed=3,
            spawn=SpawnConfig(pos_ne_m=START, airborne=True, alt_m=5.0, mode="LOITER"),
            sensor=RangeSensorConfig(messages=frozenset({"obstacle_distance"})),
        )
    )
    try:
        async with running(svc, sim):
            await gcs.recv_match(type="HEARTBEAT", timeout=HANG_S)
            await wait_state(svc, {State.IDLE}, 5.0)
            # the ground station's "Fly here": GUIDED first (as Mission Planner does), then the target
            gcs.send(
                gcs.mav.command_long_encode(1, 1, mavlink.MAV_CMD_DO_SET_MODE, 0, 1, CopterMode.GUIDED, 0, 0, 0, 0, 0)
            )
            await within(svc.clock.now, lambda: svc.handlers.mode_ok, 5.0, "GUIDED heard")
            lat, lon = ne_to_latlon(sim.cfg.home, TARGET[0], TARGET[1])
            gcs.send(
                gcs.mav.set_position_target_global_int_encode(
                    0, 1, 1, mavlink.MAV_FRAME_GLOBAL_RELATIVE_ALT_INT, MASK_POSITION,
                    round(lat * 1e7), round(lon * 1e7), -TARGET[2], 0, 0, 0, 0, 0, 0, 0, 0,
                )
            )  # fmt: skip
            await wait_state(svc, {State.NAVIGATING}, 10.0)
            route = svc.navigator.route
            assert route is not None and route.source == "autopilot-target"
            assert route.waypoints_ned_m[-1].tolist() == pytest.approx(list(TARGET), abs=0.05)
            state = await wait_state(svc, {State.ARRIVED, State.STUCK}, 120.0)
            res = sim.result()
    finally:
        await gcs.aclose()
    assert state is State.ARRIVED, svc.result()
    assert svc.counters.goals == 1  # its own echoes, hundreds of them, never became a goal
    assert svc.navigator.counters.planner_steps > 0
    assert not res["collided"]
    assert math.dist(res["final_pos_ned_m"][:2], TARGET[:2]) <= 0.7 + 0.3
    assert res["min_clearance_m"] >= 0.25  # flew around the pillar, not through it


async def test_global_target_report_is_placed_and_adopted_only_in_guided() -> None:
    """ArduCopter reports a guided destination in POSITION_TARGET_GLOBAL_INT: placed about GLOBAL_POSITION_INT,
    adopted in GUIDED only; a terrain-relative one cannot be placed and is left alone."""
    lat0, lon0 = -35.3632621, 149.1652374
    north_m = 10.0
    lat1 = lat0 + math.degrees(north_m / EARTH_RADIUS_M)
    async with rig(fast_config(goal={"adopt_autopilot_target": True})) as (svc, ap):
        mav = ap.link.mav
        gpi = mav.global_position_int_encode(0, round(lat0 * 1e7), round(lon0 * 1e7), 589_000, 5_000, 0, 0, 0, 0)

        def placed() -> bool:  # a reference needs a pose first: send until one was heard
            ap.link.send(gpi)
            return svc.handlers.global_ref is not None

        await within(svc.clock.now, placed, 5.0, "global reference")

        def report(frame: int) -> None:
            ap.link.send(
                mav.position_target_global_int_encode(
                    0, frame, MASK_POSITION, round(lat1 * 1e7), round(lon0 * 1e7), 5.0, 0, 0, 0, 0, 0, 0, 0, 0
                )
            )

        report(mavlink.MAV_FRAME_GLOBAL_RELATIVE_ALT_INT)  # in LOITER: not a command to us
        ap.custom_mode = int(CopterMode.GUIDED)
        await within(svc.clock.now, lambda: svc.handlers.mode_ok, 5.0, "GUIDED heard")
        assert svc.navigator.route is None
        report(mavlink.MAV_FRAME_GLOBAL_TERRAIN_ALT_INT)
        report(mavlink.MAV_FRAME_GLOBAL_RELATIVE_ALT_INT)
        await within(svc.clock.now, lambda: svc.navigator.route is not None, 5.0, "adopted")
        route = svc.navigator.route
        assert route is not None and route.source == "autopilot-target"
        assert route.waypoints_ned_m[-1].tolist() == pytest.approx([north_m, 0.0, -5.0], abs=0.01)
        assert svc.counters.goals == 1
