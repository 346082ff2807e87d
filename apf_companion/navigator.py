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
  the pose is stale too (the autopilot's position hold / OFFBOARD-loss failsafe acts). Falling silent forgets the
  hold point: a fresh pose with the ranges still stale holds anew at that pose (``HoldPoint``). Fresh inputs ->
  back to NAVIGATING.
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

``Navigator`` is the facade the service uses; its parts (apf_companion/navigation/) each own their state:

- ``VehicleLink`` (vehicle.py): the last HEARTBEAT and its mode, the pose, the EKF flag; freshness.
- ``GoalSlot`` (goalslot.py): the goal (``route`` / ``held``) and whether the autopilot is engaged for it.
- ``StateMachine`` (machine.py): the state, the changes not yet reported, the transitions.
- ``CycleHandlers`` (cycle.py): one handler per state (the planner, its generator, ``suspended``).
- ``StepTracker``, ``HoldPoint`` (tracking.py), ``Legs`` (legs.py): the bacteria point flown to, the hold point,
  the leg and its progress.
- ``Recovery`` (recovery.py): a lost link, a position reset, a restart mid-flight.

The navigator reads the configuration only as a frozen ``NavigatorParams`` and the obstacles only through
``ObstacleView`` (the perception front end writes them).
"""

from __future__ import annotations

import dataclasses

import numpy as np

from apf_companion.goal import Route
from apf_companion.linkquality import CLEAN_LINK, LinkQuality, caution_scale
from apf_companion.navigation.cycle import CycleHandlers
from apf_companion.navigation.goalslot import GoalSlot
from apf_companion.navigation.heading import Heading
from apf_companion.navigation.legs import Legs
from apf_companion.navigation.machine import StateMachine
from apf_companion.navigation.model import (
    Counters,
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
from apf_companion.navigation.recovery import Recovery
from apf_companion.navigation.tracking import HoldPoint, StepTracker, shortened
from apf_companion.navigation.vehicle import VehicleLink
from apf_companion.perception import Pose
from apf_companion.setpoint import SetpointKind

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
        self._params = params
        self.obstacles = obstacles
        self.dim = params.dim
        self.counters = Counters()
        self.last_output: CycleOutput | None = None
        self.vehicle = VehicleLink(params, obstacles, self.counters)
        self.goal = GoalSlot()
        self._steps = StepTracker(params, self.counters)
        self._hold = HoldPoint()
        self._heading = Heading()
        self._legs = Legs(params, self._steps)
        steps, hold = self._steps, self._hold
        self.machine = StateMachine(
            params, goal=self.goal, vehicle=self.vehicle, steps=steps, hold=hold, legs=self._legs
        )
        self.recovery = Recovery(  # link loss and position resets (``recovery.position_reset``)
            params,
            machine=self.machine,
            goal=self.goal,
            vehicle=self.vehicle,
            steps=steps,
            hold=hold,
            counters=self.counters,
        )
        self._handlers = CycleHandlers(
            params,
            planner=planner,
            rng=rng,
            obstacles=obstacles,
            counters=self.counters,
            machine=self.machine,
            goal=self.goal,
            vehicle=self.vehicle,
            legs=self._legs,
            recovery=self.recovery,
            steps=steps,
            hold=hold,
        )

    def update_pose(self, pose: Pose) -> bool:
        """A new pose (``VehicleLink.update_pose``: an older-or-equal timestamp is refused). Returns whether it
        was accepted."""
        return self.vehicle.update_pose(pose)

    def autopilot_heartbeat(self, now_s: float, *, mode_ok: bool, failsafe: bool = False) -> None:
        """An autopilot HEARTBEAT; ``mode_ok`` = its custom_mode is GUIDED (ArduPilot) / OFFBOARD (PX4);
        ``failsafe`` = its system_status is CRITICAL (PX4 and ArduPilot: a failsafe is active)."""
        self.vehicle.heard(now_s, mode_ok=mode_ok, failsafe=failsafe)
        self.machine.mode_seen(now_s, mode_ok=mode_ok)

    def set_route(self, route: Route, now_s: float) -> bool:
        """A new goal or route replaces the active (or held) one. Refused (False) while the link is lost."""
        if not self.accepts_goals(now_s):
            return False
        self.counters.goals += 1
        self.goal.fly(route, engaged=self.vehicle.mode_ok)
        self._handlers.restart_planner()
        self._restart_leg()
        self._hold.reset()
        self.machine.go(now_s, f"new goal from {route.source}: {route.to_json_list()[-1]}")
        return True

    def hold_goal(self, route: Route, now_s: float) -> bool:
        """Take ``route`` (replacing the active or held goal) without flying it: the service cannot check it yet (no
        position for ``goal.max_distance_m``). HOLDING, silent, saying why there is no position, until
        ``set_route`` (checked: flown) or ``clear_route`` (refused); a lost link keeps or drops it as a flown goal
        (``resume_after_link_lost``). Refused (False) while the link is lost, as ``set_route`` would refuse it."""
        if not self.accepts_goals(now_s):
            return False
        self.goal.hold(route)
        self._legs.leg = None
        self.machine.enter_hold(now_s, State.HOLDING, self.vehicle.no_pose_reason())
        return True

    def accepts_goals(self, now_s: float) -> bool:
        """A goal can be taken now: the link is alive and LINK_LOST has been left."""
        return self.state is not State.LINK_LOST and self.vehicle.link_alive(now_s)

    def clear_route(self, now_s: float, reason: str) -> None:
        """Forget the goal (operator stop): IDLE, send nothing."""
        self.machine.drop_goal(now_s, State.IDLE, reason)

    def drain_changes(self) -> list[StateChange]:
        """State changes recorded outside ``cycle`` (``set_route``, heartbeats), oldest first; clears them."""
        return self.machine.drain()

    def suspend(self) -> None:
        """Stop sending setpoints (the service is arming / taking off)."""
        self._handlers.suspended = True

    def resume(self) -> None:
        """Send setpoints again; the leg restarts so "keep altitude" means the altitude reached meanwhile."""
        self._handlers.suspended = False
        self._restart_leg()

    def reconfigure(self, params: NavigatorParams, planner: PlannerLike) -> None:
        """New parameters and planner for every part (``reconfigure``); the step being flown is dropped."""
        if params.dim != self.dim:
            msg = f"internal: the dimension cannot change at run time ({self.dim} -> {params.dim})"
            raise AssertionError(msg)
        self._params = params
        for part in (self.vehicle, self.machine, self.recovery, self._handlers, self._steps, self._legs):
            part.p = params
        self._handlers.planner = planner
        self._steps.target = None

    def cycle(self, now_s: float, link: LinkQuality = CLEAN_LINK) -> CycleOutput:
        """One cycle at service time ``now_s``: state and setpoint (or silence); a lossy ``link`` shortens steps."""
        self.counters.cycles += 1
        self._steps.caution = caution_scale(link, self._params.caution)
        if not self.vehicle.link_alive(now_s):
            self.recovery.link_dead(now_s)
            out = CycleOutput(t_s=now_s, state=self.state, setpoint=None)
        else:
            if self.state is State.LINK_LOST:
                self.recovery.link_back(now_s)
            out = self._handlers.run(self.vehicle.inputs(now_s))
            if self._params.yaw_travel:
                pose = self.vehicle.pose
                pos = None if pose is None else np.asarray(pose.pos_ned_m)
                sp = self._heading.apply(out.setpoint, pos, self.obstacles.look_offset_rad(now_s))
                out = dataclasses.replace(out, setpoint=sp)
        if out.setpoint is not None:
            self.counters.setpoints += 1
            self.counters.prestream_setpoints += out.setpoint.kind is SetpointKind.PRESTREAM
        changes = tuple(self.machine.drain())
        out = dataclasses.replace(out, state=self.state, changes=changes, caution=self._steps.caution)
        self.last_output = out
        return out

    def _restart_leg(self) -> None:
        self._legs.leg = None
        self._steps.target = None
        self._heading.reset()

    # What it reports, read by the service, its parts and the tests: each from the part that owns it.
    @property
    def params(self) -> NavigatorParams:
        return self._params

    @property
    def planner(self) -> PlannerLike:
        return self._handlers.planner

    @property
    def rng(self) -> np.random.Generator:
        return self._handlers.rng

    @rng.setter
    def rng(self, rng: np.random.Generator) -> None:
        self._handlers.rng = rng

    @property
    def state(self) -> State:
        return self.machine.state

    @property
    def suspended(self) -> bool:
        return self._handlers.suspended

    @property
    def pose(self) -> Pose | None:
        return self.vehicle.pose

    @property
    def mode_ok(self) -> bool:
        """The latest HEARTBEAT showed GUIDED / OFFBOARD."""
        return self.vehicle.mode_ok

    @property
    def ekf_ready(self) -> bool | None:
        """EKF_STATUS_REPORT has a horizontal position (None = not reported); the handlers set it."""
        return self.vehicle.ekf_ready

    @ekf_ready.setter
    def ekf_ready(self, ready: bool | None) -> None:
        self.vehicle.ekf_ready = ready

    @property
    def route(self) -> Route | None:
        """The goal flown."""
        return self.goal.route

    @property
    def held(self) -> Route | None:
        """A goal taken but not flown until it can be checked (``hold_goal``)."""
        return self.goal.held

    @property
    def has_goal(self) -> bool:
        """A goal is flown (``route``) or held for its check (``held``)."""
        return self.goal.has_goal

    @property
    def engaged(self) -> bool:
        """The autopilot has been seen in GUIDED/OFFBOARD for this route."""
        return self.goal.engaged

    def link_alive(self, now_s: float) -> bool:
        return self.vehicle.link_alive(now_s)

    def heartbeat_age_s(self, now_s: float) -> float | None:
        """Time since the last autopilot HEARTBEAT [s]; None before the first."""
        return self.vehicle.heartbeat_age_s(now_s)

    def pose_fresh(self, now_s: float) -> bool:
        return self.vehicle.pose_fresh(now_s)

    def ranges_fresh(self, now_s: float) -> bool:
        return self.vehicle.ranges_fresh(now_s)

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
        """The feed-forward speed towards a bacteria point ``gap_m`` away (``StepTracker.approach_speed``)."""
        return self._steps.approach_speed(gap_m, nearest_m)


def reconfigure(nav: Navigator, params: NavigatorParams, planner: PlannerLike) -> None:
    """Swap the navigator's parameters and planner (a PARAM_SET at run time, apf_companion.params).

    Called between cycles (the service runs input handling and cycles on one event loop). The bacteria point
    being flown to was planned with the old parameters, so it is dropped and the next cycle plans afresh; the
    goal, the leg's progress and the state are kept. The dimension cannot change at run time.
    """
    nav.reconfigure(params, planner)
