"""Freshness per direction: when each azimuth sector (local NED, 0 = north, clockwise) was last measured.

A sector with no usable reading (obstacle or free) for ``max_age_s`` is unknown, and the navigator does not step
into it (docs/hardening.md): "unknown is not free" per direction, not only globally. One forward DISTANCE_SENSOR
beam keeps its own sector fresh, never the sides.
"""

from __future__ import annotations

import math

import numpy as np
import numpy.typing as npt

__all__ = ["SectorFreshness"]

_TWO_PI = 2.0 * math.pi


class SectorFreshness:
    """``sectors`` equal azimuth sectors; ``sectors == 0`` turns the check off (every direction fresh)."""

    def __init__(self, sectors: int, max_age_s: float) -> None:
        self.sectors = sectors
        self.max_age_s = max_age_s
        self._t_s = np.full(max(sectors, 1), -np.inf)

    def _index(self, bearings_ned_rad: npt.ArrayLike) -> npt.NDArray[np.intp]:
        b = np.mod(np.asarray(bearings_ned_rad, dtype=np.float64), _TWO_PI)
        return np.minimum((b / _TWO_PI * self.sectors).astype(np.intp), self.sectors - 1)

    def note(self, bearings_ned_rad: npt.ArrayLike, t_s: float) -> None:
        """Readings (obstacle or free; not unknown) along these bearings were measured at ``t_s``."""
        if self.sectors == 0:
            return
        b = np.asarray(bearings_ned_rad, dtype=np.float64)
        b = b[np.isfinite(b)]
        if b.size:
            idx = self._index(b)
            self._t_s[idx] = np.maximum(self._t_s[idx], t_s)

    def note_all(self, t_s: float) -> None:
        """Every direction measured at ``t_s`` (an all-round point source, e.g. a simulation's perfect sensor)."""
        self._t_s = np.maximum(self._t_s, t_s)

    def fresh(self, bearing_ned_rad: float, now_s: float) -> bool:
        """The sector containing ``bearing_ned_rad`` was measured within ``max_age_s`` of ``now_s``."""
        if self.sectors == 0:
            return True
        if not math.isfinite(bearing_ned_rad):
            return False
        i = int(self._index(bearing_ned_rad))
        return bool(now_s - self._t_s[i] <= self.max_age_s)

    def clear(self) -> None:
        self._t_s[:] = -np.inf
