"""The pose intake: LOCAL_POSITION_NED and ATTITUDE in, poses on the service clock out.

Each pose passes the ``PoseGate`` (perception/plausibility.py; rejects are counted by verdict), takes the ATTITUDE
yaw at its own time (``HeadingTrack``) and joins the ``PoseHistory`` that scans are placed with; the offset between
the service clock and the autopilot's boot time (of the latest pose) stamps the scans. A re-anchor (EKF reset,
reboot) empties the history and the obstacle store (``pose.reset``); a conflict of two pose streams is logged
(``pose.conflict``, rate-limited). Both are taken by the handler (``take_reset``, ``take_conflict``).
"""

from __future__ import annotations

import logging
from collections.abc import Callable

import numpy as np

from apf_companion.errors import ConfigError
from apf_companion.perception.frontparams import BAD_SCAN_LOG_INTERVAL_S, PerceptionCounters
from apf_companion.perception.heading import HeadingTrack
from apf_companion.perception.history import PoseHistory
from apf_companion.perception.plausibility import PoseGate, PoseLimits, Verdict
from apf_companion.perception.ratelog import RateLimitedLog
from apf_companion.perception.store import ObstacleStore
from apf_companion.perception.types import FloatArray, Pose

__all__ = ["MAX_HEADING_AGE_S", "POSE_HISTORY_LEN", "STAMP_PLAUSIBLE_S", "PoseIntake", "Vec3"]

Vec3 = tuple[float, float, float]  # local NED: a position [m] or a velocity [m/s]
log = logging.getLogger("apf_companion.perception.frontend")  # the logger its lines had before the front end's split
MAX_HEADING_AGE_S = 1.0  # a pose this far from every ATTITUDE (the stream stopped) places no ranges [s]
POSE_HISTORY_LEN = 200  # poses kept to place scans (10 s at 20 Hz)
STAMP_PLAUSIBLE_S = 5.0  # a stamp older than this (or in the future) is on another clock: use receive time
CONFLICT_HINT = (
    "two LOCAL_POSITION_NED streams with the autopilot's ids claim different positions for the same time (a spoofed "
    "stream, or a second source with the same sysid/compid): braking while they disagree; "
    "link.require_signed_telemetry drops unsigned poses"
)


