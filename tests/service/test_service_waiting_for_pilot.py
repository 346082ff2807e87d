"""``autopilot.takeover = false``: a goal waits for the pilot to switch to GUIDED (ArduPilot) / OFFBOARD (PX4).

The state says so (WAITING_FOR_PILOT, one STATUSTEXT naming the mode), never NAVIGATING before the switch; what is
sent meanwhile is a hold at the current position (PX4 needs the stream to accept OFFBOARD), counted apart from
navigation and planner steps; the HEARTBEAT that shows the mode starts the flight (NAVIGATING, one STATUSTEXT).

The navigator alone on an injected clock first; then the service over loopback UDP, against a scripted autopilot
(every STATUSTEXT on the wire) and against the bundled simulator, switched by a ground station's DO_SET_MODE.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np
import pytest
from pymavlink.dialects.v20 import ardupilotmega as mavlink

from apf_companion.autopilot import MASK_POSITION, PX4_OFFBOARD, CopterMode, Px4MainMode, Px4Mode
from apf_companion.config import ServiceConfig, config_from_mapping
from apf_companion.goal import Route
from apf_companion.links import MavlinkLink
from apf_companion.navigator import Navigator, State, StateChange
from apf_companion.observe import CycleSnapshot
from apf_companion.perception import Pose
from apf_companion.service import CompanionService
from apf_companion.setpoint import SetpointKind
from apf_companion.status import STATUSTEXT_MAX, severity_for, statustext_for, system_status_for
from sim.vehicle import RangeSensorConfig, SimConfig, Simulator, SpawnConfig
from sim.vehicle.testing import command_long
from sim.world import World
from tests.conftest import HANG_S, SimulatorClock, until, within
from tests.service import test_service_flight as flights
from tests.service.test_service_flight import running, wait_state
from tests.service.test_service_mavlink import fast_config, rig
from tests.service.test_service_navigator import feed, make, scan

pytestmark = pytest.mark.timeout(600)

MODE = {"ardupilot": "GUIDED", "px4": "OFFBOARD"}
NO_POSE = "no pose yet (no LOCAL_POSITION_NED)"


def pilot_nav(profile: str = "ardupilot") -> Navigator:
    return make(config_from_mapping({"autopilot": {"profile": profile, "takeover": False}}))


def inputs(nav: Navigator, t: float, pos: tuple[float, float, float], *, mode_ok: bool, ranges: bool = True) -> None:
    """One tick of what the autopilot sends: HEARTBEAT (its mode), a pose, and (``ranges``) an empty scan."""
    nav.autopilot_heartbeat(t, mode_ok=mode_ok)
    nav.update_pose(Pose(t_s=t, pos_ned_m=np.array(pos), yaw_rad=0.0))
    if ranges:
        scan(nav, np.zeros((0, 3)), t)


@pytest.mark.parametrize("profile", ["ardupilot", "px4"])
def test_a_goal_waits_for_the_pilot_then_flies_when_the_mode_is_switched(profile: str) -> None:
    nav = pilot_nav(profile)
    inputs(nav, 0.0, (1.0, 2.0, -5.0), mode_ok=False)
    assert nav.set_route(Route.point(10.0, 2.0, -5.0, source="test"), 0.0)
    changes: list[StateChange] = nav.drain_changes()
    t = 0.0
    for k in range(1, 31):  # 3 s; the pilot flies the vehicle north meanwhile (LOITER / POSCTL)
        t = 0.1 * k
        here = (1.0 + 0.05 * k, 2.0, -5.0)
        inputs(nav, t, here, mode_ok=False)
        out = nav.cycle(t)
        changes += out.changes
        assert out.state is State.WAITING_FOR_PILOT
        # a hold where the vehicle is now (not where it was): PX4's proof of life, no motion of ours
        assert out.setpoint is not None and out.setpoint.kind is SetpointKind.PRESTREAM
        assert out.setpoint.pos_ned_m == here and out.setpoint.vel_ned_m_s == (0.0, 0.0, 0.0)
        assert out.decision is None and out.distance_to_goal_m == pytest.approx(10.0 - here[0])
    mode = MODE[profile]
    assert [(c.old, c.new, c.reason) for c in changes] == [
        (State.IDLE, State.WAITING_FOR_PILOT, f"switch to {mode} to fly")
    ]  # one STATUSTEXT, when the wait starts
    text = statustext_for(State.WAITING_FOR_PILOT, changes[0].reason)
    assert text == f"APF WAITING_FOR_PILOT: switch to {mode} to fly" and len(text) <= STATUSTEXT_MAX
    counts = nav.counts()
    assert counts["planner_steps"] == 0 and counts["prestream_setpoints"] == counts["setpoints"] == 30
    # the pilot switches: NAVIGATING from that HEARTBEAT on, the planner's first step in the next cycle
    nav.autopilot_heartbeat(t + 0.05, mode_ok=True)
    switched = nav.drain_changes()
    assert [(c.new, c.reason) for c in switched] == [(State.NAVIGATING, f"in {mode}, flying to the goal")]
    inputs(nav, t + 0.1, (2.5, 2.0, -5.0), mode_ok=True)
    out = nav.cycle(t + 0.1)
    assert out.state is State.NAVIGATING and not out.changes
    assert out.setpoint is not None and out.setpoint.kind is SetpointKind.NAVIGATE
    assert nav.counts()["planner_steps"] == 1 and nav.counts()["prestream_setpoints"] == 30


@pytest.mark.parametrize("profile", ["ardupilot", "px4"])
def test_a_px4_failsafe_keeps_the_wait_silent_and_says_so(profile: str) -> None:
    """PX4 ends an offboard-loss failsafe into OFFBOARD when setpoints come (failsafe.cpp ``checkModeFallback``):
    while its HEARTBEAT says CRITICAL, no holds; once the pilot's mode change ends the failsafe, the holds. ArduCopter
    drops setpoints outside GUIDED, so its holds go on."""
    nav = pilot_nav(profile)
    nav.autopilot_heartbeat(0.0, mode_ok=False, failsafe=True)
    nav.update_pose(Pose(t_s=0.0, pos_ned_m=np.array([0.0, 0.0, -5.0]), yaw_rad=0.0))
    assert nav.set_route(Route.point(10.0, 0.0, -5.0, source="test"), 0.0)
    changes = nav.drain_changes()
    sent = 0
    for k in range(1, 21):  # 2 s in the failsafe
        t = 0.1 * k
        nav.autopilot_heartbeat(t, mode_ok=False, failsafe=True)
        nav.update_pose(Pose(t_s=t, pos_ned_m=np.array([0.0, 0.0, -5.0]), yaw_rad=0.0))
        out = nav.cycle(t)
        changes += out.changes
        sent += out.setpoint is not None
        assert out.state is State.WAITING_FOR_PILOT
    reasons = [c.reason for c in changes]
    if profile == "ardupilot":
        assert sent == 20 and reasons == ["switch to GUIDED to fly"]
        return
    assert sent == 0 and reasons == ["switch to OFFBOARD to fly", "failsafe: switch mode first"]
    nav.autopilot_heartbeat(2.1, mode_ok=False, failsafe=False)  # the pilot picked Hold: failsafe over
    nav.update_pose(Pose(t_s=2.1, pos_ned_m=np.array([0.0, 0.0, -5.0]), yaw_rad=0.0))
    out = nav.cycle(2.1)
    assert out.setpoint is not None and out.setpoint.kind is SetpointKind.PRESTREAM
    assert [c.reason for c in out.changes] == ["switch to OFFBOARD to fly"]
    text = statustext_for(State.WAITING_FOR_PILOT, "failsafe: switch mode first")
    assert len(text) <= STATUSTEXT_MAX


def test_waiting_is_reported_as_standby_and_a_notice() -> None:
    """Not in control and nothing wrong: STANDBY in our HEARTBEAT (not CRITICAL as HOLDING), a NOTICE text."""
    assert system_status_for(State.WAITING_FOR_PILOT, healthy_inputs=True) == mavlink.MAV_STATE_STANDBY
    assert system_status_for(State.WAITING_FOR_PILOT, healthy_inputs=False) == mavlink.MAV_STATE_STANDBY
    assert severity_for(State.WAITING_FOR_PILOT) == mavlink.MAV_SEVERITY_NOTICE


def test_with_takeover_the_goal_is_navigating_at_once() -> None:
    """The takeover path is unchanged: the service switches the mode itself, NAVIGATING streaming the holds."""
    nav = make()
    inputs(nav, 0.0, (0.0, 0.0, -5.0), mode_ok=False)
    assert nav.set_route(Route.point(10.0, 0.0, -5.0, source="test"), 0.0)
    assert [c.new for c in nav.drain_changes()] == [State.NAVIGATING]
    out = nav.cycle(0.1)
    assert out.state is State.NAVIGATING and out.setpoint is not None
    assert out.setpoint.kind is SetpointKind.PRESTREAM


def test_in_guided_already_the_goal_is_flown_at_once() -> None:
    nav = pilot_nav()
    feed(nav, 0.0, (0.0, 0.0, -5.0))  # HEARTBEAT in GUIDED
    assert nav.set_route(Route.point(10.0, 0.0, -5.0, source="test"), 0.0)
    assert [c.new for c in nav.drain_changes()] == [State.NAVIGATING]
    out = nav.cycle(0.1)
    assert out.setpoint is not None and out.setpoint.kind is SetpointKind.NAVIGATE


def test_a_goal_before_the_first_pose_holds_then_waits_for_the_pilot() -> None:
    """No pose: HOLDING says why (nothing can be streamed, PX4 would refuse OFFBOARD); with a pose the wait starts,
    whatever the ranges (a hold at the vehicle's position needs none); once switched, stale ranges hold."""
    nav = pilot_nav()
    nav.autopilot_heartbeat(0.0, mode_ok=False)
    assert nav.set_route(Route.point(10.0, 0.0, -5.0, source="test"), 0.0)
    out = nav.cycle(0.1)
    assert [(c.new, c.reason) for c in [*nav.drain_changes(), *out.changes]] == [(State.HOLDING, NO_POSE)]
    assert out.setpoint is None
    new: list[StateChange] = []
    for k in range(2, 12):
        t = 0.1 * k
        inputs(nav, t, (0.0, 0.0, -5.0), mode_ok=False, ranges=False)
        out = nav.cycle(t)
        new += out.changes
        assert out.state is State.WAITING_FOR_PILOT
        assert out.setpoint is not None and out.setpoint.kind is SetpointKind.PRESTREAM
    assert [(c.old, c.new) for c in new] == [(State.HOLDING, State.WAITING_FOR_PILOT)]
    inputs(nav, 1.25, (0.0, 0.0, -5.0), mode_ok=True, ranges=False)
    out = nav.cycle(1.25)
    assert [c.new for c in out.changes] == [State.NAVIGATING, State.HOLDING]
    assert out.changes[-1].reason == "no ranges yet: holding position"
    assert out.setpoint is not None and out.setpoint.kind is SetpointKind.HOLD


def test_a_stale_pose_while_waiting_sends_nothing_and_keeps_waiting() -> None:
    nav = pilot_nav()
    inputs(nav, 0.0, (0.0, 0.0, -5.0), mode_ok=False)
    nav.set_route(Route.point(10.0, 0.0, -5.0, source="test"), 0.0)
    nav.drain_changes()
    for k in range(1, 11):  # heartbeats and ranges go on, the pose stops
        t = 0.1 * k
        nav.autopilot_heartbeat(t, mode_ok=False)
        scan(nav, np.zeros((0, 3)), t)
        out = nav.cycle(t)
        assert out.state is State.WAITING_FOR_PILOT and not out.changes
        assert (out.setpoint is None) == (t > nav.params.pose_max_age_s)


def test_the_link_back_without_the_mode_waits_for_the_pilot_again() -> None:
    """LINK_LOST keeps the goal; when the heartbeat returns still not in GUIDED, the pilot is asked again (it used to
    say "taking over again" and NAVIGATING)."""
    nav = pilot_nav()
    inputs(nav, 0.0, (0.0, 0.0, -5.0), mode_ok=False)
    nav.set_route(Route.point(10.0, 0.0, -5.0, source="test"), 0.0)
    nav.cycle(0.0)
    t = 0.0
    for _ in range(40):  # pose and ranges keep coming, the heartbeat does not
        t += 0.1
        nav.update_pose(Pose(t_s=t, pos_ned_m=np.array([0.0, 0.0, -5.0]), yaw_rad=0.0))
        scan(nav, np.zeros((0, 3)), t)
        out = nav.cycle(t)
    assert out.state is State.LINK_LOST and nav.route is not None
    t += 0.1
    inputs(nav, t, (0.0, 0.0, -5.0), mode_ok=False)
    out = nav.cycle(t)
    assert [(c.new, c.reason) for c in out.changes] == [(State.WAITING_FOR_PILOT, "switch to GUIDED to fly")]
    assert out.setpoint is not None and out.setpoint.kind is SetpointKind.PRESTREAM


def test_the_pilot_leaving_guided_after_the_switch_drops_the_goal() -> None:
    """Once the mode was seen for the goal, the pilot override rule holds as with a takeover: IDLE, never fought."""
    nav = pilot_nav()
    inputs(nav, 0.0, (0.0, 0.0, -5.0), mode_ok=False)
    nav.set_route(Route.point(10.0, 0.0, -5.0, source="test"), 0.0)
    nav.autopilot_heartbeat(0.1, mode_ok=True)
    assert nav.state is State.NAVIGATING
    nav.autopilot_heartbeat(0.2, mode_ok=False)
    assert (nav.state, nav.route) == (State.IDLE, None)
    assert nav.cycle(0.2).setpoint is None


# ---- the service over loopback -----------------------------------------------------------------------------------
def state_texts(ap: Any) -> list[str]:
    """The STATUSTEXTs announcing a state (``APF <STATE>: <reason>``) the scripted autopilot received."""
    return [m.text for m in ap.of_type("STATUSTEXT") if m.text.startswith("APF ")]


async def test_the_wire_says_waiting_once_then_navigating_after_the_switch() -> None:
    """Against the scripted autopilot (LOITER): the STATUSTEXTs and HEARTBEATs the service sends, and no DO_SET_MODE.
    The goal comes once the pose is known (as from zenoh or a ground station), so its STATUSTEXT is the first."""
    cfg = fast_config(autopilot={"takeover": False})
    async with rig(cfg) as (svc, ap):
        await within(svc.clock.now, lambda: svc.navigator.pose is not None, 5.0, "a pose")
        assert svc.admission.admit(Route.point(3.0, 0.0, -5.0, source="test"), svc.clock.now())
        await within(svc.clock.now, lambda: svc.navigator.counters.prestream_setpoints >= 20, 10.0, "holds streamed")
        heartbeats = len(ap.of_type("HEARTBEAT"))
        await within(svc.clock.now, lambda: len(ap.of_type("HEARTBEAT")) > heartbeats, 3.0, "a HEARTBEAT")
        assert ap.of_type("HEARTBEAT")[-1].system_status == mavlink.MAV_STATE_STANDBY  # not ACTIVE: not in control
        status = svc.reporter.status_dict(svc.clock.now())
        assert status["state"] == "WAITING_FOR_PILOT" and status["reason"] == "switch to GUIDED to fly"
        assert status["counters"]["nav_planner_steps"] == 0 and status["decision"] is None
        assert status["counters"]["nav_prestream_setpoints"] >= 20
        assert state_texts(ap) == ["APF WAITING_FOR_PILOT: switch to GUIDED to fly"]
        assert not [m for m in ap.of_type("COMMAND_LONG") if m.command == mavlink.MAV_CMD_DO_SET_MODE]
        assert all(m.x == 0.0 and m.y == 0.0 for _, m in ap.setpoints())  # holds where it is
        ap.custom_mode = int(CopterMode.GUIDED)  # the pilot switches
        await within(svc.clock.now, lambda: svc.navigator.state is State.ARRIVED, 20.0, "arrived")
        await within(svc.clock.now, lambda: len(state_texts(ap)) >= 3, 2.0, "the ARRIVED text")
        texts = state_texts(ap)
        assert texts[:2] == [
            "APF WAITING_FOR_PILOT: switch to GUIDED to fly",
            "APF NAVIGATING: in GUIDED, flying to the goal",
        ]
        assert texts[2].startswith("APF ARRIVED")
        assert svc.reporter.counters.mode_requests == 0


class StateLog:
    """A read-only cycle observer: every state change the service reported (each became a STATUSTEXT)."""

    def __init__(self) -> None:
        self.changes: list[StateChange] = []

    def on_cycle(self, snap: CycleSnapshot) -> None:
        self.changes += snap.out.changes

    def close(self) -> None:
        pass


def _set_mode_params(profile: str) -> tuple[float, ...]:
    """DO_SET_MODE as a ground station sends it: custom mode enabled, GUIDED (ArduCopter) / OFFBOARD (PX4)."""
    flag = float(mavlink.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED)
    if profile == "ardupilot":
        return (flag, float(CopterMode.GUIDED))
    return (flag, float(PX4_OFFBOARD.main), float(PX4_OFFBOARD.sub))


def _pilot_config(profile: str) -> ServiceConfig:
    return flights.service_config(profile, autopilot={"takeover": False})


@pytest.mark.slow
@pytest.mark.parametrize("profile", ["ardupilot", "px4"])
async def test_the_simulated_vehicle_waits_for_the_ground_station_then_flies(profile: str) -> None:
    """The bundled simulator hovers in LOITER / AUTO.LOITER; the service waits (no NAVIGATING, no mode request, no
    motion, no flight time); a ground station's DO_SET_MODE switches it (PX4 accepts OFFBOARD only because the
    holds stream) and the vehicle flies to the goal."""
    goal = (8.0, 3.0, -5.0)
    svc = await CompanionService.open(
        _pilot_config(profile), route=Route.point(*goal, source="test"), clock=SimulatorClock(flights.SPEEDUP)
    )
    log = StateLog()
    svc.observers.add([log])
    gcs = await MavlinkLink.open("udpin:127.0.0.1:0", source_system=255, source_component=190)
    assert svc.link is not None and svc.link.local_address is not None and gcs.local_address is not None
    sim = await Simulator.start(
        SimConfig(
            links=[f"udpout:127.0.0.1:{svc.link.local_address[1]}", f"udpout:127.0.0.1:{gcs.local_address[1]}"],
            profile=profile,
            world=World.empty(),
            speedup=flights.SPEEDUP,
            seed=3,
            spawn=SpawnConfig(pos_ne_m=(3.0, 3.0), airborne=True, alt_m=5.0, mode="LOITER"),
            sensor=RangeSensorConfig(messages=frozenset({"obstacle_distance"})),
        )
    )
    try:
        async with running(svc, sim):
            await gcs.recv_match(type="HEARTBEAT", timeout=HANG_S)
            await until(lambda: svc.navigator.counters.prestream_setpoints >= 30, what="3 s of holds streamed")
            now = svc.clock.now()
            status: dict[str, Any] = svc.reporter.status_dict(now)
            assert (status["state"], status["reason"]) == ("WAITING_FOR_PILOT", f"switch to {MODE[profile]} to fly")
            # the goal given at start is taken at the first HEARTBEAT: HOLDING until the first pose, if it is later
            assert [c.new for c in log.changes if c.reason != NO_POSE] == [State.WAITING_FOR_PILOT]
            assert svc.reporter.counters.mode_requests == 0 and svc.navigator.counters.planner_steps == 0
            assert svc.flight.flown_s(now) is None  # the holds are no flight
            assert sim.vehicle.mode == ("LOITER" if profile == "ardupilot" else "AUTO.LOITER")
            assert math.dist(sim.vehicle.pos_ned_m[:2], (3.0, 3.0)) < 0.3
            switched_at = svc.clock.now()
            texts: list[str] = []
            ack = await command_long(gcs, mavlink.MAV_CMD_DO_SET_MODE, *_set_mode_params(profile), texts=texts)
            assert ack.result == mavlink.MAV_RESULT_ACCEPTED, texts
            state = await wait_state(svc, {State.ARRIVED, State.STUCK, State.IDLE}, 120.0)
            flown_s = svc.flight.flown_s(svc.clock.now())
            custom_mode = sim.vehicle.custom_mode
            res = sim.result()
    finally:
        await gcs.aclose()
    assert state is State.ARRIVED, svc.result()
    changes = [c for c in log.changes if c.reason != NO_POSE]
    assert [c.new for c in changes] == [State.WAITING_FOR_PILOT, State.NAVIGATING, State.ARRIVED]
    assert changes[1].reason == f"in {MODE[profile]}, flying to the goal"
    assert svc.reporter.counters.mode_requests == 0 and svc.navigator.counters.planner_steps > 5
    assert flown_s is not None and flown_s <= svc.clock.now() - switched_at  # counted from the switch on
    if profile == "ardupilot":
        assert custom_mode == CopterMode.GUIDED
    else:
        assert Px4Mode.from_custom_mode(custom_mode).main == Px4MainMode.OFFBOARD
    assert math.dist(res["final_pos_ned_m"][:2], goal[:2]) <= 0.7 + 0.3


@pytest.mark.slow
async def test_px4_after_an_offboard_loss_failsafe_the_wait_streams_nothing_until_the_pilot_picks_a_mode() -> None:
    """PX4 leaves its offboard-loss failsafe for OFFBOARD by itself once setpoints come back (failsafe.cpp
    ``checkModeFallback``; the simulator's PX4 profile does too): holds streamed while waiting would have taken the
    vehicle back into OFFBOARD, and the service would have flown the goal with no pilot's switch. While the
    HEARTBEAT says CRITICAL the wait is silent and says why; the pilot's Hold ends the failsafe, the holds start,
    and the pilot's OFFBOARD starts the flight."""
    svc = await CompanionService.open(_pilot_config("px4"), clock=SimulatorClock(flights.SPEEDUP))
    gcs = await MavlinkLink.open("udpin:127.0.0.1:0", source_system=255, source_component=190)
    assert svc.link is not None and svc.link.local_address is not None and gcs.local_address is not None
    sim = await Simulator.start(
        SimConfig(
            links=[f"udpout:127.0.0.1:{svc.link.local_address[1]}", f"udpout:127.0.0.1:{gcs.local_address[1]}"],
            profile="px4",
            world=World.empty(),
            speedup=flights.SPEEDUP,
            seed=3,
            spawn=SpawnConfig(pos_ne_m=(3.0, 3.0), airborne=True, alt_m=5.0, mode="LOITER"),
            sensor=RangeSensorConfig(messages=frozenset({"obstacle_distance"})),
        )
    )
    nav = svc.navigator
    try:
        async with running(svc, sim):
            # a ground station's one setpoint and OFFBOARD, then silence: the offboard-loss failsafe (Hold) 1 s later
            await gcs.recv_match(type="HEARTBEAT", timeout=HANG_S)
            frame = mavlink.MAV_FRAME_LOCAL_NED
            gcs.send(
                gcs.mav.set_position_target_local_ned_encode(0, 1, 1, frame, MASK_POSITION, 0.0, 0.0, -5.0, *[0.0] * 8)
            )
            ack = await command_long(gcs, mavlink.MAV_CMD_DO_SET_MODE, *_set_mode_params("px4"))
            assert ack.result == mavlink.MAV_RESULT_ACCEPTED
            await gcs.recv_match(type="STATUSTEXT", condition=lambda t: "Failsafe" in t.text, timeout=HANG_S)
            failsafe = lambda: sim.vehicle.mode == "AUTO.LOITER" and not nav.mode_ok and nav.pose is not None  # noqa: E731
            await until(failsafe, what="the failsafe's HEARTBEAT (Hold, CRITICAL) seen, and a pose")
            assert svc.admission.admit(Route.point(8.0, 3.0, -5.0, source="test"), svc.clock.now())
            cycles = nav.counters.cycles
            await until(lambda: nav.counters.cycles >= cycles + 30, what="3 s of waiting")
            status: dict[str, Any] = svc.reporter.status_dict(svc.clock.now())
            assert (status["state"], status["reason"]) == ("WAITING_FOR_PILOT", "failsafe: switch mode first")
            assert nav.counters.prestream_setpoints == nav.counters.setpoints == 0
            assert sim.vehicle.mode == "AUTO.LOITER"
            # the pilot picks Hold (ends the failsafe), then OFFBOARD once the holds stream
            ack = await command_long(gcs, mavlink.MAV_CMD_DO_SET_MODE, 1.0, 4.0, 3.0)
            assert ack.result == mavlink.MAV_RESULT_ACCEPTED
            await until(lambda: nav.counters.prestream_setpoints >= 15, what="holds streamed")
            assert nav.state is State.WAITING_FOR_PILOT and sim.vehicle.mode == "AUTO.LOITER"
            ack = await command_long(gcs, mavlink.MAV_CMD_DO_SET_MODE, *_set_mode_params("px4"))
            assert ack.result == mavlink.MAV_RESULT_ACCEPTED
            await until(lambda: nav.state is State.NAVIGATING, what="NAVIGATING at the pilot's switch")
    finally:
        await gcs.aclose()
