"""A PX4 EKF2 position reset in flight: the bundled simulator's PX4 profile over loopback MAVLink
(sim.vehicle.ekfreset: the reported local position jumps, the vehicle does not, setpoints are flown in the new
frame). What the service must do (docs/hardening.md, "EKF reset"): forget the obstacles remembered in the old frame,
never fly an old-frame hold point or step in the new one, hold and say so, count it, then navigate on."""

from __future__ import annotations

import contextlib
import math
from collections.abc import AsyncIterator

import numpy as np
import pytest

from apf_companion.config import ServiceConfig
from apf_companion.goal import Route
from apf_companion.navigator import State
from apf_companion.service import CompanionService
from sim.vehicle import SimConfig, Simulator, SpawnConfig
from sim.world import World
from tests.conftest import HANG_S, SimulatorClock, until
from tests.service.test_service_flight import SPEEDUP, running, service_config

pytestmark = [pytest.mark.slow, pytest.mark.timeout(600)]

START = (3.0, 3.0)
GOAL = (28.0, 3.0, -5.0)  # due north
# Posts beside the way north (east of it): seen and remembered before the reset.
WORLD = World.from_obstacles([(8.0, 7.0), (14.0, 7.5), (20.0, 7.0)], name="reset-posts")
DELTA_NE = (0.0, 4.0)  # the estimate jumps 4 m east (a GPS glitch recovery)


@contextlib.asynccontextmanager
async def px4_flight(cfg: ServiceConfig, **sim_kw: object) -> AsyncIterator[tuple[CompanionService, Simulator]]:
    svc = await CompanionService.open(cfg, route=Route.point(*GOAL, source="test"), clock=SimulatorClock(SPEEDUP))
    assert svc.link is not None and svc.link.local_address is not None
    sim = await Simulator.start(
        SimConfig(
            links=[f"udpout:127.0.0.1:{svc.link.local_address[1]}"],
            profile="px4",
            world=WORLD,
            speedup=SPEEDUP,
            seed=5,
            spawn=SpawnConfig(pos_ne_m=START, yaw_deg=0.0, airborne=True, alt_m=5.0),
            **sim_kw,  # type: ignore[arg-type]
        )
    )
    async with running(svc, sim):
        yield svc, sim


def _stale_points(svc: CompanionService, sim: Simulator) -> int:
    """Remembered points (local NED, the estimate's frame) that lie on no obstacle once put back in the truth."""
    offset = sim.engine.estimator.offset_ned_m
    pts = svc.perception.points(svc.clock.now())
    return sum(1 for p in pts if WORLD.clearance_m(p[:2] - offset[:2]) > 0.5)


async def test_a_position_reset_seen_only_in_local_position_ned_forgets_the_old_frame_and_holds() -> None:
    """No ODOMETRY: the 4 m jump is rejected until ``pose_reset_samples`` consistent poses re-anchor. Meanwhile the
    old anchor is unconfirmed from half of them on (brake, no position), so the vehicle is not flown 4 m west to an
    old-frame point."""
    async with px4_flight(service_config(profile="px4")) as (svc, sim):
        eng = sim.engine
        await until(lambda: eng.state.pos_ned_m[0] > 9.0, HANG_S * 5, "flying north past the first post")
        assert len(svc.perception) > 0 and _stale_points(svc, sim) == 0
        east_at_reset = float(eng.state.pos_ned_m[1])
        texts_before = svc.outbox.statustexts_sent
        eng.estimator_position_reset(DELTA_NE)
        easts: list[float] = []

        def re_anchored() -> bool:
            easts.append(float(eng.state.pos_ned_m[1]))
            return svc.perception.counters.pose_resets >= 1

        await until(re_anchored, HANG_S * 5, "re-anchored on the new frame")
        assert _stale_points(svc, sim) == 0  # the old frame's points are gone
        hold_end_s = svc.clock.now() + svc.config.safety.reset_hold_s
        states: set[State] = set()

        def held() -> bool:
            easts.append(float(eng.state.pos_ned_m[1]))
            states.add(svc.navigator.state)
            sp = eng.guided.sp  # flown in the truth (the setpoint's position less the offset)
            if sp is not None and sp.pos is not None:
                assert math.dist(sp.pos[:2], eng.state.pos_ned_m[:2]) < 1.5  # never an old-frame point
            return svc.clock.now() > hold_end_s

        await until(held, HANG_S * 5, "the reset's hold")
        # It braked while the new frame was rejected: without that (the old anchor confirmed) the old-frame steps
        # pulled it 0.60 m west before the re-anchor, measured; braking from the 5th rejected pose, 0.14 m.
        assert max(abs(e - east_at_reset) for e in easts) < 0.25
        c = svc.perception.counters
        assert (c.pose_resets, c.estimator_resets) == (1, 0)
        assert State.HOLDING in states and svc.outbox.statustexts_sent > texts_before  # "HOLDING: position reset"
        assert svc.reporter.status_dict(svc.clock.now())["counters"]["pose_resets"] == 1
        # It navigates on in the new frame, with a memory of the new frame only.
        state = await _fly_on(svc, sim)
        assert state is State.ARRIVED, svc.result()


async def test_a_small_reset_announced_by_odometry_forgets_the_memory_at_the_next_pose() -> None:
    """With ODOMETRY streamed (PX4's onboard mode does, 30 Hz), a reset of 0.25 m, within the gate's reach, is known
    by its reset_counter: the memory of the old frame is dropped at the next pose, counted, and navigation goes on."""
    async with px4_flight(service_config(profile="px4"), rates_hz={"ODOMETRY": 10.0}) as (svc, sim):
        eng = sim.engine
        await until(lambda: eng.state.pos_ned_m[0] > 9.0, HANG_S * 5, "flying north past the first post")
        assert len(svc.perception) > 0
        eng.estimator_position_reset((0.0, 0.25))
        await until(lambda: svc.perception.counters.estimator_resets == 1, HANG_S * 5, "the counter change read")
        await until(lambda: svc.perception.counters.pose_resets == 1, HANG_S * 5, "the memory forgotten")
        assert svc.perception.counters.implausible_poses == 0  # within reach: accepted, yet not silently kept
        state = await _fly_on(svc, sim)
        assert state is State.ARRIVED, svc.result()
        assert svc.perception.counters.pose_resets == 1


async def _fly_on(svc: CompanionService, sim: Simulator) -> State:
    stale: list[int] = []

    def done() -> bool:
        stale.append(_stale_points(svc, sim))
        return svc.navigator.state in (State.ARRIVED, State.STUCK)

    await until(done, HANG_S * 10, "ARRIVED or STUCK")
    assert max(stale) == 0
    return svc.navigator.state


def test_the_reset_is_the_px4_profiles_only() -> None:
    from sim.vehicle.config import EngineConfig
    from sim.vehicle.engine import VehicleEngine

    eng = VehicleEngine(EngineConfig(), n_links=1, emit=lambda link, msg: None)
    with pytest.raises(ValueError, match="PX4"):
        eng.estimator_position_reset((1.0, 0.0))
    assert np.all(eng.estimator.offset_ned_m == 0.0)
