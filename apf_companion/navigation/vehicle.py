"""What the navigator knows of the autopilot and the vehicle, and how fresh it is."""

from __future__ import annotations

import numpy as np

from apf_companion.navigation.model import Counters, CycleInputs, FloatArray, NavigatorParams, ObstacleView
from apf_companion.perception import Pose

__all__ = ["VehicleLink", "nearest_m"]


class VehicleLink:
    """The autopilot's last HEARTBEAT (when, and whether it showed GUIDED / OFFBOARD), the pose, the EKF's position
    flag, and whether the link and the inputs (pose, ranges) are fresh at a given time.

    The link counts as lost until the first HEARTBEAT (``heard``).
    """

    def __init__(self, params: NavigatorParams, obstacles: ObstacleView, counters: Counters) -> None:
        self.p = params
        self.obstacles = obstacles
        self.counters = counters
        self.pose: Pose | None = None
        self.last_hb_s: float | None = None
        self.mode_ok = False  # latest HEARTBEAT: autopilot is in GUIDED/OFFBOARD
        self.failsafe = False  # latest HEARTBEAT: system_status CRITICAL (a failsafe of the autopilot is active)
        self.ekf_ready: bool | None = None  # EKF_STATUS_REPORT has a horizontal position (None = not reported)

    def update_pose(self, pose: Pose) -> bool:
        """A new pose (already validated finite by ``Pose``). Older-or-equal timestamps are refused (a frozen or
        replayed pose must not look fresh). Returns whether it was accepted."""
        if self.pose is not None and pose.t_s <= self.pose.t_s:
            self.counters.rejected_poses += 1
            return False
        self.pose = pose
        return True

    def heard(self, now_s: float, *, mode_ok: bool, failsafe: bool = False) -> None:
        """An autopilot HEARTBEAT at ``now_s``; ``mode_ok`` = it shows GUIDED (ArduPilot) / OFFBOARD (PX4);
        ``failsafe`` = its system_status is CRITICAL."""
        self.last_hb_s = now_s
        self.failsafe = failsafe
        self.mode_ok = mode_ok

    def link_alive(self, now_s: float) -> bool:
        return self.last_hb_s is not None and now_s - self.last_hb_s <= self.p.heartbeat_timeout_s

    def heartbeat_age_s(self, now_s: float) -> float | None:
        """Time since the last autopilot HEARTBEAT [s]; None before the first."""
        return None if self.last_hb_s is None else now_s - self.last_hb_s

    def pose_fresh(self, now_s: float) -> bool:
        return self.pose is not None and now_s - self.pose.t_s <= self.p.pose_max_age_s

    def ranges_fresh(self, now_s: float) -> bool:
        if not self.p.require_ranges:
            return True
        last = self.obstacles.ranges_t_s
        return last is not None and now_s - last <= self.p.ranges_max_age_s

    def inputs(self, now_s: float) -> CycleInputs:
        """What a cycle at ``now_s`` sees; a stale pose or stale ranges are counted."""
        points = self.obstacles.points(now_s)
        pose_ok = self.pose_fresh(now_s)
        ranges_ok = self.ranges_fresh(now_s)
        if not pose_ok:
            self.counters.stale_pose_cycles += 1
        if not ranges_ok:
            self.counters.stale_range_cycles += 1
        nearest = None if self.pose is None else nearest_m(points, self.pose.pos_ned_m, self.p.dim)
        return CycleInputs(now_s, points, nearest, pose_ok, ranges_ok)

    def no_pose_reason(self) -> str:
        """Why HOLDING has no pose: the EKF has no origin yet (ArduPilot sends no LOCAL_POSITION_NED then), or no
        pose came (not requested, not sent)."""
        if self.ekf_ready is False:
            return "waiting for EKF origin: no position yet"
        return "no pose yet (no LOCAL_POSITION_NED)"


def nearest_m(points: FloatArray, pos: FloatArray, dim: int) -> float | None:
    """Distance to the nearest of ``points`` (horizontal in 2D), None without points."""
    if points.shape[0] == 0:
        return None
    d = points[:, :dim] - pos[:dim]
    return float(np.sqrt(np.min(np.einsum("ij,ij->i", d, d))))
