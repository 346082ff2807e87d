"""The heading commanded with the setpoints (``[autopilot] yaw``): the service flying the bundled simulator over
loopback MAVLink. PX4 keeps its heading when a setpoint's yaw is ignored, so with a range sensor of less than 360
degrees the service must turn the vehicle so that the sensor looks where it goes: the nose for a forward sensor, the
tail for a rear one (docs/service.md, "Heading")."""

from __future__ import annotations

import contextlib
import json
import math
from collections.abc import AsyncIterator
from typing import Any

import pytest

from apf_companion.autopilot import MASK_POS_VEL, MASK_POS_VEL_YAW, TypeMask
from apf_companion.config import ServiceConfig
from apf_companion.goal import Route
from apf_companion.navigator import State
from apf_companion.service import CompanionService
from apf_companion.status import encode_status_json
from sim.vehicle import RangeSensorConfig, SimConfig, Simulator, SpawnConfig
from sim.vehicle.dynamics import wrap_pi
from sim.vehicle.guided import Setpoint as SimSetpoint
from sim.world import World
from tests.conftest import HANG_S, SimulatorClock, until
from tests.service.test_service_flight import SPEEDUP, running, service_config

pytestmark = [pytest.mark.slow, pytest.mark.timeout(600)]

START = (3.0, 3.0)
EAST_GOAL = (3.0, 22.0, -5.0)  # due east of the start: outside a forward sensor's view at the start heading north
# Point obstacles across the way east (the paper's kind), so the path bends by more than the sensor's half-width.
FIELD = World.from_obstacles([(3.0, 8.0), (2.2, 12.5), (3.8, 12.5), (3.0, 17.0)], name="yaw-field")
# A forward-only sensor: 9 sectors of 10 deg, -45..+45 deg about the nose (a single lidar / depth camera).
FORWARD_ONLY = RangeSensorConfig(sectors=9, increment_deg=10.0, angle_offset_deg=-40.0)
# The same sensor facing the tail: 140..220 deg (135..225 with the sectors' widths), centred on 180.
REAR_ONLY = RangeSensorConfig(sectors=9, increment_deg=10.0, angle_offset_deg=140.0)
RIGHT_ONLY = RangeSensorConfig(sectors=9, increment_deg=10.0, angle_offset_deg=50.0)  # 45..135 deg, centred on 90


@contextlib.asynccontextmanager
async def yaw_flight(
    world: World, cfg: ServiceConfig, goal: tuple[float, float, float], *, profile: str, sensor: RangeSensorConfig
) -> AsyncIterator[tuple[CompanionService, Simulator]]:
    """Service and simulator on loopback; the vehicle hovers at 5 m over ``START`` heading north."""
    svc = await CompanionService.open(cfg, route=Route.point(*goal, source="test"), clock=SimulatorClock(SPEEDUP))
    assert svc.link is not None and svc.link.local_address is not None
    sim = await Simulator.start(
        SimConfig(
            links=[f"udpout:127.0.0.1:{svc.link.local_address[1]}"],
            profile=profile,
            world=world,
            speedup=SPEEDUP,
            seed=3,
            spawn=SpawnConfig(pos_ne_m=START, yaw_deg=0.0, airborne=True, alt_m=5.0),
            sensor=sensor,
        )
    )
    async with running(svc, sim):
        yield svc, sim


class SetpointLog:
    """The setpoints the simulated autopilot decoded (sampled as the flight runs) and its heading meanwhile."""

    def __init__(self, sim: Simulator) -> None:
        self.sim = sim
        self.setpoints: list[SimSetpoint] = []
        self.yaws_rad: list[float] = []

    def sample(self) -> None:
        sp = self.sim.engine.guided.sp
        if sp is not None and (not self.setpoints or self.setpoints[-1] is not sp):
            self.setpoints.append(sp)
        self.yaws_rad.append(self.sim.engine.state.yaw_rad)


async def fly_until(svc: CompanionService, log: SetpointLog, states: set[State], within_s: float) -> State:
    """Sample ``log`` until the navigator is in one of ``states`` or ``within_s`` SIMULATED seconds passed."""
    deadline_s = svc.clock.now() + within_s

    def done() -> bool:
        log.sample()
        return svc.navigator.state in states or svc.clock.now() > deadline_s

    await until(done, HANG_S * 10, f"a state in {states} or {within_s} simulated s")
    return svc.navigator.state


def _cfg(profile: str, **autopilot: Any) -> ServiceConfig:
    return service_config(profile=profile, autopilot=autopilot)