class PoseIntake:
    """Owns the pose history, the ATTITUDE samples, the pose gate, the boot-time offset and the reset / conflict
    notices not yet taken.

    Args:
        store: Emptied on a re-anchor (its points are in the old frame).
        pose_added: Called when a pose joined the history (the scans waiting for it are placed then, before the
            cycle this pose triggers).
    """

    def __init__(
        self,
        limits: PoseLimits,
        counters: PerceptionCounters,
        *,
        store: ObstacleStore,
        pose_added: Callable[[], None],
    ) -> None:
        self.counters = counters
        self._store = store
        self._pose_added = pose_added
        self.history = PoseHistory(POSE_HISTORY_LEN)
        self.heading = HeadingTrack()
        self.gate = PoseGate(limits)
        self.conflict_log = RateLimitedLog(log, "pose.conflict", BAD_SCAN_LOG_INTERVAL_S)
        self.reset_log = RateLimitedLog(log, "pose.reset", BAD_SCAN_LOG_INTERVAL_S)  # forged resets can be many
        self.reset_reason: str | None = None  # set on a re-anchor; the handler takes it (hold + STATUSTEXT)
        self.conflict_said = False  # a pose.conflict WARNING was logged; the handler takes it (STATUSTEXT)
        self._boot_offset_s: float | None = None  # service time - autopilot boot time (latest pose)

    def on_attitude(self, yaw_rad: float, *, time_boot_ms: int | None = None, yaw_rate_rad_s: float = 0.0) -> None:
        """ATTITUDE.yaw [rad] measured at ``time_boot_ms``, with the heading rate [rad/s]: poses take the yaw at
        their own time from these samples (perception/heading.py). Without a time, the next poses carry it as is."""
        if np.isfinite(yaw_rad):
            h = self.heading
            h.update(float(yaw_rad), time_boot_ms, yaw_rate_rad_s)
            self.counters.stale_attitudes, self.counters.bad_attitude_rates = h.stale, h.bad_rates
        else:
            self.counters.bad_poses += 1

    def on_local_position(
        self, time_boot_ms: int, pos_ned_m: Vec3, now_s: float, vel_ned_m_s: Vec3 | None = None
    ) -> Pose | None:
        """A LOCAL_POSITION_NED received at ``now_s``: the new pose (history updated, waiting scans placed), or
        None when it is stale, non-finite or no heading is known yet. An implausible reported velocity does not
        reject the pose: the pose carries no velocity (the navigator's braking envelope is then off)."""
        self.counters.poses += 1
        yaw_rad = self.heading.at(time_boot_ms)
        if yaw_rad is None:
            return None  # no ATTITUDE yet: body-frame ranges could not be placed
        verdict = self.gate.check(time_boot_ms, pos_ned_m, now_s)
        if verdict is Verdict.CONFLICT and self.conflict_log.note(now_s, hint=CONFLICT_HINT):
            self.conflict_said = True  # the handler takes it (``take_conflict``): a STATUSTEXT as often as the log
        if verdict is Verdict.RESET:
            self._reset(f"position reset to {pos_ned_m[0]:.1f} {pos_ned_m[1]:.1f} {pos_ned_m[2]:.1f}", now_s)
        elif verdict is not Verdict.ACCEPT:
            counter = _REJECTED[verdict]
            setattr(self.counters, counter, getattr(self.counters, counter) + 1)
            return None
        vel = self._plausible_velocity(vel_ned_m_s)
        try:
            pose = Pose(t_s=now_s, pos_ned_m=np.array(pos_ned_m, dtype=np.float64), yaw_rad=yaw_rad, vel_ned_m_s=vel)
        except ConfigError:
            self.counters.bad_poses += 1
            return None
        last = self.gate.last
        # The pose's effective time (its stamp, no later than the receive clock allows): a pose stamped ahead does
        # not move where scans and headings are placed in time.
        self._boot_offset_s = now_s - (time_boot_ms / 1000.0 if last is None else last.eff_s)
        if self.heading.age_s(time_boot_ms) > MAX_HEADING_AGE_S:
            # The ATTITUDE stream stopped: the navigator still gets the position, but no range is placed with
            # a guessed heading (scans then find no pose, the memory ages, and "ranges stale" holds).
            self.counters.poses_without_heading += 1
            return pose
        self.history.add(pose)
        self._pose_added()
        return pose

    def _plausible_velocity(self, vel: tuple[float, float, float] | None) -> FloatArray | None:
        if vel is None:
            return None
        v = np.array(vel, dtype=np.float64)
        if not np.all(np.isfinite(v)) or float(np.sqrt(v @ v)) > self.gate.limits.max_speed_m_s:
            self.counters.bad_velocities += 1
            return None
        return v

    def _reset(self, reason: str, now_s: float) -> None:
        """The gate re-anchored (or an announced estimator reset came within reach): poses and remembered points are
        in the old frame; forget them (their offset is not known: LOCAL_POSITION_NED carries no ``delta_xy``)."""
        self.counters.pose_resets += 1
        self.history.clear()
        self._store.clear()
        self.reset_reason = reason
        self.reset_log.note(now_s, reason=reason)

    def on_reset_counter(self, counter: int) -> None:
        """ODOMETRY.reset_counter from the autopilot: a change is counted (``estimator_resets``) and is evidence for
        the pose gate (``PoseGate.note_reset_counter``)."""
        if self.gate.note_reset_counter(counter):
            self.counters.estimator_resets += 1

    def take_reset(self) -> str | None:
        """The reason of a re-anchor since the last call, or None."""
        reason, self.reset_reason = self.reset_reason, None
        return reason

    def take_conflict(self) -> bool:
        """Whether a ``pose.conflict`` WARNING was logged since the last call (at most one per
        ``BAD_SCAN_LOG_INTERVAL_S``): the pilot is told why the vehicle brakes as often as the log is."""
        said, self.conflict_said = self.conflict_said, False
        return said

    def autopilot_boot_s(self, now_s: float) -> float | None:
        """The autopilot's time since boot at service time ``now_s`` (offset of the latest pose), None before."""
        return None if self._boot_offset_s is None else now_s - self._boot_offset_s

    def yaw_now(self, now_s: float) -> float | None:
        """The heading [rad] at service time ``now_s``: the ATTITUDE samples carried to the autopilot's present (by
        the rate, at most 0.25 s). None before the first pose or ATTITUDE, or with no ATTITUDE for
        ``MAX_HEADING_AGE_S`` (the stream stopped)."""
        boot_s = self.autopilot_boot_s(now_s)
        if boot_s is None:
            return None
        boot_ms = round(boot_s * 1000.0)
        return None if self.heading.age_s(boot_ms) > MAX_HEADING_AGE_S else self.heading.at(boot_ms)

    def scan_time(self, boot_ms: int | None, now_s: float) -> float:
        """Service time of a measurement stamped with autopilot boot time (receive time if unknown)."""
        if boot_ms is None or self._boot_offset_s is None:
            return now_s
        t = boot_ms / 1000.0 + self._boot_offset_s
        return t if now_s - STAMP_PLAUSIBLE_S < t <= now_s else now_s  # implausible stamps: receive time


_REJECTED = {
    Verdict.NON_FINITE: "bad_poses",
    Verdict.OUT_OF_BOUNDS: "out_of_bounds_poses",
    Verdict.STALE: "stale_poses",
    Verdict.TIME_LEAD: "pose_time_leads",
    Verdict.TIME_JUMP: "pose_time_jumps",
    Verdict.CONFLICT: "pose_conflicts",
    Verdict.JUMP: "implausible_poses",
}
"""The counter of each rejecting verdict."""
