"""Remembered obstacle points in local NED, with expiry, merging and clearing by observed free space.

The paper's planner (and the authors' code) keeps every detected obstacle for the whole run; on a real
vehicle, drift and moving objects make that unsafe, so points here expire after ``expiry_s`` unless seen
again. A new point within ``merge_radius_m`` of a remembered one refreshes it (newest time, first position), so a
static obstacle seen every cycle stays one point and stays fresh, and a surface seen from a moving vehicle keeps
the points it gave: replacing them by the newest position drags them along (below).

Clearing (``clear_observed``): a beam that reports free space (+inf) or an obstacle at range ``r`` shows
that nothing lies along it nearer than that; remembered points inside such a beam, more than ``margin_m``
nearer than the reading and within ``vertical_window_m`` of the scan's height, are removed. Unknown and
invalid beams (NaN) clear nothing ("unknown is not free").

Where a point may be. A sector sensor reports the nearest surface in each window, and the point is placed on the
window's centre bearing, so the surface may lie up to ``spread_m`` = range x sin(half width) beside it (0.35 m at
8 m with 5-degree sectors). Seen at grazing incidence along a wall, such a point sits in front of the wall, and a
later beam along the wall reads past it: the wall's points were cleared one by one and the wall turned porous
(issue 7: walls 2-3 m open in ``apf-sim fly --world wall-gap``, where the planner then paced to and fro). So a
point is cleared only when every beam whose window meets the disc of radius ``spread_m`` around it sees past it,
or when one of the scan's returns lies within its spread (that return stands for the surface it may be: a door's
jamb seen closer, not a wall seen along its length, where the returns lie metres apart).
Points with no spread (a surface-fill point no return has refreshed; ``remember``) are cleared by their own beam.

Why the first position. Replacing a point by a new one within the merge radius moved the remembered wall towards
each new window's nearest point: along a wall seen obliquely from a moving vehicle, the points slid with the
vehicle and left the far end open (replayed along a flown wall-gap path: 1-4 m holes at 10 s and at 60 s expiry).
ArduPilot's obstacle database keeps the first position too (AP_OADatabase.cpp, ``database_item_refresh`` updates
the timestamp and radius only). A moving obstacle's old points go by clearing or expiry. Two exceptions: a return
at least twice as precise within a point's spread supersedes it (a closer look: the window error of a far first
sighting does not stay), and a refreshed point takes the newest height (a climb must not stack layers).

Clearing is hard to fake (docs/hardening.md): each point remembers the sensor that saw it, and only that sensor's
scans clear it, and only after ``clear_scans`` scans spread over at least ``clear_span_s`` saw through it; a scan
that sees it again (a merge) restarts the count. A flood of "all free" scans between two genuine scans of the
obstacle clears nothing; scans from another sensor never clear it (``clears_refused``).
"""

from __future__ import annotations

import math

import numpy as np
import numpy.typing as npt

from apf_companion.errors import ConfigError
from apf_companion.perception.geometry import element_half_width_rad, scan_bearings_ned_rad, scan_to_points_ned
from apf_companion.perception.types import FloatArray, Pose, RangeScan

__all__ = ["ObstacleMemory"]

_TWO_PI = 2.0 * math.pi
_SQRT3 = math.sqrt(3.0)
_MAX_COORD_M = 1e7  # 10,000 km: beyond any local NED frame


def _positive(name: str, value: float) -> None:
    if not (math.isfinite(value) and value > 0.0):
        msg = f"ObstacleMemory {name} must be finite and > 0, got {value!r}"
        raise ConfigError(msg)


def _sq_dists(a: FloatArray, b: FloatArray) -> FloatArray:
    """(N, K) squared distances between (N, 3) and (K, 3) points.

    |a|^2 + |b|^2 - 2 a.b through one matrix product: 2-3x faster than axis-wise differences here. Both
    sets are first centred on b's mean, so the cancellation error stays near eps * (scan extent)^2, far
    below any merge radius.
    """
    c = b.mean(axis=0)
    ac, bc = a - c, b - c
    out = np.einsum("ij,ij->i", ac, ac)[:, None] + np.einsum("ij,ij->i", bc, bc)[None, :] - 2.0 * (ac @ bc.T)
    return np.asarray(np.maximum(out, 0.0), dtype=np.float64)


