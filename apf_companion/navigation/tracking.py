"""Flying one step: the bacteria point being flown to with the feed-forward speed towards it (``StepTracker``), and
the point held in a holding state (``HoldPoint``)."""

from __future__ import annotations

import dataclasses

import numpy as np

from apf_companion.envelope import BrakingEnvelope
from apf_companion.navigation.model import Counters, CycleOutput, FloatArray, NavigatorParams, ObstacleView
from apf_companion.perception import Pose
from apf_companion.setpoint import (
    Setpoint,
    SetpointKind,
    hold,
    look_yaw,
    navigate,
    silent_safe_velocity,
    step_bearing,
    with_yaw,
)

__all__ = ["SLOW_FRACTION", "HoldPoint", "StepTracker", "shortened"]

SLOW_FRACTION = 0.2  # feed-forward speed next to an obstacle, as a fraction of cruise


def _into_unknown(view: ObstacleView, sp: Setpoint | None, pos: FloatArray, now_s: float) -> float | None:
    """The bearing (local NED [rad]) of ``sp``'s step when it goes towards an azimuth sector without recent ranges
    (``ObstacleView.direction_fresh``), else None."""
    bearing = step_bearing(sp, pos, 1e-9)
    return None if bearing is None or view.direction_fresh(bearing, now_s) else bearing


def shortened(pos: FloatArray, target: FloatArray, *, fraction: float, step_m: float, dim: int) -> FloatArray:
    """``target``, or the point ``fraction`` of a step (``step_m``) from ``pos`` on the way to it when it is further
    (horizontally in 2D; the target's altitude is kept). A target more than a step away (the vehicle lags behind
    its bacteria point) is shortened to ``fraction`` of the way. ``fraction`` 1 returns ``target``."""
    d = target[:dim] - pos[:dim]
    gap = float(np.sqrt(d @ d))
    reach_m = fraction * max(gap, step_m)
    if gap <= reach_m:
        return target
    aim = target.copy()
    aim[:dim] = pos[:dim] + d * (reach_m / gap)
    return aim