@pytest.mark.parametrize("profile", ["px4", "ardupilot"])
async def test_default_yaw_is_along_the_step_on_px4_and_none_on_ardupilot(profile: str) -> None:
    goal = (3.0, 12.0, -5.0)  # due east: bearing +90 deg
    async with yaw_flight(World.empty(), _cfg(profile), goal, profile=profile, sensor=RangeSensorConfig()) as (
        svc,
        sim,
    ):
        log = SetpointLog(sim)
        state = await fly_until(svc, log, {State.ARRIVED}, 120.0)
        assert state is State.ARRIVED, svc.result()
        arrived_hold = svc.navigator.last_output
    flown = [sp for sp in log.setpoints if sp.vel is not None and math.hypot(sp.vel[0], sp.vel[1]) > 0.1]
    assert len(flown) > 5
    assert arrived_hold is not None and arrived_hold.setpoint is not None
    if profile == "px4":
        assert all(sp.type_mask == MASK_POS_VEL_YAW for sp in flown)
        # Along the step: each yaw is the bearing of the setpoint's velocity feed-forward (east here).
        for sp in flown:
            assert sp.yaw is not None and sp.vel is not None
            assert abs(wrap_pi(sp.yaw - math.atan2(sp.vel[1], sp.vel[0]))) < math.radians(5.0)
        assert abs(wrap_pi(sim.engine.state.yaw_rad - math.pi / 2)) < math.radians(5.0)  # the vehicle turned
        # The hold at the goal keeps the last commanded yaw (no spin, no return to the autopilot's own).
        assert arrived_hold.setpoint.yaw_rad is not None
        assert abs(wrap_pi(arrived_hold.setpoint.yaw_rad - math.pi / 2)) < math.radians(5.0)
    else:
        assert all(sp.type_mask == MASK_POS_VEL for sp in flown)
        assert all(sp.yaw is None and sp.type_mask & TypeMask.YAW_IGNORE for sp in log.setpoints)  # brakes too
        assert arrived_hold.setpoint.yaw_rad is None


async def test_px4_turns_towards_a_commanded_yaw_at_mpc_yawrauto_max() -> None:
    """The simulator's PX4 turns at most MPC_YAWRAUTO_MAX (45 deg/s) towards the yaw it is sent, and its ATTITUDE
    carries the heading to the service (the pose the body-frame ranges are rotated with)."""
    goal = (3.0, 12.0, -5.0)
    async with yaw_flight(World.empty(), _cfg("px4"), goal, profile="px4", sensor=RangeSensorConfig()) as (svc, sim):
        log = SetpointLog(sim)
        rates: list[float] = []

        def turned() -> bool:
            log.sample()
            rates.append(abs(sim.engine.state.yaw_rate_rad_s))
            pose = svc.navigator.pose
            return pose is not None and abs(wrap_pi(pose.yaw_rad - math.pi / 2)) < math.radians(2.0)

        await until(turned, HANG_S * 5, "the service's pose facing east")
    assert max(rates) <= math.radians(45.0) + 1e-9
    assert max(rates) > math.radians(40.0)  # a 90 deg turn saturates the rate limit


@pytest.mark.parametrize(("yaw", "arrives"), [("auto", True), ("none", False)])
async def test_px4_forward_only_sensor_flies_round_obstacles_only_with_yaw(yaw: str, arrives: bool) -> None:
    cfg = _cfg("px4", yaw=yaw)
    async with yaw_flight(FIELD, cfg, EAST_GOAL, profile="px4", sensor=FORWARD_ONLY) as (svc, sim):
        log = SetpointLog(sim)
        state = await fly_until(svc, log, {State.ARRIVED, State.STUCK}, 150.0)
        res = sim.result()
        holds = svc.navigator.counters.unknown_direction_holds
        pos = sim.engine.state.pos_ned_m.copy()
    assert not res["collided"]
    if arrives:
        assert state is State.ARRIVED, svc.result()
        assert holds > 0  # it did turn in place to look before some steps
        assert math.dist(pos[:2], EAST_GOAL[:2]) <= 0.7 + 0.3
    else:
        assert state is not State.ARRIVED
        assert holds > 50  # every step east was refused: its sector never had ranges
        assert math.dist(pos[:2], START) < 1.0


@pytest.mark.parametrize(("sensor", "look_deg"), [(REAR_ONLY, 180.0), (RIGHT_ONLY, 90.0)], ids=["rear", "right"])
async def test_px4_sensor_off_the_nose_is_turned_to_look_where_the_vehicle_goes(
    sensor: RangeSensorConfig, look_deg: float
) -> None:
    """The look offset learnt from the ranges (180 deg for the rear sensor) turns the sensor along each step: the
    vehicle flies round the obstacles tail (or left side) first and arrives. Turning the nose instead (the code
    before the look offset) held at the start until STUCK: every step's sector stayed without ranges (measured in
    docs/service.md, "Heading")."""
    async with yaw_flight(FIELD, _cfg("px4"), EAST_GOAL, profile="px4", sensor=sensor) as (svc, sim):
        log = SetpointLog(sim)
        state = await fly_until(svc, log, {State.ARRIVED, State.STUCK}, 150.0)
        res = sim.result()
        offset = svc.perception.look_offset_rad(svc.clock.now())
        reported_deg = json.loads(encode_status_json(svc.reporter.status_dict(svc.clock.now())))["sensor_look_deg"]
        pos = sim.engine.state.pos_ned_m.copy()
    assert not res["collided"]
    assert state is State.ARRIVED, svc.result()
    assert math.dist(pos[:2], EAST_GOAL[:2]) <= 0.7 + 0.3
    look = math.radians(look_deg)
    assert abs(wrap_pi(offset - look)) < math.radians(1.0)
    assert abs(wrap_pi(math.radians(reported_deg) - look)) < math.radians(1.0)  # the status topic says it too
    flown = [sp for sp in log.setpoints if sp.vel is not None and math.hypot(sp.vel[0], sp.vel[1]) > 0.1]
    assert len(flown) > 5
    # The sensor ahead: each yaw is the bearing of the setpoint's feed-forward less the look offset.
    for sp in flown:
        assert sp.yaw is not None and sp.vel is not None
        assert abs(wrap_pi(sp.yaw + look - math.atan2(sp.vel[1], sp.vel[0]))) < math.radians(5.0)
