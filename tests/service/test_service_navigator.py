"""The pure decision core driven by a fake clock: states, freshness, holds, silence."""

from __future__ import annotations

import itertools
import math

import numpy as np
import pytest

from apf_companion.autopilot import MASK_POS_VEL
from apf_companion.builders import build_navigator
from apf_companion.config import ServiceConfig, config_from_mapping
from apf_companion.goal import Route
from apf_companion.navigator import Navigator, State
from apf_companion.observe import Observers, PlanTap
from apf_companion.perception import PerceptionFrontEnd, PerceptionParams, Pose
from apf_companion.planning import GiveUp, PlannerParams, get_planner
from apf_companion.reporter import FaultLog, ServiceCounters
from apf_companion.service import build_planner
from apf_companion.setpoint import SetpointKind
from apf_companion.status import STATUSTEXT_MAX, statustext_for


def make(cfg: ServiceConfig | None = None, *, tapped: bool = False) -> Navigator:
    """``tapped``: the planner behind the service's ``PlanTap``, as the service builds it."""
    cfg = cfg or ServiceConfig()
    perception = PerceptionFrontEnd(PerceptionParams(memory_expiry_s=30.0, merge_radius_m=0.1))
    planner = build_planner(cfg)
    nav = build_navigator(cfg, PlanTap(planner) if tapped else planner, perception)
    nav.rng = np.random.default_rng(1)
    return nav


def scan(nav: Navigator, points_ned_m: np.ndarray, t: float) -> None:
    """A scan's placed points, written by the memory's one writer (the perception front end)."""
    assert isinstance(nav.obstacles, PerceptionFrontEnd)
    nav.obstacles.remember(points_ned_m, t)


def feed(nav: Navigator, t: float, pos: tuple[float, float, float], *, ranges: bool = True) -> None:
    nav.autopilot_heartbeat(t, mode_ok=True)
    nav.update_pose(Pose(t_s=t, pos_ned_m=np.array(pos), yaw_rad=0.0))
    if ranges:
        scan(nav, np.zeros((0, 3)), t)


def fly(nav: Navigator, t0: float, pos: np.ndarray, n: int, dt: float = 0.1) -> tuple[float, np.ndarray]:
    """Let the vehicle jump to each commanded position (a perfect tracker)."""
    t = t0
    for _ in range(n):
        t += dt
        feed(nav, t, (pos[0], pos[1], pos[2]))
        out = nav.cycle(t)
        if out.setpoint is not None:
            pos = np.array(out.setpoint.pos_ned_m)
        if nav.state is not State.NAVIGATING:
            break
    return t, pos


def test_idle_without_goal_sends_nothing() -> None:
    nav = make()
    feed(nav, 0.1, (0, 0, -5))
    out = nav.cycle(0.1)
    assert out.state is State.IDLE and out.setpoint is None


def test_flies_to_goal_and_arrives_with_holds() -> None:
    nav = make()
    feed(nav, 0.1, (0, 0, -5))
    assert nav.set_route(Route.point(5.0, 3.0, None, source="test"), 0.1)
    t, pos = fly(nav, 0.1, np.array([0.0, 0.0, -5.0]), 200)
    assert nav.state is State.ARRIVED
    assert np.hypot(pos[0] - 5.0, pos[1] - 3.0) <= 0.7
    assert pos[2] == -5.0  # NaN down = keep the altitude
    feed(nav, t + 0.1, tuple(pos))
    out = nav.cycle(t + 0.1)
    assert out.setpoint is not None and out.setpoint.kind is SetpointKind.HOLD
    assert out.setpoint.vel_ned_m_s == (0.0, 0.0, 0.0) and out.setpoint.type_mask == MASK_POS_VEL