class StepTracker:
    """The bacteria point being flown to, and the feed-forward speed towards it."""

    def __init__(self, params: NavigatorParams, counters: Counters) -> None:
        self.p = params
        self.counters = counters
        self.target: FloatArray | None = None
        self.target_t_s = 0.0
        self.envelope = BrakingEnvelope(
            accel_m_s2=params.brake_accel_m_s2,
            latency_s=params.brake_latency_s,
            clearance_m=params.tracking_clearance_m,
            dim=params.dim,
        )
        self.caution = 1.0  # this cycle's ``caution_scale``: the step, speed and silent drift fraction

    def set(self, target: FloatArray, now_s: float) -> None:
        self.target = target
        self.target_t_s = now_s

    def track(self, pos: FloatArray, obstacles: FloatArray, now_s: float, nearest_m: float | None) -> Setpoint | None:
        """Keep flying to the current bacteria point until within ``replan_radius_m`` of it.

        The point is re-validated every cycle against the fresh obstacle memory (at least ``target_guard_m``
        from every point), the vehicle must still be near the step (within two steps of it) and must get there
        in time (three steps at the approach speed, at least 1 s); otherwise it is dropped and the planner runs
        from the pose. Returns the setpoint, or None to plan now.
        """
        p = self.p
        target = self.target
        if p.dry_run:
            self.target = None  # nothing moves the vehicle along the plan: plan from the pose each cycle
            return None
        if target is None:
            return None
        d = pos[: p.dim] - target[: p.dim]
        gap = float(np.sqrt(d @ d))
        if gap <= p.replan_radius_m:
            return None  # reached: plan from it
        # In time: three steps at the speed flown here (cruise, or the slower speed near obstacles).
        too_long = now_s - self.target_t_s > max(1.0, 3.0 * p.step_m / self.approach_speed(p.step_m, nearest_m))
        if gap > 2.0 * p.step_m or too_long or not self._clear(target, obstacles):
            self.target = None
            self.counters.dropped_targets += 1
            return None
        return self.setpoint(pos, target, self.approach_speed(gap, nearest_m), obstacles)

    def setpoint(self, pos: FloatArray, target: FloatArray, speed_m_s: float, obstacles: FloatArray) -> Setpoint:
        """Fly towards ``target`` at ``speed_m_s``, with the feed-forward cut to what can still stop short of the
        tracking clearance (``BrakingEnvelope``) and to what is safe if nothing follows.

        On a lossy link (``caution`` < 1) the setpoint's position is only that fraction of a step ahead on the
        way to ``target`` (``shortened``) and the silent drift allowed shrinks by the same fraction.
        """
        p = self.p
        cap = self.envelope.speed_cap_m_s(pos, target - pos, obstacles)
        if cap < speed_m_s:
            self.counters.envelope_caps += 1
            speed_m_s = cap
        self.counters.shortened_setpoints += self.caution < 1.0
        aim = shortened(pos, target, fraction=self.caution, step_m=p.step_m, dim=p.dim)
        sp = navigate(pos, aim, cruise_speed_m_s=speed_m_s, dim=p.dim)
        vel = silent_safe_velocity(
            aim,
            sp.vel_ned_m_s,
            obstacles,
            horizon_s=p.silent_horizon_s,
            max_drift_m=p.silent_drift_m * self.caution,
            clearance_m=p.clearance_m,
            dim=p.dim,
        )
        return dataclasses.replace(sp, vel_ned_m_s=vel)

    def watch(self, out: CycleOutput, pose: Pose, obstacles: FloatArray) -> None:
        """Where the vehicle can be, not where the setpoint is: count the cycles whose reported velocity, followed
        by this setpoint, could carry the vehicle inside the tracking clearance before it can stop
        (``envelope_warnings``, in the status). Only counted: overriding the plan with a brake made the paper
        planners pass closer on the simulator's ArduCopter controller (docs/hardening.md, "Tracking margin")."""
        sp = out.setpoint
        if sp is None or sp.kind is not SetpointKind.NAVIGATE:
            return
        pos = np.asarray(pose.pos_ned_m, dtype=np.float64)
        if self.envelope.breaches(pos, pose.vel_ned_m_s, np.asarray(sp.vel_ned_m_s), obstacles):
            self.counters.envelope_warnings += 1

    def known_direction(self, out: CycleOutput, pos: FloatArray, view: ObstacleView) -> CycleOutput:
        """A step towards a sector without recent ranges is not flown: hold here and plan again next cycle. With a
        commanded heading (``yaw_travel``) the hold turns the vehicle so that the centre of what its range sensors
        cover (``ObstacleView.look_offset_rad``, body FRD: 0 for a forward sensor, pi for a rear one) faces that
        direction; a sensor covering less than 360 degrees then looks there and the step is flown once its sector
        has fresh ranges."""
        bearing = _into_unknown(view, out.setpoint, pos, out.t_s)
        if bearing is None:
            return out
        self.counters.unknown_direction_holds += 1
        self.target = None
        sp = hold(pos)
        if not self.p.yaw_travel:
            return dataclasses.replace(out, setpoint=sp)
        return dataclasses.replace(out, setpoint=with_yaw(sp, look_yaw(bearing, view.look_offset_rad(out.t_s))))

    def approach_speed(self, gap_m: float, nearest_m: float | None = None) -> float:
        """Feed-forward speed: cruise, tapering within one step of the point (no orbiting around it), and slower
        near obstacles (``clearance_m``): a vehicle that reaches a bacteria point at speed swings on along its old
        heading when the next step turns, towards the obstacle it is turning away from."""
        p = self.p
        speed = p.cruise_speed_m_s * self.caution * min(1.0, gap_m / p.step_m)
        if p.clearance_m > 0.0 and nearest_m is not None:
            span = 2.0 * p.step_m
            frac = min(1.0, max(0.0, (nearest_m - p.clearance_m) / span))
            speed *= SLOW_FRACTION + (1.0 - SLOW_FRACTION) * frac
        return speed

    def _clear(self, point: FloatArray, obstacles: FloatArray) -> bool:
        guard = self.p.target_guard_m
        if guard <= 0.0 or obstacles.shape[0] == 0:
            return True
        d = obstacles[:, : self.p.dim] - point[: self.p.dim]
        return bool(np.min(np.einsum("ij,ij->i", d, d)) >= guard**2)


class HoldPoint:
    """The point held in HOLDING / ARRIVED / STUCK: fixed on the first holding cycle, and again at the first fresh
    pose after the pose went stale (``setpoint``)."""

    def __init__(self) -> None:
        self.anchor: FloatArray | None = None
        self.sent = False

    def reset(self) -> None:
        self.anchor = None
        self.sent = False

    def setpoint(self, pose: Pose | None, *, pose_fresh: bool) -> Setpoint | None:
        """Hold at the anchor: always once (the first cycle in a holding state, at the last known position), then
        only with a fresh pose.

        A stale pose after that silences the hold and forgets the anchor: while nothing is sent the vehicle moves on
        (the last navigation setpoint's feed-forward, the autopilot's own hold, wind), so the next fresh pose fixes
        the hold anew where the vehicle is. Re-sending the old anchor would fly the vehicle back to it, on ranges
        that are still stale, for the cycle before navigation resumed from the new pose (the hostile-input review,
        docs/hardening.md "A silent gap")."""
        if self.anchor is None:
            if pose is None or (self.sent and not pose_fresh):
                return None  # silenced by a stale pose: wait for a fresh one
            self.anchor = np.array(pose.pos_ned_m, dtype=np.float64)
        if pose_fresh or not self.sent:
            self.sent = True
            return hold(self.anchor)
        self.anchor = None
        return None
