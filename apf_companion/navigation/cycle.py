"""One handler per state, for a cycle with the autopilot link alive: what to send, and the transitions a cycle
makes (arrival, STUCK, HOLDING on stale inputs, waiting for the pilot)."""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import numpy as np

from apf_companion.navigation.goalslot import GoalSlot
from apf_companion.navigation.legs import Leg, Legs
from apf_companion.navigation.machine import FAILSAFE_WAIT_REASON, StateMachine
from apf_companion.navigation.model import (
    WANTS_POSE,
    Counters,
    CycleInputs,
    CycleOutput,
    Decision,
    FloatArray,
    NavigatorParams,
    ObstacleView,
    PlannerLike,
    State,
)
from apf_companion.navigation.recovery import Recovery
from apf_companion.navigation.tracking import HoldPoint, StepTracker
from apf_companion.navigation.vehicle import VehicleLink
from apf_companion.planning import GiveUp
from apf_companion.setpoint import Setpoint, SetpointKind, hold

__all__ = ["CycleHandlers"]


class CycleHandlers:
    """The per-state handlers (``run``), the planner and its random generator, and ``suspended`` (the service is
    busy arming / taking off: no setpoints)."""

    def __init__(
        self,
        params: NavigatorParams,
        *,
        planner: PlannerLike,
        rng: np.random.Generator,
        obstacles: ObstacleView,
        counters: Counters,
        machine: StateMachine,
        goal: GoalSlot,
        vehicle: VehicleLink,
        steps: StepTracker,
        hold: HoldPoint,
        legs: Legs,
        recovery: Recovery,
    ) -> None:
        self.p = params
        self.planner = planner
        self.rng = rng
        self.obstacles = obstacles
        self.counters = counters
        self.machine = machine
        self.goal = goal
        self.vehicle = vehicle
        self.steps = steps
        self.hold = hold
        self.legs = legs
        self.recovery = recovery
        self.suspended = False

    def run(self, inp: CycleInputs) -> CycleOutput:
        """The current state's handler (``_HANDLERS``)."""
        return _HANDLERS[self.machine.state](self, inp)

    def restart_planner(self) -> None:
        """A stateful planner (bapf-nav) that gave up stays given up until its target changes: a new goal, even the
        same point again (a retry, the next flight of a long-lived service), starts it afresh. Looked up by name, as
        ``_planner_give_up``, through the service's ``observe.PlanTap``."""
        reset = getattr(self.planner, "reset", None)
        if callable(reset):
            reset()

    def _on_idle(self, inp: CycleInputs) -> CycleOutput:
        """IDLE (and LINK_LOST, left in ``Navigator.cycle`` once the link is back): no goal, nothing to send."""
        return self._silent(inp)

    def _on_waiting(self, inp: CycleInputs) -> CycleOutput:
        """WAITING_FOR_PILOT (a HEARTBEAT showing GUIDED / OFFBOARD goes NAVIGATING: ``StateMachine.mode_seen``).

        With a fresh pose, a hold at the current position each cycle, as while taking over. PX4 enters OFFBOARD
        only while setpoints stream: NAVIGATION_STATE_OFFBOARD requires the offboard signal
        (src/modules/commander/ModeUtil/mode_requirements.cpp), which counts as lost unless the last
        offboard_control_mode is younger than COM_OF_LOSS_T (.../HealthAndArmingChecks/checks/offboardCheck.cpp);
        src/modules/mavlink/mavlink_receiver.cpp publishes one for every setpoint and uses the setpoint itself only
        in OFFBOARD. ArduCopter drops setpoints outside GUIDED (ArduCopter/GCS_MAVLink_Copter.cpp
        ``handle_message_set_position_target_local_ned``: not ``in_guided_mode()``, return). So whichever hold is
        in force at the switch keeps the vehicle about where it was. No planner step and no leg yet: a "keep
        altitude" goal keeps the altitude of the switch. Silent with a stale pose.

        Silent too on PX4 while its HEARTBEAT reports a failsafe (CRITICAL), saying so: after an offboard-loss
        failsafe PX4 goes back to OFFBOARD by itself as soon as setpoints come (src/modules/commander/failsafe/
        failsafe.cpp ``checkModeFallback``: the user's intended mode stays OFFBOARD and the fallback clears with its
        condition), and the holds would then look like the pilot's switch. The pilot first picks another mode,
        which ends the failsafe, then OFFBOARD."""
        blocked = self._blocked(inp)
        if blocked is not None:
            return blocked
        if self.p.setpoints_end_failsafe and self.vehicle.failsafe:
            self.machine.change(inp.now_s, State.WAITING_FOR_PILOT, FAILSAFE_WAIT_REASON)
            return self._silent(inp)
        self.machine.change(inp.now_s, State.WAITING_FOR_PILOT, self.machine.switch_reason())
        if not inp.pose_ok:
            return self._silent(inp)
        pose = self.vehicle.pose
        assert pose is not None
        return self._out(inp, hold(pose.pos_ned_m, SetpointKind.PRESTREAM), self._distance_to_goal())

    def _on_navigating(self, inp: CycleInputs) -> CycleOutput:
        blocked = self._blocked(inp)
        if blocked is not None:
            return blocked
        if self.machine.pilot_must_switch():
            return self._wait_for_pilot(inp)
        if not (inp.pose_ok and inp.ranges_ok):
            return self._hold_stale(inp)
        return self._fly(inp)

    def _on_holding(self, inp: CycleInputs) -> CycleOutput:
        blocked = self._blocked(inp)
        if blocked is not None:
            return blocked
        if self.machine.pilot_must_switch():
            return self._wait_for_pilot(inp)  # e.g. the goal came before the first pose: now the pilot is asked
        if not (inp.pose_ok and inp.ranges_ok):
            return self._hold_stale(inp)
        if self.recovery.holding(inp.now_s):
            return self._out(inp, self.hold.setpoint(self.vehicle.pose, pose_fresh=True), self._distance_to_goal())
        self.hold.reset()
        self.machine.change(inp.now_s, State.NAVIGATING, "inputs fresh again: navigating")
        return self._fly(inp)

    def _on_done(self, inp: CycleInputs) -> CycleOutput:
        """ARRIVED and STUCK: hold where the state was entered (while the pose is fresh)."""
        blocked = self._blocked(inp)
        if blocked is not None:
            return blocked
        sp = self.hold.setpoint(self.vehicle.pose, pose_fresh=inp.pose_ok)
        return self._out(inp, sp, self._distance_to_goal())

    def _blocked(self, inp: CycleInputs) -> CycleOutput | None:
        """Silence when there is no goal or pose (NAVIGATING -> HOLDING without a pose), or while suspended."""
        goal, pose, machine = self.goal, self.vehicle.pose, self.machine
        if goal.route is None and goal.held is None and pose is not None and machine.state is State.HOLDING:
            return self.recovery.goalless_hold(inp)  # restarted mid-flight (``Recovery.restart_hold``)
        if goal.route is None or pose is None:
            # Held: the service checks the goal at the next pose (one may have come while the link was lost).
            if goal.has_goal and pose is None and machine.state in WANTS_POSE:
                machine.enter_hold(inp.now_s, State.HOLDING, self.vehicle.no_pose_reason())
            return self._silent(inp)
        if self.suspended:
            return self._silent(inp)
        return None if self.recovery.pose_confirmed else self.recovery.brake(inp)

    def _hold_stale(self, inp: CycleInputs) -> CycleOutput:
        dist = self._distance_to_goal()
        reason = _stale_reason(inp, ranges_seen=self.obstacles.ranges_t_s is not None)
        self.machine.enter_hold(inp.now_s, State.HOLDING, reason)
        return self._out(inp, self.hold.setpoint(self.vehicle.pose, pose_fresh=inp.pose_ok), dist)

    def _wait_for_pilot(self, inp: CycleInputs) -> CycleOutput:
        self.steps.target = None
        self.hold.reset()  # a hold point of HOLDING is not where the pilot will have flown it by the switch
        self.machine.change(inp.now_s, State.WAITING_FOR_PILOT, self.machine.switch_reason())
        return self._on_waiting(inp)

    def _fly(self, inp: CycleInputs) -> CycleOutput:
        pose = self.vehicle.pose
        assert pose is not None
        pos = np.asarray(pose.pos_ned_m, dtype=np.float64)
        if not self.goal.engaged:
            # Taking over: hold here until the autopilot reports GUIDED/OFFBOARD.
            return self._out(inp, hold(pos, SetpointKind.PRESTREAM), self._distance_to_goal())
        assert self.goal.route is not None
        leg, dist = self.legs.current(self.goal.route, pos, inp.now_s)
        if leg is None:
            self.machine.enter_hold(inp.now_s, State.ARRIVED, f"arrived at goal ({dist:.2f} m)")
            return self._out(inp, self.hold.setpoint(pose, pose_fresh=True), dist)
        obstacles = _near(inp.points, pos, self.p.dim, self.p.max_range_m + 1.0)  # sensor range + a step
        tracked = self.steps.track(pos, obstacles, inp.now_s, inp.nearest_m)
        n = int(obstacles.shape[0])
        if tracked is not None:
            out = self._out(inp, tracked, dist, decision=Decision.TRACKING.value, n_obstacles=n)
        else:
            out = self._plan(inp, pos, leg, dist, obstacles)
        self.steps.watch(out, pose, obstacles)
        return self.steps.known_direction(out, pos, self.obstacles)

    def _plan(self, inp: CycleInputs, pos: FloatArray, leg: Leg, dist: float, obstacles: FloatArray) -> CycleOutput:
        """Plan the next step from the bacteria point just reached (the paper's path), else from the pose."""
        steps = self.steps
        origin = pos if steps.target is None else steps.target
        steps.target = None
        self.counters.planner_steps += 1
        dim = self.p.dim
        decision = self.planner.step(origin[:dim].copy(), leg.target_ned_m[:dim].copy(), obstacles[:, :dim], self.rng)
        reason = decision.reason.name
        leg.streak = 0 if reason == Decision.GREEDY.value else leg.streak + 1
        self.counters.decision(reason)
        n = int(obstacles.shape[0])
        give_up = self.legs.give_up(leg, inp.now_s)
        if reason == Decision.GAVE_UP.value:
            give_up = _planner_give_up(self.planner)
        if give_up is not None:
            self.machine.enter_hold(inp.now_s, State.STUCK, give_up)
            sp_hold = self.hold.setpoint(self.vehicle.pose, pose_fresh=True)
            return self._out(inp, sp_hold, dist, decision=reason, n_obstacles=n)
        nxt = decision.next_point_m
        if nxt is None:
            sp = hold(pos)  # a local minimum inside the budget: wait here (memory may change)
        else:
            target = np.empty(3)
            target[:dim] = np.asarray(nxt, dtype=np.float64)[:dim]
            if dim == 2:
                target[2] = leg.target_ned_m[2]
            steps.set(target, inp.now_s)
            gap = float(np.linalg.norm((target - pos)[:dim]))
            speed = steps.approach_speed(gap, inp.nearest_m)
            sp = steps.setpoint(pos, target, speed, obstacles)
        return self._out(inp, sp, dist, decision=reason, n_obstacles=n)

    def _distance_to_goal(self) -> float:
        route, pose = self.goal.route, self.vehicle.pose
        assert route is not None and pose is not None
        return self.legs.provisional_distance(route, pose.pos_ned_m)

    def _silent(self, inp: CycleInputs) -> CycleOutput:
        return CycleOutput(t_s=inp.now_s, state=self.machine.state, setpoint=None, nearest_obstacle_m=inp.nearest_m)

    def _out(self, inp: CycleInputs, sp: Setpoint | None, dist: float, **kw: Any) -> CycleOutput:
        return CycleOutput(
            t_s=inp.now_s,
            state=self.machine.state,
            setpoint=sp,
            distance_to_goal_m=dist,
            nearest_obstacle_m=inp.nearest_m,
            **kw,
        )