def test_navigate_setpoint_is_one_step_with_feed_forward() -> None:
    nav = make()
    feed(nav, 0.1, (0, 0, -5))
    nav.set_route(Route.point(10.0, 0.0, -5.0, source="test"), 0.1)
    out = nav.cycle(0.1)
    sp = out.setpoint
    assert sp is not None and sp.kind is SetpointKind.NAVIGATE and out.decision == "GREEDY"
    assert math.isclose(math.dist(sp.pos_ned_m[:2], (0, 0)), 0.4, rel_tol=1e-9)
    # Cruise, cut to what is safe if this is the last setpoint: at most silent_drift_m over GUID_TIMEOUT.
    safety = ServiceConfig().safety
    cap = min(ServiceConfig().cycle.cruise_speed_m_s, safety.silent_drift_m / safety.guid_timeout_s)
    assert math.isclose(math.hypot(*sp.vel_ned_m_s[:2]), cap, rel_tol=1e-9)
    assert sp.vel_ned_m_s[1] == 0.0 and sp.vel_ned_m_s[0] > 0.0
    assert sp.vel_ned_m_s[2] == 0.0


def test_not_engaged_prestreams_hold_at_current_position() -> None:
    nav = make()
    nav.autopilot_heartbeat(0.1, mode_ok=False)
    nav.update_pose(Pose(t_s=0.1, pos_ned_m=np.array([1.0, 2.0, -3.0]), yaw_rad=0.0))
    scan(nav, np.zeros((0, 3)), 0.1)
    nav.set_route(Route.point(10.0, 0.0, -5.0, source="test"), 0.1)
    out = nav.cycle(0.1)
    assert out.setpoint is not None and out.setpoint.kind is SetpointKind.PRESTREAM
    assert out.setpoint.pos_ned_m == (1.0, 2.0, -3.0)
    nav.autopilot_heartbeat(0.15, mode_ok=True)
    assert nav.engaged
    assert nav.cycle(0.2).setpoint.kind is SetpointKind.NAVIGATE  # type: ignore[union-attr]


@pytest.mark.parametrize("what", ["pose", "ranges"])
def test_stale_input_holds_within_one_cycle(what: str) -> None:
    nav = make()
    feed(nav, 0.1, (0, 0, -5))
    nav.set_route(Route.point(10.0, 0.0, -5.0, source="test"), 0.1)
    t, pos = fly(nav, 0.1, np.array([0.0, 0.0, -5.0]), 5)
    # Freeze one input; the other (and the heartbeat) keep coming.
    last_fresh = t
    for _ in range(10):
        t += 0.1
        nav.autopilot_heartbeat(t, mode_ok=True)
        if what == "pose":
            scan(nav, np.zeros((0, 3)), t)
        else:
            nav.update_pose(Pose(t_s=t, pos_ned_m=pos, yaw_rad=0.0))
        out = nav.cycle(t)
        if t - last_fresh > 0.5:  # the navigator rule: age > limit is stale
            break
        assert out.state is State.NAVIGATING
    assert out.state is State.HOLDING  # the first cycle past the limit
    assert out.setpoint is not None and out.setpoint.kind is SetpointKind.HOLD
    assert out.changes[0].new is State.HOLDING and what in out.changes[0].reason
    t += 0.1
    nav.autopilot_heartbeat(t, mode_ok=True)
    if what == "ranges":
        nav.update_pose(Pose(t_s=t, pos_ned_m=pos, yaw_rad=0.0))
    out2 = nav.cycle(t)
    if what == "pose":
        assert out2.setpoint is None  # stale pose: one hold, then silence
    else:
        assert out2.setpoint is not None and out2.setpoint.pos_ned_m == out.setpoint.pos_ned_m
    # Fresh again -> navigating.
    t += 0.1
    feed(nav, t, tuple(pos))
    assert nav.cycle(t).state is State.NAVIGATING


def _silent_gap(nav: Navigator, t: float, gap_s: float = 2.0) -> float:
    """Nothing arrives for ``gap_s`` (shorter than the heartbeat timeout): the cycles run on at 10 Hz. Returns the
    time of the last cycle; the pose and ranges went stale within it, so the hold fell silent."""
    outs = []
    for _ in range(round(gap_s / 0.1)):
        t += 0.1
        outs.append(nav.cycle(t))
    assert nav.link_alive(t) and outs[-1].setpoint is None
    assert any(o.setpoint is not None and o.setpoint.kind is SetpointKind.HOLD for o in outs)
    return t


