"""The navigator's vocabulary: its states and decisions, what it reads (parameters, obstacles, planner) and what a
cycle reports. Values only; the parts that act on them are the other modules of this package."""

from __future__ import annotations

import dataclasses
import enum
from dataclasses import dataclass
from typing import Protocol

import numpy as np
import numpy.typing as npt

from apf_companion.linkquality import CautionParams
from apf_companion.setpoint import Setpoint

__all__ = [
    "ENGAGED_STATES",
    "HOLD_STATES",
    "WANTS_POSE",
    "Counters",
    "CycleInputs",
    "CycleOutput",
    "Decision",
    "DecisionLike",
    "FloatArray",
    "NavigatorParams",
    "ObstacleView",
    "PlannerLike",
    "State",
    "StateChange",
]

FloatArray = npt.NDArray[np.float64]


class State(enum.Enum):
    """Service states (reported in STATUSTEXT, HEARTBEAT.system_status and the zenoh status)."""

    IDLE = "IDLE"
    WAITING_FOR_PILOT = "WAITING_FOR_PILOT"
    NAVIGATING = "NAVIGATING"
    ARRIVED = "ARRIVED"
    HOLDING = "HOLDING"
    STUCK = "STUCK"
    LINK_LOST = "LINK_LOST"


class Decision(enum.Enum):
    """What a cycle decided about the next step (``CycleOutput.decision``; the planner's own reasons plus
    TRACKING, still flying to the previous bacteria point)."""

    GREEDY = "GREEDY"
    RANDOM_WALK = "RANDOM_WALK"
    LOCAL_MINIMUM = "LOCAL_MINIMUM"
    #: The planner gave up (bapf-nav: no way on the remembered map, no progress for its patience, or a goal
    #: outside its flying area; the STUCK reason says which, ``planning.GiveUp``).
    GAVE_UP = "GAVE_UP"
    TRACKING = "TRACKING"


class ObstacleView(Protocol):
    """What the navigator reads of the obstacle memory; the perception front end
    (apf_companion.perception.PerceptionFrontEnd) is its one writer."""

    def points(self, now_s: float) -> FloatArray: ...

    @property
    def ranges_t_s(self) -> float | None: ...

    def direction_fresh(self, bearing_ned_rad: float, now_s: float) -> bool: ...

    def look_offset_rad(self, now_s: float) -> float: ...


class DecisionLike(Protocol):
    @property
    def next_point_m(self) -> FloatArray | None: ...

    @property
    def reason(self) -> enum.Enum: ...


class PlannerLike(Protocol):
    """One step of a planner (apf_companion.planning.Planner)."""

    def step(
        self, position_m: FloatArray, target_m: FloatArray, obstacles_m: FloatArray, rng: np.random.Generator
    ) -> DecisionLike: ...


@dataclass(frozen=True, slots=True, kw_only=True)
class NavigatorParams:
    """Everything the navigator reads of the configuration (built by ``apf_companion.builders.navigator_params``).

    Attributes:
        dim: 2 (north, east; altitude held) or 3.
        heartbeat_timeout_s: No autopilot HEARTBEAT for this long = LINK_LOST [s].
        pose_max_age_s, ranges_max_age_s: Freshness limits of the inputs [s].
        require_ranges: False = fly without range data (ranges always count as fresh).
        arrival_radius_m: Within this of a waypoint it is reached [m].
        replan_radius_m: Within this of a bacteria point the next step is planned from it [m].
        cruise_speed_m_s: Feed-forward speed along a step [m/s].
        max_range_m: Obstacle points beyond this (+ 1 m) are not given to the planner [m].
        random_walk_budget: Non-greedy decisions in a row before STUCK.
        progress_timeout_s: No progress for this long = STUCK [s].
        dry_run: Nothing moves the vehicle along the plan: plan from the pose every cycle.
        step_m: The planner's step (bacteria ring radius) [m].
        target_guard_m: A bacteria point being flown to is dropped (and the planner re-run) once a remembered
            obstacle lies closer than this to it; the planner's rho_l for CR-BAPF / CR-BAPF*, 0 = no check.
        clearance_m: The clearance the planner keeps (its rho_l). Within ``clearance_m + 2 step_m`` of a
            remembered obstacle the feed-forward speed falls linearly to ``SLOW_FRACTION`` of cruise at
            ``clearance_m``, so the vehicle turns at the bacteria points there without swinging wide (0 = off).
        reset_hold_s: After a position reset (``position_reset``) hold this long before navigating [s].
        silent_horizon_s, silent_drift_m: Safe when silent: the last setpoint's feed-forward may carry the vehicle
            at most ``silent_drift_m`` past its position over ``silent_horizon_s`` (GUID_TIMEOUT), never towards a
            remembered obstacle (``apf_companion.setpoint.silent_safe_velocity``).
        brake_accel_m_s2, brake_latency_s, tracking_clearance_m: The braking envelope
            (``apf_companion.envelope``): the feed-forward never exceeds the speed that can still stop
            ``tracking_clearance_m`` short of a remembered point along the step; cycles whose reported velocity
            could carry the vehicle closer than that are counted (``envelope_warnings``). 0 = off.
        caution: Fewer setpoints, more caution: on a lossy link (``apf_companion.linkquality``) each setpoint
            reaches a fraction of a step ahead and its feed-forward speed and silent drift shrink by that fraction.
        resume_after_link_lost: LINK_LOST keeps the goal; when the heartbeat returns with the autopilot still in
            GUIDED / OFFBOARD the service holds, then navigates on once the inputs are fresh. False: the goal is
            dropped (IDLE once the link is back; motion only after a new goal).
        takeover: The service switches the autopilot to GUIDED / OFFBOARD itself (``autopilot.takeover``); the
            navigator streams holds meanwhile, NAVIGATING. False: a goal waits in WAITING_FOR_PILOT until the
            autopilot's HEARTBEAT shows that mode.
        guided_mode: The name of that mode, for the pilot ("GUIDED" ArduPilot, "OFFBOARD" PX4).
        setpoints_end_failsafe: The autopilot returns to that mode by itself when setpoints come back after its
            setpoint-loss failsafe (PX4: the offboard loss is a mode fallback that keeps OFFBOARD as the user's
            intended mode and clears with its condition, src/modules/commander/failsafe/failsafe.cpp
            ``checkModeFallback``). WAITING_FOR_PILOT then streams no holds while the autopilot's HEARTBEAT reports
            a failsafe (system_status CRITICAL): they would put the vehicle back into OFFBOARD with no pilot's switch.
        yaw_travel: Command the heading (``[autopilot] yaw`` "travel"; navigation.heading): each navigation and hold
            setpoint carries the yaw that points the range sensor along the step flown
            (``ObstacleView.look_offset_rad``), a hold refused towards a sector without ranges the yaw that points it
            that way. False: no yaw (the autopilot's own heading).
    """

    dim: int = 2
    heartbeat_timeout_s: float = 3.0
    pose_max_age_s: float = 0.5
    ranges_max_age_s: float = 0.5
    require_ranges: bool = True
    arrival_radius_m: float = 0.7
    replan_radius_m: float = 0.1
    cruise_speed_m_s: float = 1.0
    max_range_m: float = 8.0
    random_walk_budget: int = 100
    progress_timeout_s: float = 60.0
    dry_run: bool = False
    step_m: float = 0.4
    target_guard_m: float = 0.0
    clearance_m: float = 0.0
    reset_hold_s: float = 2.0
    silent_horizon_s: float = 3.0
    silent_drift_m: float = 1.0
    brake_accel_m_s2: float = 0.0
    brake_latency_s: float = 0.5
    tracking_clearance_m: float = 0.0
    caution: CautionParams = dataclasses.field(default_factory=CautionParams)
    resume_after_link_lost: bool = True
    takeover: bool = True
    guided_mode: str = "GUIDED"
    setpoints_end_failsafe: bool = False
    yaw_travel: bool = False