def _voxel_first(points: FloatArray, cell_m: float) -> npt.NDArray[np.intp]:
    """Indices (ascending) of the first point in each occupied cell of a grid with edge ``cell_m``.

    O(K log K) for any layout. (An exact "keep unless within r of an earlier kept point" rule is
    sequential: along a dense scan of a wall it needs one vectorised pass per point, 10-17 ms for 360
    beams, measured.)
    """
    keys = np.floor(points / cell_m).astype(np.int64)
    keys -= keys.min(axis=0)
    dims = keys.max(axis=0) + 1
    if float(np.prod(dims.astype(np.float64))) < 2.0**62:
        # One int64 per cell: a 1-D unique is several times faster than unique(axis=0).
        flat = (keys[:, 0] * dims[1] + keys[:, 1]) * dims[2] + keys[:, 2]
        _, first = np.unique(flat, return_index=True)
    else:
        _, first = np.unique(keys, axis=0, return_index=True)
    return np.sort(first)


def _nearest_reach(
    b_sorted: FloatArray,
    reach: FloatArray,
    beam: npt.NDArray[np.intp],
    bearing: FloatArray,
    half_rad: float,
    sin_disc: FloatArray,
) -> FloatArray:
    """The shortest reach among the beams whose window (``half_rad`` either side) meets a disc seen at ``bearing``
    with angular radius asin(``sin_disc``), starting from its nearest ``beam``. The loop runs over beam offsets
    (at most half the scan), each pass over the discs that the last offset still met: bearings are sorted, so a
    disc that misses both windows at offset k misses every farther one."""
    m = b_sorted.size
    window = half_rad + np.arcsin(np.minimum(sin_disc, 1.0))
    lowest = reach[beam].copy()
    active = np.arange(beam.size)
    for k in range(1, m // 2 + 1):
        met = np.zeros(active.size, dtype=np.bool_)
        for j in ((beam[active] + k) % m, (beam[active] - k) % m):
            hit = np.abs(np.remainder(bearing[active] - b_sorted[j] + math.pi, _TWO_PI) - math.pi) <= window[active]
            lowest[active[hit]] = np.minimum(lowest[active[hit]], reach[j[hit]])
            met |= hit
        active = active[met]
        if active.size == 0:
            break
    return np.asarray(lowest, dtype=np.float64)


def _nearest_beam(b_sorted: FloatArray, pb: FloatArray) -> tuple[npt.NDArray[np.intp], FloatArray]:
    """For bearings ``pb``: the index of the nearest of the sorted beam bearings ``b_sorted`` (cyclically: the
    neighbours either side of the insertion point) and the angle to it [rad]."""
    m = b_sorted.size
    hi = np.searchsorted(b_sorted, pb) % m
    lo = (hi - 1) % m
    d_hi = np.abs(np.remainder(pb - b_sorted[hi] + math.pi, _TWO_PI) - math.pi)
    d_lo = np.abs(np.remainder(pb - b_sorted[lo] + math.pi, _TWO_PI) - math.pi)
    return np.where(d_hi <= d_lo, hi, lo), np.minimum(d_hi, d_lo)


class ObstacleMemory:
    """Obstacle points in local NED with expiry and merging (vectorised).

    Parameters
    ----------
    expiry_s:
        A point not seen for longer than this is forgotten [s], > 0.
    merge_radius_m:
        Points closer than this are one obstacle [m], > 0.
    max_points:
        Capacity; when full, the points seen longest ago are dropped first (>= 1).
    """

    __slots__ = (
        "_expiry_s",
        "_free_n",
        "_free_t0",
        "_max_points",
        "_merge_radius_m",
        "_pts",
        "_spread",
        "_src",
        "_t",
        "clears_refused",
        "dropped_full",
    )

    def __init__(self, *, expiry_s: float = 5.0, merge_radius_m: float = 0.2, max_points: int = 2000) -> None:
        _positive("expiry_s", expiry_s)
        _positive("merge_radius_m", merge_radius_m)
        if not isinstance(max_points, int) or max_points < 1:
            msg = f"ObstacleMemory max_points must be an int >= 1, got {max_points!r}"
            raise ConfigError(msg)
        self._expiry_s = expiry_s
        self._merge_radius_m = merge_radius_m
        self._max_points = max_points
        self.clear()
        self.dropped_full = 0
        self.clears_refused = 0  # see-throughs by a sensor other than the one that saw the point

    def __len__(self) -> int:
        return int(self._t.size)

    @property
    def expiry_s(self) -> float:
        """Time after which an unseen point is forgotten [s]."""
        return self._expiry_s

    def clear(self) -> None:
        """Forget everything."""
        self._pts = np.empty((0, 3), dtype=np.float64)
        self._t = np.empty(0, dtype=np.float64)
        self._src = np.empty(0, dtype=np.int64)  # the sensor that saw each point (-1: any may clear it)
        self._free_n = np.empty(0, dtype=np.int64)  # scans of that sensor that saw through it since
        self._free_t0 = np.empty(0, dtype=np.float64)  # the first of them
        self._spread = np.empty(0, dtype=np.float64)  # how far beside it the surface may lie [m]

    def _keep(self, keep: npt.NDArray[np.bool_] | npt.NDArray[np.intp]) -> None:
        """Keep the rows selected by a mask or an index array (every per-point array alike)."""
        self._pts = self._pts[keep]
        self._t = self._t[keep]
        self._src = self._src[keep]
        self._free_n = self._free_n[keep]
        self._free_t0 = self._free_t0[keep]
        self._spread = self._spread[keep]

    def add(self, points_ned_m: FloatArray, t_s: float, sensor: int = -1, spread_m: FloatArray | None = None) -> None:
        """Remember ``points_ned_m`` ((K, 3) float64, local NED [m]) as seen at ``t_s`` [s].

        Rows that are not finite or lie beyond 1e7 m are ignored. New points in the same cell of a grid with edge
        ``merge_radius_m / sqrt(3)`` are one point (the first is kept), so every dropped point lies within
        ``merge_radius_m`` of a kept one; kept points in neighbouring cells may be closer than that. A
        remembered point within ``merge_radius_m`` of a kept new point is refreshed in place and that new point is
        not added, unless a new point supersedes it (``_merge``). ``spread_m`` ((K,), default 0): how far beside each
        point the surface may lie (module docstring) [m].
        """
        pts = np.asarray(points_ned_m, dtype=np.float64)
        if pts.ndim != 2 or pts.shape[1] != 3:
            msg = f"points_ned_m must have shape (K, 3), got {pts.shape}"
            raise ConfigError(msg)
        if not math.isfinite(t_s):
            msg = f"t_s must be finite, got {t_s}"
            raise ConfigError(msg)
        spread = np.zeros(pts.shape[0]) if spread_m is None else np.asarray(spread_m, dtype=np.float64)
        if spread.shape != (pts.shape[0],):
            msg = f"spread_m must have shape ({pts.shape[0]},), got {spread.shape}"
            raise ConfigError(msg)
        # Also drops absurd coordinates, which would overflow the int64 grid keys; a bad spread counts as none.
        ok = np.all(np.abs(pts) < _MAX_COORD_M, axis=1)
        pts, spread = pts[ok], np.where(np.isfinite(spread[ok]), np.maximum(spread[ok], 0.0), 0.0)
        if pts.shape[0] == 0:
            return
        if pts.shape[0] > 1:
            first = _voxel_first(pts, self._merge_radius_m / _SQRT3)
            pts, spread = pts[first], spread[first]
        if self._t.size:
            # Only remembered points inside the new batch's bounding box, grown by the merge radius or the largest
            # spread, can merge or be superseded.
            grow = max(self._merge_radius_m, float(self._spread.max(initial=0.0)))
            near = np.all((self._pts >= pts.min(axis=0) - grow) & (self._pts <= pts.max(axis=0) + grow), axis=1)
            idx = np.flatnonzero(near)
            if idx.size:
                pts, spread = self._merge(idx, pts, spread, t_s, sensor)
        k = pts.shape[0]
        self._pts = np.concatenate([self._pts, pts])
        self._t = np.concatenate([self._t, np.full(k, float(t_s))])
        self._src = np.concatenate([self._src, np.full(k, sensor, dtype=np.int64)])
        self._free_n = np.concatenate([self._free_n, np.zeros(k, dtype=np.int64)])
        self._free_t0 = np.concatenate([self._free_t0, np.full(k, np.nan)])
        self._spread = np.concatenate([self._spread, spread])
        excess = self._t.size - self._max_points
        if excess > 0:
            # Stable sort: among equal times the older rows (earlier in the arrays) go first.
            order = np.argsort(self._t, kind="stable")[excess:]
            order.sort()
            self._keep(order)
            self.dropped_full += excess

    def _merge(
        self, idx: npt.NDArray[np.intp], pts: FloatArray, spread: FloatArray, t_s: float, sensor: int
    ) -> tuple[FloatArray, FloatArray]:
        """Merge a batch with the remembered points ``idx``; returns the batch's points still to add.

        A new return at least twice as precise (half the spread) within a remembered point's spread is the same
        surface seen closer: it supersedes that point, which goes. Otherwise a remembered point within the merge
        radius of new points is refreshed in place: time and sensor, clearing count restarted, the spread the
        largest of its own and theirs, and the height of the nearest of them (a horizontal scan's height is the
        vehicle's: climbing must not stack the points in layers). Those new points are not added.
        """
        d2 = _sq_dists(self._pts[idx], pts)
        old = self._spread[idx]
        reach2 = np.maximum(old, self._merge_radius_m) ** 2
        sharper = (spread[None, :] > 0.0) & (2.0 * spread[None, :] <= old[:, None]) & (d2 < reach2[:, None])
        gone: npt.NDArray[np.bool_] = np.asarray(sharper.any(axis=1))
        close = (d2 < self._merge_radius_m**2) & ~gone[:, None]
        hit: npt.NDArray[np.bool_] = np.asarray(close.any(axis=1))
        seen = idx[hit]
        close_seen = close[hit]
        self._spread[seen] = np.maximum(old[hit], np.where(close_seen, spread[None, :], 0.0).max(axis=1))
        z_new = pts[np.argmin(np.where(close_seen, d2[hit], np.inf), axis=1), 2]
        moved = z_new != self._pts[seen, 2]
        self._pts[seen, 2] = z_new
        self._t[seen] = float(t_s)
        self._src[seen] = sensor
        self._free_n[seen] = 0
        self._free_t0[seen] = np.nan
        # Every new point stays within the merge radius of a remembered one: those a new height leaves farther
        # are added.
        if moved.any():
            close_seen[moved] = _sq_dists(self._pts[seen[moved]], pts) < self._merge_radius_m**2
        new: npt.NDArray[np.bool_] = np.asarray(~close_seen.any(axis=0))
        if gone.any():
            keep = np.ones(self._t.size, dtype=np.bool_)
            keep[idx[gone]] = False
            self._keep(keep)
        return pts[new], spread[new]

    def expire(self, now_s: float) -> int:
        """Drop points last seen more than ``expiry_s`` before ``now_s``; returns how many."""
        keep = self._t >= now_s - self._expiry_s
        removed = int(keep.size - np.count_nonzero(keep))
        if removed:
            self._keep(keep)
        return removed

    def points(self, now_s: float) -> FloatArray:
        """(N, 3) float64 copy of the remembered points still valid at ``now_s`` (expired ones removed)."""
        self.expire(now_s)
        return self._pts.copy()

    def ages_s(self, now_s: float) -> FloatArray:
        """(N,) time since each remembered point was last seen [s], in the order of ``points``."""
        self.expire(now_s)
        return np.asarray(now_s - self._t, dtype=np.float64)

    def clear_observed(
        self,
        scan: RangeScan,
        pose: Pose,
        *,
        beam_half_width_rad: float | None = None,
        margin_m: float = 0.3,
        vertical_window_m: float = 1.0,
        sensor: int = -1,
        clear_scans: int = 1,
        clear_span_s: float = 0.0,
    ) -> int:
        """Remove remembered points that ``scan`` (taken at ``pose``) sees through; returns how many.

        Parameters
        ----------
        scan, pose:
            The scan and the pose at its measurement time.
        beam_half_width_rad:
            Half the angular width of one element; default ``element_half_width_rad`` of the bearings
            (0 for a one-beam scan: a single beam then clears only what lies exactly on it, i.e. nothing).
        margin_m:
            A point must be at least this much nearer than the reading to be cleared [m]; keeps the
            obstacle that produced the reading. A point with a spread must be that much nearer than the reading
            of every beam whose window meets its disc (module docstring).
        vertical_window_m:
            Only points within this height of the vehicle are in the scan's plane [m].
        sensor, clear_scans, clear_span_s:
            The scan's sensor; a point it sees through is removed once ``clear_scans`` scans of the sensor that
            saw the point (or of any sensor, for points added with -1) saw through it over ``clear_span_s``.
        """
        if self._t.size == 0 or len(scan) == 0:
            return 0
        cleared = self._seen_through(scan, pose, beam_half_width_rad, margin_m, vertical_window_m)
        ours = cleared & ((self._src == sensor) | (self._src < 0))
        self.clears_refused += int(np.count_nonzero(cleared & ~ours))
        first = ours & (self._free_n == 0)
        self._free_t0[first] = scan.t_s
        self._free_n[ours] += 1
        gone = ours & (self._free_n >= clear_scans) & (scan.t_s - self._free_t0 >= clear_span_s)
        removed = int(np.count_nonzero(gone))
        if removed:
            self._keep(~gone)
        return removed

    def _seen_through(
        self, scan: RangeScan, pose: Pose, beam_half_width_rad: float | None, margin_m: float, vertical_window_m: float
    ) -> npt.NDArray[np.bool_]:
        """Which remembered points ``scan`` sees through (see ``clear_observed``)."""
        bearings = np.mod(scan_bearings_ned_rad(scan, pose), _TWO_PI)
        order = np.argsort(bearings)
        b_sorted = bearings[order]
        reach = scan.ranges_m[order]
        # Free beams clear out to range_max_m; obstacles up to their range; NaN beams nothing.
        reach = np.where(np.isposinf(reach), scan.range_max_m, reach)
        reach = np.where(np.isnan(reach), -np.inf, reach)
        if beam_half_width_rad is None:
            beam_half_width_rad = element_half_width_rad(b_sorted)

        rel = self._pts - pose.pos_ned_m
        dist_m = np.hypot(rel[:, 0], rel[:, 1])
        bearing = np.mod(np.arctan2(rel[:, 1], rel[:, 0]), _TWO_PI)
        beam, ang = _nearest_beam(b_sorted, bearing)
        cleared = (
            (ang <= beam_half_width_rad + 1e-12)
            & (dist_m < reach[beam] - margin_m)
            & (np.abs(rel[:, 2]) <= vertical_window_m)
        )
        wide = np.flatnonzero(cleared & (self._spread > 0.0))
        if wide.size:
            sin_disc = self._spread[wide] / np.maximum(dist_m[wide], 1e-9)
            reach_w = _nearest_reach(b_sorted, reach, beam[wide], bearing[wide], beam_half_width_rad, sin_disc)
            seen = dist_m[wide] < reach_w - margin_m
            # A point the disc keeps goes all the same when one of this scan's returns lies within its spread: that
            # return (added after clearing) stands for the surface the point may be, and measures it better. Along
            # a wall seen at grazing incidence there is none near (returns metres apart), at a door's jamb there is.
            kept = wide[~seen]
            ret = scan_to_points_ned(scan, pose)[:, :2] if kept.size else np.empty((0, 2))
            if ret.shape[0]:
                rel_k = self._pts[kept, None, :2] - ret[None, :, :]
                near = (np.einsum("ijk,ijk->ij", rel_k, rel_k) < self._spread[kept, None] ** 2).any(axis=1)
                seen[~seen] = near
            cleared[wide] = seen
        return np.asarray(cleared, dtype=np.bool_)