@pytest.mark.parametrize("before", [State.NAVIGATING, State.ARRIVED])
def test_after_a_silent_gap_the_first_setpoint_holds_at_the_newest_pose(before: State) -> None:
    """The hostile-input review: after a 2 s silent gap the first cycle (pose fresh, ranges not yet) sent the hold
    point fixed before the gap, 1 m behind the vehicle, for one cycle before navigation resumed from the new pose."""
    nav = make()
    feed(nav, 0.1, (0, 0, -5))
    goal = 10.0 if before is State.NAVIGATING else 1.0
    nav.set_route(Route.point(goal, 0.0, -5.0, source="test"), 0.1)
    t, pos = fly(nav, 0.1, np.array([0.0, 0.0, -5.0]), 5 if before is State.NAVIGATING else 50)
    if before is State.ARRIVED:
        assert nav.state is State.ARRIVED
        t += 0.1
        feed(nav, t, tuple(pos))
        assert nav.cycle(t).setpoint is not None  # the arrival's hold point is fixed
    t = _silent_gap(nav, t)
    assert nav.state in (State.HOLDING, State.ARRIVED)
    # The heartbeat and a pose come back first, the vehicle 1 m on from where it was; no ranges yet.
    t += 0.1
    moved = (pos[0] + 1.0, pos[1] + 0.3, pos[2])
    nav.autopilot_heartbeat(t, mode_ok=True)
    assert nav.update_pose(Pose(t_s=t, pos_ned_m=np.array(moved), yaw_rad=0.0))
    out = nav.cycle(t)
    assert out.setpoint is not None and out.setpoint.kind is SetpointKind.HOLD
    assert out.setpoint.pos_ned_m == pytest.approx(moved)  # where the vehicle is now, not the old hold point
    t += 0.1
    nav.update_pose(Pose(t_s=t, pos_ned_m=np.array(moved), yaw_rad=0.0))
    out = nav.cycle(t)  # ranges still stale: the new hold point is kept while the pose is fresh
    assert out.setpoint is not None and out.setpoint.pos_ned_m == pytest.approx(moved)
    if before is State.NAVIGATING:
        t += 0.1
        feed(nav, t, moved)  # ranges too: navigation resumes from the newest pose
        out = nav.cycle(t)
        assert out.state is State.NAVIGATING and out.setpoint is not None
        assert out.setpoint.kind is SetpointKind.NAVIGATE
        assert math.dist(out.setpoint.pos_ned_m[:2], moved[:2]) <= nav.params.step_m + 1e-9


def test_a_hold_on_stale_ranges_keeps_its_point_while_the_pose_is_fresh() -> None:
    """Only a stale pose forgets the hold point: with the pose fresh and the ranges stale it stays where it was
    fixed, however the pose moves."""
    nav = make()
    feed(nav, 0.1, (0, 0, -5))
    nav.set_route(Route.point(10.0, 0.0, -5.0, source="test"), 0.1)
    t, pos = fly(nav, 0.1, np.array([0.0, 0.0, -5.0]), 3)
    points = []
    for k in range(12):  # ranges stop, the pose keeps coming and wanders
        t += 0.1
        nav.autopilot_heartbeat(t, mode_ok=True)
        nav.update_pose(Pose(t_s=t, pos_ned_m=pos + np.array([0.02 * k, 0.0, 0.0]), yaw_rad=0.0))
        out = nav.cycle(t)
        if out.state is State.HOLDING:
            assert out.setpoint is not None
            points.append(out.setpoint.pos_ned_m)
    assert len(points) >= 5 and len(set(points)) == 1


def test_frozen_pose_timestamp_is_refused() -> None:
    nav = make()
    assert nav.update_pose(Pose(t_s=1.0, pos_ned_m=np.zeros(3), yaw_rad=0.0))
    assert not nav.update_pose(Pose(t_s=1.0, pos_ned_m=np.ones(3), yaw_rad=0.0))
    assert nav.counters.rejected_poses == 1


