"""The service's decision core: state machine and planning cycle, pure and clock-injected.

No sockets, no asyncio, no wall clock: the service feeds inputs stamped with its own monotonic clock and calls
``cycle(now_s)`` at the cycle rate; tests drive it with a fake clock. One cycle returns at most one setpoint, and
a setpoint is only ever computed from inputs fresh at ``now_s`` (pose younger than ``pose_max_age_s``, ranges
younger than ``ranges_max_age_s``); nothing re-sends an old setpoint.

States (the README's Service section has the diagram):

- IDLE: no goal (or the pilot took the vehicle out of GUIDED/OFFBOARD). Sends nothing.
- NAVIGATING: a goal and fresh inputs. Before the autopilot is in GUIDED/OFFBOARD it streams holds at the
  current position (PX4 needs setpoints before it accepts OFFBOARD); then runs the planner every cycle and
  sends its next point with velocity feed-forward.
- HOLDING: pose or ranges stale. In the first HOLDING cycle it commands a hold at the last known position;
  after that it keeps commanding that hold only while the pose is fresh (ranges stale), and falls silent when
  the pose is stale too (the autopilot's position hold / OFFBOARD-loss failsafe acts). Fresh inputs -> back to
  NAVIGATING.
- ARRIVED: within ``arrival_radius_m`` of the last waypoint: hold where it is (while the pose is fresh).
- STUCK: the planner found no greedy move for ``random_walk_budget`` cycles in a row, or no progress for
  ``progress_timeout_s``: hold and report. A new goal restarts.
- LINK_LOST: no autopilot HEARTBEAT for ``heartbeat_timeout_s``: send nothing; the goal is dropped, so motion
  only resumes after a new goal once the link is back (state IDLE).
"""

from __future__ import annotations

import enum
import math
from dataclasses import dataclass
from typing import Protocol

import numpy as np
import numpy.typing as npt

from apf_companion.config import ServiceConfig
from apf_companion.goal import Route
from apf_companion.perception import Pose
from apf_companion.setpoint import Setpoint, SetpointKind, hold, navigate

__all__ = ["CycleOutput", "Navigator", "ObstacleStore", "PlannerLike", "State", "StateChange"]

FloatArray = npt.NDArray[np.float64]
PROGRESS_EPS_M = 0.1  # a new best distance to the goal must beat the old by this much to count as progress
SLOW_FRACTION = 0.2  # feed-forward speed next to an obstacle, as a fraction of cruise


class State(enum.Enum):
    """Service states (reported in STATUSTEXT, HEARTBEAT.system_status and the zenoh status)."""

    IDLE = "IDLE"
    NAVIGATING = "NAVIGATING"
    ARRIVED = "ARRIVED"
    HOLDING = "HOLDING"
    STUCK = "STUCK"
    LINK_LOST = "LINK_LOST"


