"""A short history of vehicle poses, to place a measurement with the pose at its own time."""

from __future__ import annotations

import logging
import math

import numpy as np

from apf_companion.errors import ConfigError
from apf_companion.perception.types import Pose

__all__ = ["PoseHistory"]

log = logging.getLogger(__name__)


class PoseHistory:
    """Bounded, time-ordered pose buffer with interpolation.

    Poses must arrive in non-decreasing ``t_s``; an older pose than the newest is dropped (and counted in
    ``rejected``), because the autopilot's stream never goes back in time and a reordered datagram is stale.
    A pose with the same time as the newest replaces it.

    Parameters
    ----------
    maxlen:
        Number of poses kept (>= 1). At 50 Hz, 100 poses cover 2 s.
    hold_s:
        How far outside the buffer ``at`` still answers, with the nearest end pose held (not
        extrapolated) [s], >= 0. A scan stamped on receipt is usually a little newer than the newest pose;
        without this margin it would find no pose. Default 0.05 s.
    """

    __slots__ = ("_count", "_hold_s", "_maxlen", "_pos", "_t", "_yaw", "rejected")

    def __init__(self, maxlen: int = 100, *, hold_s: float = 0.05) -> None:
        if not isinstance(maxlen, int) or maxlen < 1:
            msg = f"PoseHistory maxlen must be an int >= 1, got {maxlen!r}"
            raise ConfigError(msg)
        if not (math.isfinite(hold_s) and hold_s >= 0.0):
            msg = f"PoseHistory hold_s must be finite and >= 0, got {hold_s!r}"
            raise ConfigError(msg)
        self._maxlen = maxlen
        self._hold_s = hold_s
        self._t = np.empty(maxlen, dtype=np.float64)
        self._pos = np.empty((maxlen, 3), dtype=np.float64)
        # Yaw is stored unwrapped so that linear interpolation takes the short way through +-pi.
        self._yaw = np.empty(maxlen, dtype=np.float64)
        self._count = 0
        self.rejected = 0

    def __len__(self) -> int:
        return self._count

    @property
    def maxlen(self) -> int:
        """Capacity of the buffer."""
        return self._maxlen

    def clear(self) -> None:
        """Forget every pose (e.g. after an EKF reset or a reboot of the autopilot)."""
        self._count = 0

    def add(self, pose: Pose) -> bool:
        """Append ``pose``; returns False (and counts it) when it is older than the newest pose."""
        n = self._count
        yaw = pose.yaw_rad
        if n > 0:
            last_t = self._t[n - 1]
            if pose.t_s < last_t:
                self.rejected += 1
                log.debug("pose_history.out_of_order", extra={"t_s": pose.t_s, "newest_t_s": last_t})
                return False
            last_yaw = self._yaw[n - 1]
            yaw = last_yaw + math.remainder(pose.yaw_rad - last_yaw, 2.0 * math.pi)
            if pose.t_s == last_t:
                n -= 1
        if n == self._maxlen:
            self._t[:-1] = self._t[1:]
            self._pos[:-1] = self._pos[1:]
            self._yaw[:-1] = self._yaw[1:]
            n -= 1
        self._t[n] = pose.t_s
        self._pos[n] = pose.pos_ned_m
        self._yaw[n] = yaw
        self._count = n + 1
        return True

    def latest(self) -> Pose | None:
        """The newest pose, or None when empty."""
        if self._count == 0:
            return None
        return self._pose(self._count - 1)

    def _pose(self, i: int, t_s: float | None = None) -> Pose:
        return Pose(
            t_s=float(self._t[i]) if t_s is None else t_s,
            pos_ned_m=self._pos[i].copy(),
            yaw_rad=math.remainder(float(self._yaw[i]), 2.0 * math.pi),
        )

    def at(self, t_s: float) -> Pose | None:
        """The pose at ``t_s``, linearly interpolated between the two poses around it.

        Position is interpolated linearly, yaw along the shorter arc. Within ``hold_s`` before the oldest or
        after the newest pose the end pose is returned (with ``t_s`` set to the asked time); further out, or
        when empty, None.
        """
        n = self._count
        if n == 0 or not math.isfinite(t_s):
            return None
        t = self._t[:n]
        if t_s <= t[0]:
            return self._pose(0, t_s) if t[0] - t_s <= self._hold_s else None
        if t_s >= t[n - 1]:
            return self._pose(n - 1, t_s) if t_s - t[n - 1] <= self._hold_s else None
        hi = int(np.searchsorted(t, t_s, side="right"))
        lo = hi - 1
        w = (t_s - t[lo]) / (t[hi] - t[lo])
        pos = self._pos[lo] + w * (self._pos[hi] - self._pos[lo])
        yaw = self._yaw[lo] + w * (self._yaw[hi] - self._yaw[lo])
        return Pose(t_s=t_s, pos_ned_m=pos, yaw_rad=math.remainder(float(yaw), 2.0 * math.pi))