def test_heartbeat_loss_goes_silent_and_needs_new_goal() -> None:
    nav = make(config_from_mapping({"safety": {"resume_after_link_lost": False}}))
    feed(nav, 0.1, (0, 0, -5))
    nav.set_route(Route.point(10.0, 0.0, -5.0, source="test"), 0.1)
    assert nav.cycle(0.1).setpoint is not None
    t = 0.1
    for _ in range(40):  # pose and ranges keep coming, the heartbeat does not
        t += 0.1
        nav.update_pose(Pose(t_s=t, pos_ned_m=np.zeros(3), yaw_rad=0.0))
        scan(nav, np.zeros((0, 3)), t)
        out = nav.cycle(t)
        if t - 0.1 > 3.0:
            assert out.state is State.LINK_LOST and out.setpoint is None
        else:
            assert out.state is State.NAVIGATING and out.setpoint is not None
    assert not nav.set_route(Route.point(1.0, 1.0, None, source="test"), t)
    t += 0.1
    feed(nav, t, (0, 0, -5))
    out = nav.cycle(t)
    assert out.state is State.IDLE and out.setpoint is None  # link back: no motion without a new goal
    assert nav.set_route(Route.point(1.0, 1.0, None, source="test"), t)


def _lose_link(nav: Navigator, t: float, n: int = 40) -> float:
    for _ in range(n):  # pose and ranges keep coming, the heartbeat does not
        t += 0.1
        nav.update_pose(Pose(t_s=t, pos_ned_m=np.zeros(3), yaw_rad=0.0))
        scan(nav, np.zeros((0, 3)), t)
        out = nav.cycle(t)
    assert out.state is State.LINK_LOST and out.setpoint is None
    return t


def test_heartbeat_loss_keeps_the_goal_and_resumes_in_guided_with_fresh_inputs() -> None:
    nav = make()
    feed(nav, 0.1, (0, 0, -5))
    nav.set_route(Route.point(10.0, 0.0, -5.0, source="test"), 0.1)
    assert nav.cycle(0.1).setpoint is not None
    t = _lose_link(nav, 0.1)
    assert nav.route is not None  # packet loss never drops the goal
    t += 0.1
    feed(nav, t, (0, 0, -5))  # heartbeat back, still GUIDED
    out = nav.cycle(t)
    assert [c.new for c in out.changes] == [State.HOLDING, State.NAVIGATING]
    assert out.setpoint is not None and out.setpoint.kind is SetpointKind.NAVIGATE


def test_heartbeat_back_in_another_mode_drops_the_goal() -> None:
    nav = make()
    feed(nav, 0.1, (0, 0, -5))
    nav.set_route(Route.point(10.0, 0.0, -5.0, source="test"), 0.1)
    nav.cycle(0.1)
    t = _lose_link(nav, 0.1) + 0.1
    nav.autopilot_heartbeat(t, mode_ok=False)  # the pilot / a failsafe took over meanwhile: never fight it
    out = nav.cycle(t)
    assert nav.state is State.IDLE and nav.route is None and out.setpoint is None


def test_pilot_override_drops_goal() -> None:
    nav = make()
    feed(nav, 0.1, (0, 0, -5))
    nav.set_route(Route.point(10.0, 0.0, -5.0, source="test"), 0.1)
    nav.cycle(0.1)
    nav.autopilot_heartbeat(0.2, mode_ok=False)
    assert nav.state is State.IDLE and nav.route is None
    assert nav.cycle(0.2).setpoint is None


def test_local_minimum_beyond_budget_is_stuck() -> None:
    # A ring of points 0.7 m around the agent: every CR-BAPF bacteria point is within rho_l of one.
    cfg = config_from_mapping({"planner": {"name": "cr-bapf", "random_walk_budget": 5}})
    nav = make(cfg)
    feed(nav, 0.1, (0, 0, -5))
    ang = np.linspace(0.0, 2.0 * np.pi, 40, endpoint=False)
    wall = np.stack([0.7 * np.cos(ang), 0.7 * np.sin(ang), np.full(40, -5.0)], axis=1)
    scan(nav, wall, 0.1)
    nav.set_route(Route.point(10.0, 0.0, -5.0, source="test"), 0.1)
    states = []
    t = 0.1
    for _ in range(10):
        feed(nav, t, (0, 0, -5))
        out = nav.cycle(t)
        states.append(out.state)
        assert out.setpoint is not None and out.setpoint.kind is SetpointKind.HOLD
        t += 0.1
    assert State.STUCK in states
    assert states.index(State.STUCK) == 5  # budget 5: the 6th non-greedy cycle gives up
    assert nav.set_route(Route.point(-5.0, 0.0, -5.0, source="test"), t)
    assert nav.state is State.NAVIGATING


