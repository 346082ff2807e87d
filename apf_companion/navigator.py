"""The service's decision core: state machine and planning cycle, pure and clock-injected.

No sockets, no asyncio, no wall clock: the service feeds inputs stamped with its own monotonic clock and calls
``cycle(now_s)`` at the cycle rate; tests drive it with a fake clock. One cycle returns at most one setpoint, and
a setpoint is only ever computed from inputs fresh at ``now_s`` (pose younger than ``pose_max_age_s``, ranges
younger than ``ranges_max_age_s``); nothing re-sends an old setpoint.

States (docs/service.md has the diagram):

- IDLE: no goal (or the pilot took the vehicle out of GUIDED/OFFBOARD). Sends nothing.
- WAITING_FOR_PILOT: a goal, ``autopilot.takeover`` off and the autopilot not (yet) in GUIDED / OFFBOARD: the
  pilot has to switch (the reason names the mode). While the pose is fresh it streams holds at the current
  position (``SetpointKind.PRESTREAM``: PX4 accepts OFFBOARD only while setpoints stream; ArduCopter ignores
  setpoints outside GUIDED), runs no planner step, and goes NAVIGATING at the HEARTBEAT that shows the mode.
- NAVIGATING: a goal and fresh inputs. Before the autopilot is in GUIDED/OFFBOARD (the service takes over:
  ``autopilot.takeover``) it streams holds at the current position (PX4 needs setpoints before it accepts
  OFFBOARD); then runs the planner every cycle and sends its next point with velocity feed-forward.
- HOLDING: pose or ranges stale. In the first HOLDING cycle it commands a hold at the last known position;
  after that it keeps commanding that hold only while the pose is fresh (ranges stale), and falls silent when
  the pose is stale too (the autopilot's position hold / OFFBOARD-loss failsafe acts). Fresh inputs -> back to
  NAVIGATING.
- ARRIVED: within ``arrival_radius_m`` of the last waypoint: hold where it is (while the pose is fresh).
- STUCK: the planner found no greedy move for ``random_walk_budget`` cycles in a row, or no progress for
  ``progress_timeout_s``: hold and report. A new goal restarts.
- LINK_LOST: no autopilot HEARTBEAT for ``heartbeat_timeout_s``: send nothing. The goal is kept (packet loss
  never drops it): when the heartbeat returns, the autopilot's mode is checked first: still GUIDED / OFFBOARD ->
  HOLDING, and NAVIGATING once the inputs are fresh; another mode (the pilot or a failsafe took over) -> the goal
  is dropped (IDLE). With ``resume_after_link_lost`` false the goal is dropped at once and motion only resumes
  after a new goal (IDLE once the link is back). A goal held for its check (``held``) follows the same rule.

The goal is one of: none, ``held`` (taken, not flown until the service can check it: ``hold_goal``) or ``route``
(flown: ``set_route``); never both.

Each state has one handler (``_HANDLERS``, keyed by ``State``). The navigator reads the configuration only as a
frozen ``NavigatorParams`` and the obstacles only through ``ObstacleView`` (the perception front end writes them).
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Callable
from typing import Any

import numpy as np

from apf_companion.goal import Route
from apf_companion.linkquality import CLEAN_LINK, LinkQuality, caution_scale
from apf_companion.navigation.legs import Leg, Legs
from apf_companion.navigation.model import (
    ENGAGED_STATES,
    HOLD_STATES,
    WANTS_POSE,
    Counters,
    CycleInputs,
    CycleOutput,
    Decision,
    DecisionLike,
    FloatArray,
    NavigatorParams,
    ObstacleView,
    PlannerLike,
    State,
    StateChange,
)
from apf_companion.navigation.tracking import HoldPoint, StepTracker, shortened
from apf_companion.perception import Pose
from apf_companion.planning import GiveUp
from apf_companion.setpoint import Setpoint, SetpointKind, brake, hold

__all__ = [
    "CycleOutput",
    "Decision",
    "DecisionLike",
    "Navigator",
    "NavigatorParams",
    "ObstacleView",
    "PlannerLike",
    "Recovery",
    "State",
    "StateChange",
    "reconfigure",
    "shortened",
]

REASON_REPEAT_S = 1.0  # a changed HOLDING reason is announced at most this often (a flapping cause cannot flood)


def _nearest_m(points: FloatArray, pos: FloatArray, dim: int) -> float | None:
    """Distance to the nearest of ``points`` (horizontal in 2D), None without points."""
    if points.shape[0] == 0:
        return None
    d = points[:, :dim] - pos[:dim]
    return float(np.sqrt(np.min(np.einsum("ij,ij->i", d, d))))


def _near(points: FloatArray, pos: FloatArray, dim: int, reach_m: float) -> FloatArray:
    """Obstacle points within ``reach_m`` (those that can matter this step), vectorised."""
    if points.shape[0] == 0:
        return np.zeros((0, 3))
    d = points[:, :dim] - pos[:dim]
    keep = np.einsum("ij,ij->i", d, d) <= reach_m * reach_m
    return np.asarray(points[keep], dtype=np.float64)


def _no_pose_reason(ekf_ready: bool | None) -> str:
    """Why HOLDING has no pose: the EKF has no origin yet (ArduPilot sends no LOCAL_POSITION_NED then), or no pose
    came (not requested, not sent)."""
    if ekf_ready is False:
        return "waiting for EKF origin: no position yet"
    return "no pose yet (no LOCAL_POSITION_NED)"


def _repeats(said: tuple[str, float], reason: str, now_s: float) -> bool:
    return reason == said[0] or now_s - said[1] < REASON_REPEAT_S


def _stale_reason(inp: CycleInputs, *, ranges_seen: bool) -> str:
    ranges = "ranges stale" if ranges_seen else "no ranges yet"
    if not inp.pose_ok:
        return f"pose stale, {ranges}: holding position" if not inp.ranges_ok else "pose stale: holding position"
    return f"{ranges}: holding position"


class Recovery:
    """What the navigator keeps through a lost link or a position reset, and how it resumes (docs/hardening.md)."""

    def __init__(self, nav: Navigator) -> None:
        self.nav = nav
        self.hold_until_s = -math.inf  # a position reset holds until then
        self.pose_confirmed = True  # the pose gate's anchor is confirmed (set by the handler on every pose)

    def brake(self, inp: CycleInputs) -> CycleOutput:
        """The pose is not confirmed (docs/hardening.md): while flying for a goal (engaged), stop where the vehicle
        is, with no position in the setpoint; silence before that (nothing was commanded yet) and once the pose is
        stale. No hold point, step or arrival is taken from an unconfirmed pose."""
        nav = self.nav
        nav._steps.target = None
        nav._hold.reset()
        nav.counters.unconfirmed_pose_cycles += 1
        sp = brake() if inp.pose_ok and nav.engaged else None
        return CycleOutput(t_s=inp.now_s, state=nav.state, setpoint=sp, nearest_obstacle_m=inp.nearest_m)

    def holding(self, now_s: float) -> bool:
        return now_s < self.hold_until_s

    def position_reset(self, now_s: float, reason: str) -> None:
        """The old step and hold point are in the old frame: hold at the new position (a STATUSTEXT says why)."""
        nav = self.nav
        nav._steps.target = None
        nav._hold.reset()
        self.hold_until_s = now_s + nav.params.reset_hold_s
        if nav.route is not None and nav.state in (State.NAVIGATING, State.HOLDING):
            nav._change(now_s, State.HOLDING, f"{reason}: holding")

    def restart_hold(self, now_s: float, reason: str) -> None:
        """The service started while the vehicle flies in GUIDED / OFFBOARD: hold where it is, without a goal, until
        a fresh goal arrives (``set_route``) or the pilot takes the vehicle (IDLE)."""
        nav = self.nav
        nav.engaged = True  # the vehicle is in our mode: a mode change by the pilot ends the hold
        nav._hold.reset()
        nav._change(now_s, State.HOLDING, reason)

    def goalless_hold(self, inp: CycleInputs) -> CycleOutput:
        nav = self.nav
        if not self.pose_confirmed:
            return self.brake(inp)
        sp = nav._hold.setpoint(nav.pose, pose_fresh=inp.pose_ok)
        return CycleOutput(t_s=inp.now_s, state=nav.state, setpoint=sp, nearest_obstacle_m=inp.nearest_m)

    def link_dead(self, now_s: float) -> None:
        """No heartbeat: silence. The goal (flown or held) is kept (``resume_after_link_lost``), the step and hold
        forgotten."""
        nav = self.nav
        if nav._last_hb_s is None or nav.state is State.LINK_LOST:
            return
        if nav.params.resume_after_link_lost and nav.has_goal:
            nav._steps.target = None
            nav._hold.reset()
            nav._change(now_s, State.LINK_LOST, "autopilot heartbeat lost: stopped sending, goal kept")
        else:
            nav._drop_route(now_s, State.LINK_LOST, "autopilot heartbeat lost: stopped sending")

    def link_back(self, now_s: float) -> None:
        """The heartbeat is back; its mode was checked in ``autopilot_heartbeat`` (a mode not ours while engaged
        dropped the goal). Hold first: ``_on_holding`` navigates on once the inputs are fresh."""
        nav = self.nav
        if nav.held is not None:  # never flown: the service checks it at the next pose
            reason = _no_pose_reason(nav.ekf_ready) if nav.pose is None else "goal checked at the next pose"
            nav._change(now_s, State.HOLDING, f"autopilot heartbeat back: {reason}")
        elif nav.route is None:
            nav._change(now_s, State.IDLE, "autopilot heartbeat back: send a new goal to fly")
        elif nav.engaged and nav.mode_ok:
            nav._change(now_s, State.HOLDING, "autopilot heartbeat back, guided: resuming when inputs are fresh")
        else:
            nav._go(now_s, "autopilot heartbeat back: taking over again for the goal")


def _planner_give_up(planner: object) -> str:
    """The STUCK reason of a planner that gave up, with its cause where it says one (bapf-nav's
    ``give_up_cause``; looked up by name, as ``reset`` below, so that it reaches through the service's
    ``observe.PlanTap``, which forwards attributes by ``__getattr__``)."""
    give_up_cause = getattr(planner, "give_up_cause", None)
    if callable(give_up_cause):
        cause = give_up_cause()
        if isinstance(cause, GiveUp) and cause is not GiveUp.NONE:
            return f"planner gave up: {cause.text}"
    return "planner gave up"


def _reset_planner(planner: object) -> None:
    """A stateful planner (bapf-nav) that gave up stays given up until its target changes: a new goal, even the
    same point again (a retry, the next flight of a long-lived service), starts it afresh."""
    reset = getattr(planner, "reset", None)
    if callable(reset):
        reset()


class Navigator:
    """The decision core. Feed it inputs, call ``cycle(now_s)`` at the cycle rate.

    Args:
        params: What it reads of the configuration (``NavigatorParams``).
        planner: A planner (``get_planner(name, params)``) whose dimension matches ``params.dim``.
        obstacles: The obstacle memory it reads (written only by the perception front end).
        rng: The random walk's generator.

    The link counts as lost until the first autopilot HEARTBEAT (``autopilot_heartbeat``).
    """

    def __init__(
        self,
        *,
        params: NavigatorParams,
        planner: PlannerLike,
        obstacles: ObstacleView,
        rng: np.random.Generator,
    ) -> None:
        self.params = params
        self.planner = planner
        self.obstacles = obstacles
        self.rng = rng
        self.dim = params.dim
        self.state = State.IDLE
        self.counters = Counters()
        self.pose: Pose | None = None
        self.route: Route | None = None
        self.engaged = False  # the autopilot has been seen in GUIDED/OFFBOARD for this route
        self.mode_ok = False  # latest HEARTBEAT: autopilot is in GUIDED/OFFBOARD
        self.suspended = False  # the service is busy with arming/takeoff: no setpoints
        self.held: Route | None = None  # a goal taken but not flown until it can be checked (``hold_goal``)
        self.ekf_ready: bool | None = None  # EKF_STATUS_REPORT has a horizontal position (None = not reported)
        self._said: tuple[str, float] = ("", -math.inf)  # the last reason announced, and when
        self.last_output: CycleOutput | None = None
        self._steps = StepTracker(params, self.counters)
        self._hold = HoldPoint()
        self._legs = Legs(params, self._steps)
        self._last_hb_s: float | None = None
        self.recovery = Recovery(self)  # link loss and position resets (``recovery.position_reset``)
        self._pending: list[StateChange] = []

    # ---- inputs ------------------------------------------------------------------------------------------------
    def update_pose(self, pose: Pose) -> bool:
        """A new pose (already validated finite by ``Pose``). Older-or-equal timestamps are refused (a frozen or
        replayed pose must not look fresh). Returns whether it was accepted."""
        if self.pose is not None and pose.t_s <= self.pose.t_s:
            self.counters.rejected_poses += 1
            return False
        self.pose = pose
        return True

    def autopilot_heartbeat(self, now_s: float, *, mode_ok: bool) -> None:
        """An autopilot HEARTBEAT; ``mode_ok`` = its custom_mode is GUIDED (ArduPilot) / OFFBOARD (PX4)."""
        self._last_hb_s = now_s
        if self.engaged and not mode_ok and (self.state in ENGAGED_STATES or self.state is State.LINK_LOST):
            # The pilot (or a failsafe) took the vehicle: never fight it; wait for a new goal.
            self._drop_route(now_s, State.IDLE, "autopilot left guided control: goal dropped")
        self.mode_ok = mode_ok
        if mode_ok and self.route is not None:
            self.engaged = True
            if self.state is State.WAITING_FOR_PILOT:
                self._change(now_s, State.NAVIGATING, f"in {self.params.guided_mode}, flying to the goal")

    def set_route(self, route: Route, now_s: float) -> bool:
        """A new goal or route replaces the active (or held) one. Refused (False) while the link is lost."""
        if not self.accepts_goals(now_s):
            return False
        self.counters.goals += 1
        self.route = route
        self.held = None
        _reset_planner(self.planner)
        self._legs.leg = None
        self._steps.target = None
        self._hold.reset()
        self.engaged = self.mode_ok
        self._go(now_s, f"new goal from {route.source}: {route.to_json_list()[-1]}")
        return True

    def hold_goal(self, route: Route, now_s: float) -> bool:
        """Take ``route`` (replacing the active or held goal) without flying it: the service cannot check it yet (no
        position for ``goal.max_distance_m``). HOLDING, silent, saying why there is no position, until
        ``set_route`` (checked: flown) or ``clear_route`` (refused); a lost link keeps or drops it as a flown goal
        (``resume_after_link_lost``). Refused (False) while the link is lost, as ``set_route`` would refuse it."""
        if not self.accepts_goals(now_s):
            return False
        self.route, self.held = None, route  # one goal (a flown one has a pose: it is not held, in practice)
        self._legs.leg = None
        self._enter_hold_state(now_s, State.HOLDING, _no_pose_reason(self.ekf_ready))
        return True

    def accepts_goals(self, now_s: float) -> bool:
        """A goal can be taken now: the link is alive and LINK_LOST has been left."""
        return self.state is not State.LINK_LOST and self.link_alive(now_s)

    @property
    def has_goal(self) -> bool:
        """A goal is flown (``route``) or held for its check (``held``)."""
        return self.route is not None or self.held is not None

    def drain_changes(self) -> list[StateChange]:
        """State changes recorded outside ``cycle`` (``set_route``, heartbeats), oldest first; clears them."""
        changes, self._pending = self._pending, []
        return changes

    def suspend(self) -> None:
        """Stop sending setpoints (the service is arming / taking off)."""
        self.suspended = True

    def resume(self) -> None:
        """Send setpoints again; the leg restarts so "keep altitude" means the altitude reached meanwhile."""
        self.suspended = False
        self._legs.leg = None
        self._steps.target = None

    def clear_route(self, now_s: float, reason: str) -> None:
        """Forget the goal (operator stop): IDLE, send nothing."""
        self._drop_route(now_s, State.IDLE, reason)

    # ---- what it reports ---------------------------------------------------------------------------------------
    def link_alive(self, now_s: float) -> bool:
        return self._last_hb_s is not None and now_s - self._last_hb_s <= self.params.heartbeat_timeout_s

    def heartbeat_age_s(self, now_s: float) -> float | None:
        """Time since the last autopilot HEARTBEAT [s]; None before the first."""
        return None if self._last_hb_s is None else now_s - self._last_hb_s

    def pose_fresh(self, now_s: float) -> bool:
        return self.pose is not None and now_s - self.pose.t_s <= self.params.pose_max_age_s

    def ranges_fresh(self, now_s: float) -> bool:
        if not self.params.require_ranges:
            return True
        last = self.obstacles.ranges_t_s
        return last is not None and now_s - last <= self.params.ranges_max_age_s

    @property
    def active_target_ned_m(self) -> FloatArray | None:
        """The waypoint being flown to (down resolved), if any."""
        return None if self._legs.leg is None or self.route is None else self._legs.leg.target_ned_m

    @property
    def leg_index(self) -> int | None:
        return None if self._legs.leg is None else self._legs.leg.index

    def counts(self) -> dict[str, int]:
        """Counters for status and tests."""
        return {name: getattr(self.counters, name) for name in self.counters.__dataclass_fields__}

    def approach_speed(self, gap_m: float, nearest_m: float | None = None) -> float:
        """The feed-forward speed towards a bacteria point ``gap_m`` away (see ``StepTracker``)."""
        return self._steps.approach_speed(gap_m, nearest_m)

    # ---- the cycle ---------------------------------------------------------------------------------------------
    def cycle(self, now_s: float, link: LinkQuality = CLEAN_LINK) -> CycleOutput:
        """One cycle at service time ``now_s``: state and setpoint (or silence); a lossy ``link`` shortens steps."""
        self.counters.cycles += 1
        self._steps.caution = caution_scale(link, self.params.caution)
        if not self.link_alive(now_s):
            self.recovery.link_dead(now_s)
            out = CycleOutput(t_s=now_s, state=self.state, setpoint=None)
        else:
            if self.state is State.LINK_LOST:
                self.recovery.link_back(now_s)
            inp = self._inputs(now_s)
            out = _HANDLERS[self.state](self, inp)
        if out.setpoint is not None:
            self.counters.setpoints += 1
            self.counters.prestream_setpoints += out.setpoint.kind is SetpointKind.PRESTREAM
        changes = tuple(self._pending)
        self._pending.clear()
        out = dataclasses.replace(out, state=self.state, changes=changes, caution=self._steps.caution)
        self.last_output = out
        return out

    def _inputs(self, now_s: float) -> CycleInputs:
        points = self.obstacles.points(now_s)
        pose_ok = self.pose_fresh(now_s)
        ranges_ok = self.ranges_fresh(now_s)
        if not pose_ok:
            self.counters.stale_pose_cycles += 1
        if not ranges_ok:
            self.counters.stale_range_cycles += 1
        nearest = None if self.pose is None else _nearest_m(points, self.pose.pos_ned_m, self.dim)
        return CycleInputs(now_s, points, nearest, pose_ok, ranges_ok)

    def _silent(self, inp: CycleInputs) -> CycleOutput:
        return CycleOutput(t_s=inp.now_s, state=self.state, setpoint=None, nearest_obstacle_m=inp.nearest_m)

    def _out(self, inp: CycleInputs, sp: Setpoint | None, dist: float, **kw: Any) -> CycleOutput:
        return CycleOutput(
            t_s=inp.now_s,
            state=self.state,
            setpoint=sp,
            distance_to_goal_m=dist,
            nearest_obstacle_m=inp.nearest_m,
            **kw,
        )

    def _blocked(self, inp: CycleInputs) -> CycleOutput | None:
        """Silence when there is no goal or pose (NAVIGATING -> HOLDING without a pose), or while suspended."""
        if self.route is None and self.held is None and self.pose is not None and self.state is State.HOLDING:
            return self.recovery.goalless_hold(inp)  # restarted mid-flight (``Recovery.restart_hold``)
        if self.route is None or self.pose is None:
            # Held: the service checks the goal at the next pose (one may have come while the link was lost).
            if self.has_goal and self.pose is None and self.state in WANTS_POSE:
                self._enter_hold_state(inp.now_s, State.HOLDING, _no_pose_reason(self.ekf_ready))
            return self._silent(inp)
        if self.suspended:
            return self._silent(inp)
        return None if self.recovery.pose_confirmed else self.recovery.brake(inp)

    def _distance_to_goal(self) -> float:
        assert self.route is not None and self.pose is not None
        return self._legs.provisional_distance(self.route, self.pose.pos_ned_m)

    # ---- one handler per state ---------------------------------------------------------------------------------
    def _on_idle(self, inp: CycleInputs) -> CycleOutput:
        """IDLE (and LINK_LOST, left in ``cycle`` once the link is back): no goal, nothing to send."""
        return self._silent(inp)

    def _on_waiting(self, inp: CycleInputs) -> CycleOutput:
        """WAITING_FOR_PILOT (``autopilot_heartbeat`` goes NAVIGATING when the HEARTBEAT shows GUIDED / OFFBOARD).

        With a fresh pose, a hold at the current position each cycle, as while taking over. PX4 enters OFFBOARD
        only while setpoints stream: NAVIGATION_STATE_OFFBOARD requires the offboard signal
        (src/modules/commander/ModeUtil/mode_requirements.cpp), which counts as lost unless the last
        offboard_control_mode is younger than COM_OF_LOSS_T (.../HealthAndArmingChecks/checks/offboardCheck.cpp);
        src/modules/mavlink/mavlink_receiver.cpp publishes one for every setpoint and uses the setpoint itself only
        in OFFBOARD. ArduCopter drops setpoints outside GUIDED (ArduCopter/GCS_MAVLink_Copter.cpp
        ``handle_message_set_position_target_local_ned``: not ``in_guided_mode()``, return). So whichever hold is
        in force at the switch keeps the vehicle about where it was. No planner step and no leg yet: a "keep
        altitude" goal keeps the altitude of the switch. Silent with a stale pose."""
        blocked = self._blocked(inp)
        if blocked is not None:
            return blocked
        if not inp.pose_ok:
            return self._silent(inp)
        assert self.pose is not None
        return self._out(inp, hold(self.pose.pos_ned_m, SetpointKind.PRESTREAM), self._distance_to_goal())

    def _on_navigating(self, inp: CycleInputs) -> CycleOutput:
        blocked = self._blocked(inp)
        if blocked is not None:
            return blocked
        if self._pilot_must_switch():
            return self._wait_for_pilot(inp)
        if not (inp.pose_ok and inp.ranges_ok):
            return self._hold_stale(inp)
        return self._fly(inp)

    def _on_holding(self, inp: CycleInputs) -> CycleOutput:
        blocked = self._blocked(inp)
        if blocked is not None:
            return blocked
        if self._pilot_must_switch():
            return self._wait_for_pilot(inp)  # e.g. the goal came before the first pose: now the pilot is asked
        if not (inp.pose_ok and inp.ranges_ok):
            return self._hold_stale(inp)
        if self.recovery.holding(inp.now_s):
            return self._out(inp, self._hold.setpoint(self.pose, pose_fresh=True), self._distance_to_goal())
        self._hold.anchor = None
        self._change(inp.now_s, State.NAVIGATING, "inputs fresh again: navigating")
        return self._fly(inp)

    def _on_done(self, inp: CycleInputs) -> CycleOutput:
        """ARRIVED and STUCK: hold where the state was entered (while the pose is fresh)."""
        blocked = self._blocked(inp)
        if blocked is not None:
            return blocked
        sp = self._hold.setpoint(self.pose, pose_fresh=inp.pose_ok)
        return self._out(inp, sp, self._distance_to_goal())

    def _hold_stale(self, inp: CycleInputs) -> CycleOutput:
        dist = self._distance_to_goal()
        reason = _stale_reason(inp, ranges_seen=self.obstacles.ranges_t_s is not None)
        self._enter_hold_state(inp.now_s, State.HOLDING, reason)
        return self._out(inp, self._hold.setpoint(self.pose, pose_fresh=inp.pose_ok), dist)

    def _fly(self, inp: CycleInputs) -> CycleOutput:
        assert self.pose is not None
        pos = np.asarray(self.pose.pos_ned_m, dtype=np.float64)
        if not self.engaged:
            # Taking over: hold here until the autopilot reports GUIDED/OFFBOARD.
            return self._out(inp, hold(pos, SetpointKind.PRESTREAM), self._distance_to_goal())
        assert self.route is not None
        leg, dist = self._legs.current(self.route, pos, inp.now_s)
        if leg is None:
            self._enter_hold_state(inp.now_s, State.ARRIVED, f"arrived at goal ({dist:.2f} m)")
            return self._out(inp, self._hold.setpoint(self.pose, pose_fresh=True), dist)
        obstacles = _near(inp.points, pos, self.dim, self.params.max_range_m + 1.0)  # sensor range + a step
        tracked = self._steps.track(pos, obstacles, inp.now_s, inp.nearest_m)
        n = int(obstacles.shape[0])
        if tracked is not None:
            out = self._out(inp, tracked, dist, decision=Decision.TRACKING.value, n_obstacles=n)
        else:
            out = self._plan(inp, pos, leg, dist, obstacles)
        self._steps.watch(out, self.pose, obstacles)
        return self._steps.known_direction(out, pos, self.obstacles)

    def _plan(self, inp: CycleInputs, pos: FloatArray, leg: Leg, dist: float, obstacles: FloatArray) -> CycleOutput:
        """Plan the next step from the bacteria point just reached (the paper's path), else from the pose."""
        origin = pos if self._steps.target is None else self._steps.target
        self._steps.target = None
        self.counters.planner_steps += 1
        dim = self.dim
        decision = self.planner.step(origin[:dim].copy(), leg.target_ned_m[:dim].copy(), obstacles[:, :dim], self.rng)
        reason = decision.reason.name
        leg.streak = 0 if reason == Decision.GREEDY.value else leg.streak + 1
        self.counters.decision(reason)
        n = int(obstacles.shape[0])
        give_up = self._legs.give_up(leg, inp.now_s)
        if reason == Decision.GAVE_UP.value:
            give_up = _planner_give_up(self.planner)
        if give_up is not None:
            self._enter_hold_state(inp.now_s, State.STUCK, give_up)
            return self._out(inp, self._hold.setpoint(self.pose, pose_fresh=True), dist, decision=reason, n_obstacles=n)
        nxt = decision.next_point_m
        if nxt is None:
            sp = hold(pos)  # a local minimum inside the budget: wait here (memory may change)
        else:
            target = np.empty(3)
            target[:dim] = np.asarray(nxt, dtype=np.float64)[:dim]
            if dim == 2:
                target[2] = leg.target_ned_m[2]
            self._steps.set(target, inp.now_s)
            gap = float(np.linalg.norm((target - pos)[:dim]))
            speed = self._steps.approach_speed(gap, inp.nearest_m)
            sp = self._steps.setpoint(pos, target, speed, obstacles)
        return self._out(inp, sp, dist, decision=reason, n_obstacles=n)

    def _wait_for_pilot(self, inp: CycleInputs) -> CycleOutput:
        self._steps.target = None
        self._hold.reset()  # a hold point of HOLDING is not where the pilot will have flown it by the switch
        self._change(inp.now_s, State.WAITING_FOR_PILOT, self._switch_reason())
        return self._on_waiting(inp)

    # ---- helpers -----------------------------------------------------------------------------------------------
    def _pilot_must_switch(self) -> bool:
        """A goal the service may not take over for (``takeover`` off) and the autopilot not seen in its mode."""
        return not self.params.takeover and self.route is not None and not self.engaged

    def _switch_reason(self) -> str:
        return f"switch to {self.params.guided_mode} to fly"  # "APF WAITING_FOR_PILOT: ..." fits one STATUSTEXT

    def _go(self, now_s: float, reason: str) -> None:
        """NAVIGATING for the goal (``reason``), or WAITING_FOR_PILOT when the pilot has to switch the mode first
        (HOLDING without a pose yet: PX4 would refuse OFFBOARD without the hold stream, and nothing can be flown)."""
        if self._pilot_must_switch() and self.pose is None:
            self._change(now_s, State.HOLDING, _no_pose_reason(self.ekf_ready))
        elif self._pilot_must_switch():
            self._change(now_s, State.WAITING_FOR_PILOT, self._switch_reason())
        else:
            self._change(now_s, State.NAVIGATING, reason)

    def _change(self, now_s: float, new: State, reason: str) -> None:
        if new is self.state and (new is not State.HOLDING or _repeats(self._said, reason, now_s)):
            return  # HOLDING says why now: a new cause is announced (at most every REASON_REPEAT_S)
        self._pending.append(StateChange(t_s=now_s, old=self.state, new=new, reason=reason))
        self.state = new
        self._said = (reason, now_s)

    def _drop_route(self, now_s: float, new: State, reason: str) -> None:
        self.route = None
        self.held = None
        self._legs.leg = None
        self.engaged = False
        self._hold.anchor = None
        self._change(now_s, new, reason)

    def _enter_hold_state(self, now_s: float, new: State, reason: str) -> None:
        self._steps.target = None
        if self.state not in HOLD_STATES or new is not self.state:
            self._hold.reset()
        self._change(now_s, new, reason)


