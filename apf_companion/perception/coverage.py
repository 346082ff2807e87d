"""Where the range sensors look, in the body frame: the "look offset" the commanded heading turns by.

``[autopilot] yaw = "travel"`` points the vehicle so that its range sensor looks where it goes. That is the nose
only for a sensor facing forward: a side or rear sensor (OBSTACLE_DISTANCE with an ``angle_offset``,
``[sensors] obstacle_distance_mount_yaw_deg`` / ``laserscan_mount_yaw_deg``, a DISTANCE_SENSOR facing YAW_180)
must itself face the step. ``LookCoverage`` learns the covered arc from the readings the service places: each
usable reading (obstacle or free, not unknown / invalid) marks its element's width around its body bearing (FRD,
0 = nose, clockwise), after the mount yaw, as measured at its scan's time. The look offset is the body bearing of
the centre of the covered arc; the heading is then ``step bearing - look offset``.

Rules (``offset_rad``):

- nothing covered within ``max_age_s`` (no readings yet, or every source stale): 0, the nose, as before;
- at least ``FULL_COVER_DEG`` covered (an all-round scanner, even with a few unknown sectors where the frame or
  a leg blocks it, or a too-close reading is invalid): 0, turning would gain nothing;
- otherwise the centre of the widest contiguous covered arc; arcs within ``TIE_DEG`` of the widest count as as
  wide, and of those the one whose centre is nearest the nose wins (a front and a rear sensor of one kind: the
  nose leads, as before).

The sources are merged: a bin is covered while any source read there recently; a source that stops ages out on
its own. Times are the service clock, passed in (no clock here).
"""

from __future__ import annotations

import math

import numpy as np
import numpy.typing as npt

__all__ = ["BINS", "FULL_COVER_DEG", "TIE_DEG", "LookCoverage", "wrap_pi_upper"]

BINS = 360  # 1-degree bins: the arc's centre to within half a degree
FULL_COVER_DEG = 300.0  # this much covered counts as all-round [deg]
TIE_DEG = 10.0  # arcs this much narrower than the widest still count as as wide [deg]

_BIN_RAD = 2.0 * math.pi / BINS
_CENTRES_RAD = (np.arange(BINS, dtype=np.float64) + 0.5) * _BIN_RAD


def wrap_pi_upper(angle_rad: float) -> float:
    """``angle_rad`` wrapped to (-pi, pi] (a rear-facing sensor's centre is +pi, not -pi)."""
    return -((-angle_rad + math.pi) % (2.0 * math.pi) - math.pi)


class LookCoverage:
    """When each 1-degree body-frame bin (FRD, clockwise from the nose) last had a usable reading; the look offset
    (see the module docstring). Owned by the obstacle store, written as scans are placed."""

    def __init__(self, max_age_s: float) -> None:
        self.max_age_s = max_age_s
        self._t_s = np.full(BINS, -np.inf)

    def note(self, body_bearings_rad: npt.ArrayLike, half_width_rad: float, t_s: float) -> None:
        """Usable readings along these body bearings (FRD [rad]), each covering ``half_width_rad`` either side (at
        least half a bin: a single beam covers its own bin), measured at ``t_s``. Non-finite bearings are ignored;
        a non-finite width counts as a single beam."""
        b = np.asarray(body_bearings_rad, dtype=np.float64).ravel()
        b = b[np.isfinite(b)]
        if b.size == 0 or not math.isfinite(t_s):
            return
        hw = half_width_rad if math.isfinite(half_width_rad) and half_width_rad > 0.0 else 0.0
        hw = min(max(hw, 0.5 * _BIN_RAD), math.pi)
        off = np.abs(np.mod(_CENTRES_RAD[:, None] - b[None, :] + math.pi, 2.0 * math.pi) - math.pi)
        covered = np.any(off <= hw + 1e-9, axis=1)
        self._t_s[covered] = np.maximum(self._t_s[covered], t_s)

    def note_all(self, t_s: float) -> None:
        """Every direction read at ``t_s`` (an all-round perfect sensor in tests and closed-loop simulations)."""
        if math.isfinite(t_s):
            self._t_s = np.maximum(self._t_s, t_s)

    def covered(self, now_s: float) -> npt.NDArray[np.bool_]:
        """(BINS,) the bins read within ``max_age_s`` of ``now_s``; bin ``i`` spans ``[i, i + 1)`` degrees."""
        return np.asarray(now_s - self._t_s <= self.max_age_s)

    def offset_rad(self, now_s: float) -> float:
        """The look offset: the body bearing (FRD, (-pi, pi] [rad]) the heading turns away from the step so the
        covered arc's centre faces it; 0 without readings or with all-round coverage (module docstring)."""
        cov = self.covered(now_s)
        n = int(np.count_nonzero(cov))
        if n == 0 or n * 360.0 / BINS >= FULL_COVER_DEG:
            return 0.0
        first_gap = int(np.argmin(cov))  # a bin without a reading exists: n < BINS
        rolled = np.roll(cov, -first_gap).astype(np.int8)
        edges = np.diff(np.concatenate([[0], rolled, [0]]))
        starts, ends = np.flatnonzero(edges == 1), np.flatnonzero(edges == -1)
        widths = ends - starts
        centres = [wrap_pi_upper((first_gap + s + 0.5 * w) * _BIN_RAD) for s, w in zip(starts, widths, strict=True)]
        tied = widths >= widths.max() - TIE_DEG * BINS / 360.0
        best = min((abs(c), i) for i, c in enumerate(centres) if tied[i])
        return centres[best[1]]

    def clear(self) -> None:
        self._t_s[:] = -np.inf