def test_route_legs_in_order() -> None:
    nav = make()
    feed(nav, 0.1, (0, 0, -5))
    nav.set_route(Route(waypoints_ned_m=np.array([[2.0, 0.0, -5.0], [2.0, 2.0, -6.0]]), source="t"), 0.1)
    _t, pos = fly(nav, 0.1, np.array([0.0, 0.0, -5.0]), 100)
    assert nav.state is State.ARRIVED and nav.leg_index == 1
    assert np.hypot(pos[0] - 2.0, pos[1] - 2.0) <= 0.7 and pos[2] == -6.0


def test_goal_replaced_mid_flight() -> None:
    nav = make()
    feed(nav, 0.1, (0, 0, -5))
    nav.set_route(Route.point(10.0, 0.0, -5.0, source="a"), 0.1)
    t, pos = fly(nav, 0.1, np.array([0.0, 0.0, -5.0]), 5)
    nav.set_route(Route.point(pos[0], 10.0, -5.0, source="b"), t)
    t += 0.1
    feed(nav, t, tuple(pos))
    sp = nav.cycle(t).setpoint
    assert sp is not None and sp.pos_ned_m[1] > pos[1] + 0.3  # now heading east


def test_holding_reason_follows_the_current_cause() -> None:
    """The HOLDING reason says what is missing now (it used to stay "no pose yet" while ranges were missing)."""
    nav = make()
    nav.autopilot_heartbeat(0.0, mode_ok=False)
    nav.ekf_ready = False  # EKF_STATUS_REPORT without a horizontal position
    assert nav.set_route(Route.point(5.0, 3.0, None, source="test"), 0.0)
    nav.drain_changes()
    out = nav.cycle(0.1)
    assert out.state is State.HOLDING and out.setpoint is None
    assert [c.reason for c in out.changes] == ["waiting for EKF origin: no position yet"]
    # the origin is set, poses come, no ranges yet: the reason changes (same state, a new StateChange)
    nav.ekf_ready = True
    reasons: list[str] = []
    for k in range(2, 40):
        t = 0.1 * k
        nav.autopilot_heartbeat(t, mode_ok=False)
        nav.update_pose(Pose(t_s=t, pos_ned_m=np.array([0.0, 0.0, -5.0]), yaw_rad=0.0))
        out = nav.cycle(t)
        reasons += [c.reason for c in out.changes if c.new is State.HOLDING]
    assert out.state is State.HOLDING
    assert reasons == ["no ranges yet: holding position"]  # announced once, not every cycle
    # ranges arrive: navigating (taking over)
    t = 4.0
    feed(nav, t, (0.0, 0.0, -5.0))
    out = nav.cycle(t)
    assert out.state is State.NAVIGATING