_HANDLERS: dict[State, Callable[[Navigator, CycleInputs], CycleOutput]] = {
    State.IDLE: Navigator._on_idle,
    State.LINK_LOST: Navigator._on_idle,  # left in ``cycle`` as soon as the link is alive
    State.WAITING_FOR_PILOT: Navigator._on_waiting,
    State.NAVIGATING: Navigator._on_navigating,
    State.HOLDING: Navigator._on_holding,
    State.ARRIVED: Navigator._on_done,
    State.STUCK: Navigator._on_done,
}
"""One handler per state, for a cycle with the autopilot link alive."""


def reconfigure(nav: Navigator, params: NavigatorParams, planner: PlannerLike) -> None:
    """Swap the navigator's parameters and planner (a PARAM_SET at run time, apf_companion.params).

    Called between cycles (the service runs input handling and cycles on one event loop). The bacteria point
    being flown to was planned with the old parameters, so it is dropped and the next cycle plans afresh; the
    goal, the leg's progress and the state are kept. The dimension cannot change at run time.
    """
    if params.dim != nav.dim:
        msg = f"internal: the dimension cannot change at run time ({nav.dim} -> {params.dim})"
        raise AssertionError(msg)
    nav.params = params
    nav.planner = planner
    nav._steps.p = params  # the navigator's own parts, in its own module
    nav._legs.p = params
    nav._steps.target = None