class ObstacleStore(Protocol):
    """What the navigator needs of an obstacle memory (apf_companion.perception.ObstacleMemory)."""

    def add(self, points_ned: FloatArray, t_s: float) -> None: ...

    def points(self, now_s: float) -> FloatArray: ...


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
        decision: The planner's reason name ("GREEDY", "RANDOM_WALK", "LOCAL_MINIMUM") if it ran.
        distance_to_goal_m: Distance to the active waypoint (horizontal in 2D), if a goal and pose exist.
        nearest_obstacle_m: Distance to the nearest remembered obstacle point, if any.
        n_obstacles: Remembered obstacle points used this cycle.
    """

    t_s: float
    state: State
    setpoint: Setpoint | None
    changes: tuple[StateChange, ...] = ()
    decision: str | None = None
    distance_to_goal_m: float | None = None
    nearest_obstacle_m: float | None = None
    n_obstacles: int = 0


@dataclass(slots=True)
class _Counters:
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


@dataclass(slots=True)
class _Leg:
    index: int
    target_ned_m: FloatArray  # (3,), down resolved
    best_dist_m: float = math.inf
    best_t_s: float = 0.0
    streak: int = 0  # consecutive non-greedy decisions


class Navigator:
    """The decision core. Feed it inputs, call ``cycle(now_s)`` at the cycle rate.

    Args:
        config: The validated service configuration.
        planner: A planner (``get_planner(name, params)``) whose dimension matches ``config.planner.dim``.
        memory: Where obstacle points live (expiry and merging are the memory's).
        rng: The random walk's generator.
        now_s: Service clock at construction [s]; the heartbeat timeout counts from here.
        step_m: The planner's step (bacteria ring radius) [m].
        target_guard_m: A bacteria point being flown to is dropped (and the planner re-run) once a remembered
            obstacle lies closer than this to it; the planner's rho_l for CR-BAPF / CR-BAPF*, 0 = no check.
        clearance_m: The clearance the planner keeps (its rho_l). Within ``clearance_m + 2 step_m`` of a
            remembered obstacle the feed-forward speed falls linearly to ``SLOW_FRACTION`` of cruise at
            ``clearance_m``, so the vehicle turns at the bacteria points there without swinging wide (0 = off).
    """

    def __init__(
        self,
        *,
        config: ServiceConfig,
        planner: PlannerLike,
        memory: ObstacleStore,
        rng: np.random.Generator,
        now_s: float,
        step_m: float = 0.4,
        target_guard_m: float = 0.0,
        clearance_m: float = 0.0,
    ) -> None:
        self.config = config
        self.step_m = step_m
        self.target_guard_m = target_guard_m
        self.clearance_m = clearance_m
        self._step_target: FloatArray | None = None
        self._step_target_t = 0.0
        self.planner = planner
        self.memory = memory
        self.rng = rng
        self.dim = config.planner.dim
        self.state = State.IDLE
        self.counters = _Counters()
        self.pose: Pose | None = None
        self.route: Route | None = None
        self.engaged = False  # the autopilot has been seen in GUIDED/OFFBOARD for this route
        self.mode_ok = False  # latest HEARTBEAT: autopilot is in GUIDED/OFFBOARD
        self.suspended = False  # the service is busy with arming/takeoff: no setpoints
        self._leg: _Leg | None = None
        self._last_hb_s: float | None = None
        self._created_s = now_s
        self._last_ranges_s: float | None = None
        self._hold_anchor: FloatArray | None = None
        self._hold_sent = False
        self._pending: list[StateChange] = []
        self.last_output: CycleOutput | None = None

    # ---- inputs ------------------------------------------------------------------------------------------------
    def update_pose(self, pose: Pose) -> bool:
        """A new pose (already validated finite by ``Pose``). Older-or-equal timestamps are refused (a frozen or
        replayed pose must not look fresh). Returns whether it was accepted."""
        if self.pose is not None and pose.t_s <= self.pose.t_s:
            self.counters.rejected_poses += 1
            return False
        self.pose = pose
        return True

    def update_ranges(self, points_ned_m: FloatArray, t_s: float) -> None:
        """A valid scan measured at ``t_s`` (its obstacle points, possibly none: all free is news too)."""
        if points_ned_m.shape[0]:
            self.memory.add(points_ned_m, t_s)
        if self._last_ranges_s is None or t_s > self._last_ranges_s:
            self._last_ranges_s = t_s

    def autopilot_heartbeat(self, now_s: float, *, mode_ok: bool) -> None:
        """An autopilot HEARTBEAT; ``mode_ok`` = its custom_mode is GUIDED (ArduPilot) / OFFBOARD (PX4)."""
        self._last_hb_s = now_s
        if (
            self.engaged
            and not mode_ok
            and self.state
            in (
                State.NAVIGATING,
                State.HOLDING,
                State.ARRIVED,
                State.STUCK,
            )
        ):
            # The pilot (or a failsafe) took the vehicle: never fight it; wait for a new goal.
            self._drop_route(now_s, State.IDLE, "autopilot left guided control: goal dropped")
        self.mode_ok = mode_ok
        if mode_ok and self.route is not None:
            self.engaged = True

    def set_route(self, route: Route, now_s: float) -> bool:
        """A new goal or route replaces the active one. Refused (False) while the link is lost."""
        if self.state is State.LINK_LOST or not self._link_alive(now_s):
            return False
        self.counters.goals += 1
        self.route = route
        self._leg = None
        self._step_target = None
        self._hold_anchor = None
        self._hold_sent = False
        self.engaged = self.mode_ok
        self._change(now_s, State.NAVIGATING, f"new goal from {route.source}: {route.to_json_list()[-1]}")
        return True

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
        self._leg = None
        self._step_target = None

    def clear_route(self, now_s: float, reason: str) -> None:
        """Forget the goal (operator stop): IDLE, send nothing."""
        self._drop_route(now_s, State.IDLE, reason)

    # ---- helpers -----------------------------------------------------------------------------------------------
    def _change(self, now_s: float, new: State, reason: str) -> None:
        if new is self.state:
            return
        self._pending.append(StateChange(t_s=now_s, old=self.state, new=new, reason=reason))
        self.state = new

    def _drop_route(self, now_s: float, new: State, reason: str) -> None:
        self.route = None
        self._leg = None
        self.engaged = False
        self._hold_anchor = None
        self._change(now_s, new, reason)

    def _link_alive(self, now_s: float) -> bool:
        last = self._created_s if self._last_hb_s is None else self._last_hb_s
        return self._last_hb_s is not None and now_s - last <= self.config.link.heartbeat_timeout_s

    def pose_fresh(self, now_s: float) -> bool:
        return self.pose is not None and now_s - self.pose.t_s <= self.config.cycle.pose_max_age_s

    def ranges_fresh(self, now_s: float) -> bool:
        if not self.config.sensors.require_ranges:
            return True
        last = self._last_ranges_s
        return last is not None and now_s - last <= self.config.cycle.ranges_max_age_s

    def _distance(self, a: FloatArray, b: FloatArray) -> float:
        d = a[: self.dim] - b[: self.dim]
        return float(np.sqrt(d @ d))

    def _start_leg(self, index: int, now_s: float) -> _Leg:
        assert self.route is not None and self.pose is not None
        target = np.array(self.route.waypoints_ned_m[index], dtype=np.float64)
        if math.isnan(target[2]):
            target[2] = self.pose.pos_ned_m[2]  # keep the altitude this leg starts at
        leg = _Leg(index=index, target_ned_m=target, best_t_s=now_s)
        self._leg = leg
        self._step_target = None
        return leg

    def _hold_at_anchor(self, now_s: float, *, pose_fresh: bool) -> Setpoint | None:
        """Hold at the anchor: always once (the first cycle in a holding state), then only with a fresh pose."""
        if self._hold_anchor is None:
            if self.pose is None:
                return None
            self._hold_anchor = np.array(self.pose.pos_ned_m, dtype=np.float64)
            self._hold_sent = False
        if pose_fresh or not self._hold_sent:
            self._hold_sent = True
            return hold(self._hold_anchor)
        return None

    def _enter_hold_state(self, now_s: float, new: State, reason: str) -> None:
        self._step_target = None
        if self.state not in (State.HOLDING, State.ARRIVED, State.STUCK) or new is not self.state:
            self._hold_anchor = None
            self._hold_sent = False
        self._change(now_s, new, reason)

    def nearest_obstacle(self, points: FloatArray) -> float | None:
        if self.pose is None or points.shape[0] == 0:
            return None
        d = points[:, : self.dim] - self.pose.pos_ned_m[: self.dim]
        return float(np.sqrt(np.min(np.einsum("ij,ij->i", d, d))))

    # ---- the cycle ---------------------------------------------------------------------------------------------
    def cycle(self, now_s: float) -> CycleOutput:
        """Run one cycle at service time ``now_s``: update the state and decide the setpoint (or silence)."""
        self.counters.cycles += 1
        out = self._cycle(now_s)
        if out.setpoint is not None:
            self.counters.setpoints += 1
        changes = tuple(self._pending)
        self._pending.clear()
        out = CycleOutput(
            t_s=out.t_s,
            state=self.state,
            setpoint=out.setpoint,
            changes=changes,
            decision=out.decision,
            distance_to_goal_m=out.distance_to_goal_m,
            nearest_obstacle_m=out.nearest_obstacle_m,
            n_obstacles=out.n_obstacles,
        )
        self.last_output = out
        return out

    def _cycle(self, now_s: float) -> CycleOutput:
        cfg = self.config
        if not self._link_alive(now_s):
            if self._last_hb_s is not None and self.state is not State.LINK_LOST:
                self._drop_route(now_s, State.LINK_LOST, "autopilot heartbeat lost: stopped sending")
            return CycleOutput(t_s=now_s, state=self.state, setpoint=None)
        if self.state is State.LINK_LOST:
            self._change(now_s, State.IDLE, "autopilot heartbeat back: send a new goal to fly")

        points = self.memory.points(now_s)
        nearest = self.nearest_obstacle(points)
        pose_ok = self.pose_fresh(now_s)
        ranges_ok = self.ranges_fresh(now_s)
        if not pose_ok:
            self.counters.stale_pose_cycles += 1
        if not ranges_ok:
            self.counters.stale_range_cycles += 1
        if self.route is None or self.pose is None:
            if self.route is not None and self.state is State.NAVIGATING:
                self._enter_hold_state(now_s, State.HOLDING, "no pose yet")
            return CycleOutput(t_s=now_s, state=self.state, setpoint=None, nearest_obstacle_m=nearest)
        if self.suspended:
            return CycleOutput(t_s=now_s, state=self.state, setpoint=None, nearest_obstacle_m=nearest)

        pos = np.asarray(self.pose.pos_ned_m, dtype=np.float64)
        if self._leg is not None:
            dist = self._distance(pos, self._leg.target_ned_m)
        else:
            # Not started: the leg (and its "keep altitude") is fixed only once the autopilot is engaged, so a
            # takeoff in between sets the altitude that is kept.
            provisional = np.where(np.isnan(self.route.waypoints_ned_m[0]), pos, self.route.waypoints_ned_m[0])
            dist = self._distance(pos, provisional)

        if self.state in (State.ARRIVED, State.STUCK):
            sp = self._hold_at_anchor(now_s, pose_fresh=pose_ok)
            return CycleOutput(
                t_s=now_s, state=self.state, setpoint=sp, distance_to_goal_m=dist, nearest_obstacle_m=nearest
            )

        if not (pose_ok and ranges_ok):
            what = "pose" if not pose_ok else "ranges"
            if not pose_ok and not ranges_ok:
                what = "pose and ranges"
            self._enter_hold_state(now_s, State.HOLDING, f"{what} stale: holding position")
            sp = self._hold_at_anchor(now_s, pose_fresh=pose_ok)
            return CycleOutput(
                t_s=now_s, state=self.state, setpoint=sp, distance_to_goal_m=dist, nearest_obstacle_m=nearest
            )
        if self.state is State.HOLDING:
            self._hold_anchor = None
            self._change(now_s, State.NAVIGATING, "inputs fresh again: navigating")

        if not self.engaged:
            # Taking over: hold here until the autopilot reports GUIDED/OFFBOARD.
            sp = hold(pos, SetpointKind.PRESTREAM)
            return CycleOutput(
                t_s=now_s, state=self.state, setpoint=sp, distance_to_goal_m=dist, nearest_obstacle_m=nearest
            )

        leg = self._leg if self._leg is not None else self._start_leg(0, now_s)
        dist = self._distance(pos, leg.target_ned_m)
        # Arrival (and the next leg of a route).
        while dist <= cfg.cycle.arrival_radius_m:
            assert self.route is not None
            if leg.index + 1 >= len(self.route):
                self._enter_hold_state(now_s, State.ARRIVED, f"arrived at goal ({dist:.2f} m)")
                sp = self._hold_at_anchor(now_s, pose_fresh=True)
                return CycleOutput(
                    t_s=now_s, state=self.state, setpoint=sp, distance_to_goal_m=dist, nearest_obstacle_m=nearest
                )
            leg = self._start_leg(leg.index + 1, now_s)
            dist = self._distance(pos, leg.target_ned_m)

        # Progress bookkeeping (time-based give-up, notes.md decision 7).
        if dist < leg.best_dist_m - PROGRESS_EPS_M or math.isinf(leg.best_dist_m):
            leg.best_dist_m = dist
            leg.best_t_s = now_s

        obstacles = self._near(points, pos)
        tracked = self._track_step_target(pos, obstacles, now_s, nearest)
        if tracked is not None:
            return CycleOutput(
                t_s=now_s,
                state=self.state,
                setpoint=tracked,
                decision="TRACKING",
                distance_to_goal_m=dist,
                nearest_obstacle_m=nearest,
                n_obstacles=int(obstacles.shape[0]),
            )
        # Plan the next step from the bacteria point just reached (the paper's path), else from the pose.
        origin = pos if self._step_target is None else self._step_target
        self._step_target = None
        self.counters.planner_steps += 1
        decision = self.planner.step(
            origin[: self.dim].copy(), leg.target_ned_m[: self.dim].copy(), obstacles[:, : self.dim], self.rng
        )
        reason = decision.reason.name
        if reason == "GREEDY":
            self.counters.greedy += 1
            leg.streak = 0
        elif reason == "RANDOM_WALK":
            self.counters.random_walk += 1
            leg.streak += 1
        else:
            self.counters.local_minimum += 1
            leg.streak += 1

        give_up = None
        if leg.streak > cfg.planner.random_walk_budget:
            give_up = f"stuck: no greedy move for {leg.streak} cycles"
        elif now_s - leg.best_t_s > cfg.planner.progress_timeout_s:
            give_up = f"stuck: no progress for {now_s - leg.best_t_s:.0f} s"
        if give_up is not None:
            self._enter_hold_state(now_s, State.STUCK, give_up)
            sp = self._hold_at_anchor(now_s, pose_fresh=True)
            return CycleOutput(
                t_s=now_s,
                state=self.state,
                setpoint=sp,
                decision=reason,
                distance_to_goal_m=dist,
                nearest_obstacle_m=nearest,
                n_obstacles=int(obstacles.shape[0]),
            )

        nxt = decision.next_point_m
        if nxt is None:
            sp = hold(pos)  # a local minimum inside the budget: wait here (memory may change)
        else:
            target = np.empty(3)
            target[: self.dim] = np.asarray(nxt, dtype=np.float64)[: self.dim]
            if self.dim == 2:
                target[2] = leg.target_ned_m[2]
            self._step_target = target
            self._step_target_t = now_s
            gap = float(np.linalg.norm((target - pos)[: self.dim]))
            sp = navigate(pos, target, cruise_speed_m_s=self._approach_speed(gap, nearest), dim=self.dim)
        return CycleOutput(
            t_s=now_s,
            state=self.state,
            setpoint=sp,
            decision=reason,
            distance_to_goal_m=dist,
            nearest_obstacle_m=nearest,
            n_obstacles=int(obstacles.shape[0]),
        )

    def _track_step_target(
        self, pos: FloatArray, obstacles: FloatArray, now_s: float, nearest_m: float | None
    ) -> Setpoint | None:
        """Keep flying to the current bacteria point until within ``replan_radius_m`` of it.

        The point is re-validated every cycle against the fresh obstacle memory (at least ``target_guard_m``
        from every point), the vehicle must still be near the step (within two steps of it) and must get there
        in time (three steps at the approach speed, at least 1 s); otherwise it is dropped and the planner runs from
        the pose. Returns the setpoint, or None to plan now.
        """
        target = self._step_target
        if self.config.dry_run:
            self._step_target = None  # nothing moves the vehicle along the plan: plan from the pose each cycle
            return None
        if target is None:
            return None
        d = pos[: self.dim] - target[: self.dim]
        gap = float(np.sqrt(d @ d))
        if gap <= self.config.cycle.replan_radius_m:
            return None  # reached: plan from it
        # In time: three steps at the speed flown here (cruise, or the slower speed near obstacles).
        too_long = now_s - self._step_target_t > max(
            1.0, 3.0 * self.step_m / self._approach_speed(self.step_m, nearest_m)
        )
        if gap > 2.0 * self.step_m or too_long or not self._clear(target, obstacles):
            self._step_target = None
            self.counters.dropped_targets += 1
            return None
        return navigate(pos, target, cruise_speed_m_s=self._approach_speed(gap, nearest_m), dim=self.dim)

    def _approach_speed(self, gap_m: float, nearest_m: float | None = None) -> float:
        """Feed-forward speed: cruise, tapering within one step of the point (no orbiting around it), and slower
        near obstacles (``clearance_m``): a vehicle that reaches a bacteria point at speed swings on along its old
        heading when the next step turns, towards the obstacle it is turning away from."""
        speed = self.config.cycle.cruise_speed_m_s * min(1.0, gap_m / self.step_m)
        if self.clearance_m > 0.0 and nearest_m is not None:
            span = 2.0 * self.step_m
            frac = min(1.0, max(0.0, (nearest_m - self.clearance_m) / span))
            speed *= SLOW_FRACTION + (1.0 - SLOW_FRACTION) * frac
        return speed

    def _clear(self, point: FloatArray, obstacles: FloatArray) -> bool:
        if self.target_guard_m <= 0.0 or obstacles.shape[0] == 0:
            return True
        d = obstacles[:, : self.dim] - point[: self.dim]
        return bool(np.min(np.einsum("ij,ij->i", d, d)) >= self.target_guard_m**2)

    def _near(self, points: FloatArray, pos: FloatArray) -> FloatArray:
        """Obstacle points that can matter this step (within the sensor range + a step), vectorised."""
        if points.shape[0] == 0:
            return np.zeros((0, 3))
        reach = self.config.sensors.max_range_m + 1.0
        d = points[:, : self.dim] - pos[: self.dim]
        keep = np.einsum("ij,ij->i", d, d) <= reach * reach
        return np.asarray(points[keep], dtype=np.float64)

    @property
    def active_target_ned_m(self) -> FloatArray | None:
        """The waypoint being flown to (down resolved), if any."""
        return None if self._leg is None or self.route is None else self._leg.target_ned_m

    @property
    def leg_index(self) -> int | None:
        return None if self._leg is None else self._leg.index

    def link_alive(self, now_s: float) -> bool:
        return self._link_alive(now_s)

    def counts(self) -> dict[str, int]:
        """Counters for status and tests."""
        return {name: getattr(self.counters, name) for name in self.counters.__dataclass_fields__}