@dataclass(frozen=True, slots=True, kw_only=True)
class StateChange:
    """One transition, with a human reason (it becomes a STATUSTEXT)."""

    t_s: float
    old: State
    new: State
    reason: str


@dataclass(frozen=True, slots=True, kw_only=True)
class CycleOutput:
    """Everything one cycle decided.

    Attributes:
        t_s: Cycle time (service clock) [s].
        state: State after the cycle.
        setpoint: The setpoint to send now, or None (send nothing).
        changes: Transitions in this cycle, oldest first.
        decision: The planner's reason name ("GREEDY", "RANDOM_WALK", "LOCAL_MINIMUM") if it ran, "TRACKING"
            while it flies on to the previous bacteria point (``Decision`` values).
        distance_to_goal_m: Distance to the active waypoint (horizontal in 2D), if a goal and pose exist.
        nearest_obstacle_m: Distance to the nearest remembered obstacle point, if any.
        n_obstacles: Remembered obstacle points used this cycle.
        caution: The step fraction the link quality allowed (1 = a clean link; ``linkquality.caution_scale``).
    """

    t_s: float
    state: State
    setpoint: Setpoint | None
    changes: tuple[StateChange, ...] = ()
    decision: str | None = None
    distance_to_goal_m: float | None = None
    nearest_obstacle_m: float | None = None
    n_obstacles: int = 0
    caution: float = 1.0


@dataclass(slots=True)
class Counters:
    """The navigator's counters (``Navigator.counts``, in the status prefixed ``nav_``); each part counts its own."""

    cycles: int = 0
    setpoints: int = 0
    planner_steps: int = 0
    greedy: int = 0
    random_walk: int = 0
    local_minimum: int = 0
    stale_pose_cycles: int = 0
    stale_range_cycles: int = 0
    rejected_poses: int = 0
    goals: int = 0
    dropped_targets: int = 0
    unknown_direction_holds: int = 0  # a step towards a sector without recent ranges: held instead
    envelope_caps: int = 0  # feed-forward cut to the speed that can still stop short of the tracking clearance
    envelope_warnings: int = 0  # the reported velocity could carry the vehicle inside it before it can stop
    shortened_setpoints: int = 0  # navigation setpoints shortened for a lossy link (``caution`` < 1)
    unconfirmed_pose_cycles: int = 0  # braked or silent: the pose gate's anchor is not confirmed yet
    prestream_setpoints: int = 0  # holds streamed before GUIDED / OFFBOARD (taking over, waiting for the pilot)

    def decision(self, reason: str) -> None:
        """Count a planner decision by its ``Decision`` name."""
        if reason == Decision.GREEDY.value:
            self.greedy += 1
        elif reason == Decision.RANDOM_WALK.value:
            self.random_walk += 1
        else:
            self.local_minimum += 1


@dataclass(frozen=True, slots=True)
class CycleInputs:
    """What one cycle sees: the time, the remembered obstacles and the freshness of the inputs."""

    now_s: float
    points: FloatArray
    nearest_m: float | None
    pose_ok: bool
    ranges_ok: bool


HOLD_STATES = (State.HOLDING, State.ARRIVED, State.STUCK)
WANTS_POSE = (State.NAVIGATING, State.HOLDING, State.WAITING_FOR_PILOT)  # a goal without a pose: HOLDING, saying so
ENGAGED_STATES = (State.NAVIGATING, State.HOLDING, State.ARRIVED, State.STUCK)