_HANDLERS: dict[State, Callable[[CycleHandlers, CycleInputs], CycleOutput]] = {
    State.IDLE: CycleHandlers._on_idle,
    State.LINK_LOST: CycleHandlers._on_idle,  # left in ``Navigator.cycle`` as soon as the link is alive
    State.WAITING_FOR_PILOT: CycleHandlers._on_waiting,
    State.NAVIGATING: CycleHandlers._on_navigating,
    State.HOLDING: CycleHandlers._on_holding,
    State.ARRIVED: CycleHandlers._on_done,
    State.STUCK: CycleHandlers._on_done,
}
"""One handler per state, for a cycle with the autopilot link alive."""


def _near(points: FloatArray, pos: FloatArray, dim: int, reach_m: float) -> FloatArray:
    """Obstacle points within ``reach_m`` (those that can matter this step), vectorised."""
    if points.shape[0] == 0:
        return np.zeros((0, 3))
    d = points[:, :dim] - pos[:dim]
    keep = np.einsum("ij,ij->i", d, d) <= reach_m * reach_m
    return np.asarray(points[keep], dtype=np.float64)


def _stale_reason(inp: CycleInputs, *, ranges_seen: bool) -> str:
    ranges = "ranges stale" if ranges_seen else "no ranges yet"
    if not inp.pose_ok:
        return f"pose stale, {ranges}: holding position" if not inp.ranges_ok else "pose stale: holding position"
    return f"{ranges}: holding position"


def _planner_give_up(planner: object) -> str:
    """The STUCK reason of a planner that gave up, with its cause where it says one (bapf-nav's
    ``give_up_cause``; looked up by name, as ``reset`` in ``restart_planner``, so that it reaches through the
    service's ``observe.PlanTap``, which forwards attributes by ``__getattr__``)."""
    give_up_cause = getattr(planner, "give_up_cause", None)
    if callable(give_up_cause):
        cause = give_up_cause()
        if isinstance(cause, GiveUp) and cause is not GiveUp.NONE:
            return f"planner gave up: {cause.text}"
    return "planner gave up"