def test_holding_reason_changes_are_rate_limited() -> None:
    nav = make()
    feed(nav, 0.0, (0.0, 0.0, -5.0))
    assert nav.set_route(Route.point(5.0, 3.0, None, source="test"), 0.0)
    nav.cycle(0.0)
    nav.drain_changes()
    # ranges stay stale; the pose comes and goes (0.7 s on, 0.7 s off): the cause flips every few cycles, the
    # announcements at most once per REASON_REPEAT_S
    changes = []
    for k in range(1, 81):
        t = 0.6 + 0.1 * k
        nav.autopilot_heartbeat(t, mode_ok=True)
        if (k // 7) % 2 == 0:
            nav.update_pose(Pose(t_s=t, pos_ned_m=np.array([0.0, 0.0, -5.0]), yaw_rad=0.0))
        changes += [c for c in nav.cycle(t).changes if c.old is State.HOLDING and c.new is State.HOLDING]
    assert len(changes) >= 3
    assert {c.reason for c in changes} == {
        "ranges stale: holding position",
        "pose stale, ranges stale: holding position",
    }
    assert all(b.t_s - a.t_s >= 1.0 - 1e-9 for a, b in itertools.pairwise(changes))


def test_the_same_goal_again_after_stuck_starts_the_planner_afresh() -> None:
    """bapf-nav gives up on an enclosed goal; once the enclosure is gone, sending the same goal again must fly (the
    planner's give-up state is per goal, not for the life of the service)."""
    cfg = config_from_mapping({"planner": {"name": "bapf-nav", "params": {"nav_patience_steps": 60}}})
    nav = make(cfg)
    feed(nav, 0.1, (0, 0, -5))
    ang = np.linspace(0.0, 2.0 * np.pi, 120, endpoint=False)
    ring = np.stack([6.0 + 1.5 * np.cos(ang), 1.5 * np.sin(ang), np.full(120, -5.0)], axis=1)
    scan(nav, ring, 0.1)
    goal = Route.point(6.0, 0.0, -5.0, source="test")
    assert nav.set_route(goal, 0.1)
    t, pos = fly(nav, 0.1, np.array([0.0, 0.0, -5.0]), 600)
    first = nav.state
    assert first is State.STUCK
    t += 40.0  # the ring expires from the memory (30 s); the vehicle still where it gave up
    feed(nav, t, tuple(pos))
    assert len(nav.obstacles.points(t)) == 0
    assert nav.set_route(goal, t)
    t, pos = fly(nav, t, pos, 200)
    assert nav.state is State.ARRIVED


@pytest.mark.parametrize("tapped", [False, True], ids=["planner", "service-tap"])
@pytest.mark.parametrize(
    ("centre_ne_m", "cause"),
    [((6.0, 0.0), GiveUp.NO_PROGRESS), ((0.0, 0.0), GiveUp.NO_WAY)],
    ids=["goal-enclosed", "vehicle-enclosed"],
)
def test_stuck_says_why_bapf_nav_gave_up(centre_ne_m: tuple[float, float], cause: GiveUp, tapped: bool) -> None:
    """The STUCK reason (a STATUSTEXT) names bapf-nav's cause: a ring of points around the goal is no progress
    for its patience; a ring around the vehicle is no way on the remembered map, at once. Also behind the
    service's ``PlanTap`` (``tapped``), which forwards the planner's attributes by ``__getattr__``."""
    cfg = config_from_mapping({"planner": {"name": "bapf-nav", "params": {"nav_patience_steps": 60}}})
    nav = make(cfg, tapped=tapped)
    feed(nav, 0.1, (0, 0, -5))
    ang = np.linspace(0.0, 2.0 * np.pi, 120, endpoint=False)
    north, east = centre_ne_m
    ring = np.stack([north + 1.5 * np.cos(ang), east + 1.5 * np.sin(ang), np.full(120, -5.0)], axis=1)
    scan(nav, ring, 0.1)
    assert nav.set_route(Route.point(6.0, 0.0, -5.0, source="test"), 0.1)
    t, pos, reasons = 0.1, np.array([0.0, 0.0, -5.0]), []
    for _ in range(600):
        t += 0.1
        feed(nav, t, (pos[0], pos[1], pos[2]))
        out = nav.cycle(t)
        reasons += [c.reason for c in out.changes if c.new is State.STUCK]
        if out.setpoint is not None:
            pos = np.array(out.setpoint.pos_ned_m)
        if nav.state is State.STUCK:
            break
    assert reasons == [f"planner gave up: {cause.text}"]
    assert statustext_for(State.STUCK, reasons[0]).endswith(cause.text)  # one STATUSTEXT holds all of it


def test_every_give_up_cause_fits_one_statustext() -> None:
    for cause in GiveUp:
        assert len(f"APF {State.STUCK.value}: planner gave up: {cause.text}") <= STATUSTEXT_MAX


def test_a_planner_swapped_at_run_time_is_observed_and_its_steps_counted_on() -> None:
    """A PARAM_SET or the fence's area puts a new planner in service: the observers tap the new one (the
    recording shows its decisions, not the old tap's last), and the plan sequence number goes on."""
    observers = Observers(FaultLog(ServiceCounters()))
    first = observers.tap(get_planner("bapf-nav", PlannerParams()))
    assert isinstance(first, PlanTap)
    for _ in range(3):
        first.step(np.zeros(2), np.array([10.0, 0.0]), np.zeros((0, 2)), np.random.default_rng(0))
    second = observers.tap(get_planner("bapf-nav", PlannerParams(rho_l_m=0.6)))
    assert isinstance(second, PlanTap) and second is not first and second.seq == 3
    assert second.plan() is None  # nothing stepped on the new planner yet
    second.step(np.zeros(2), np.array([10.0, 0.0]), np.zeros((0, 2)), np.random.default_rng(0))
    plan = second.plan()
    assert plan is not None and plan.seq == 4
