"""bapf-nav's line of sight on rows of agents: whether the straight line to the goal crosses the remembered map,
which starts an escape before a concave obstacle traps the agent (``BapfNavPlanner._start``; one agent:
``navsingle.SightLine``, the same result).
"""

from __future__ import annotations

import numpy as np
import numpy.typing as npt

from apf_companion.planning.area import zones_block_line, zones_bound_lines
from apf_companion.planning.clearance import compact_rows
from apf_companion.planning.params import PlannerParams

__all__ = ["LineOfSight"]

FloatArray = npt.NDArray[np.float64]
BoolArray = npt.NDArray[np.bool_]
IntArray = npt.NDArray[np.intp]

#: Agents x obstacle points per group in the line-of-sight test (``LineOfSight.blocked``).
_SIGHT_CELLS = 32768
#: Known points closer than this to each other belong to one surface (sampled every 0.2 m, ``blocked``).
_SURFACE_M = 0.45
#: Slack of the sight test's neighbour prefilter (``blocked``): rounding is below 1e-12 m there [m].
_AROUND_SLACK_M = 1e-3
#: Blocking points tested for being part of a surface, the first along the line (``blocked``).
_SIGHT_FIRST = 3
#: Smallest normal float64: the divisor for an agent on its goal (zero direction, never 0/0).
_TINY = float(np.finfo(np.float64).tiny)
_any = np.logical_or.reduce


class LineOfSight:
    """The line-of-sight test of a planner's agents.

    Parameters
    ----------
    params : the planner's parameters; clearance_m : its clearance C [m].
    """

    def __init__(self, params: PlannerParams, clearance_m: float) -> None:
        self.params = params
        self.clearance_m = clearance_m
        self._c2 = clearance_m * clearance_m
        self._around2 = (clearance_m + _SURFACE_M + _AROUND_SLACK_M) ** 2

    def blocked(
        self,
        active: BoolArray,
        positions_m: FloatArray,
        targets_m: FloatArray,
        obstacles_m: FloatArray,
        obstacle_mask: BoolArray | None,
    ) -> BoolArray:
        """(A,) agents of ``active`` whose straight line to the goal is blocked on the remembered map.

        The line runs from one step ahead of the agent (an obstacle beside the agent that noise brought within C
        does not block it) to ``nav_sight_m`` towards the goal, or to the goal. A known obstacle point closer to
        it than the clearance C lies on the inflated map that the escape grid is built from. The line is blocked
        when such a point lies on its first ``nav_sight_points_m`` (any point: a cluster of the paper's point
        obstacles just ahead is passed on the grid's potential, not greedily on the side met first), or when
        one of the first ``_SIGHT_FIRST`` such points along the whole line is part of a surface: two other known
        points lie within ``_SURFACE_M`` of it (its neighbours on a wall or trunk sampled every 0.2 m), which
        starts the escape before a concave wall traps the agent. All off when ``nav_sight_m`` is 0. A line that
        leaves a polygonal flying area or passes within C of its inner corners, or comes within C of a keep-out
        zone, is blocked too, whatever ``nav_sight_m`` (``area.leaves_area``, ``area.meets_keepout``).
        """
        out = self._points_block(active, positions_m, targets_m, obstacles_m, obstacle_mask)
        area, keepouts = self.params.nav_area_ne_m, self.params.nav_keepout_ne_m
        if zones_bound_lines(area, keepouts):
            rows = np.flatnonzero(active)
            start, end = positions_m[rows, :2], targets_m[rows, :2]
            out[rows] |= zones_block_line(area, keepouts, start, end, self.clearance_m)
        return out

    def _points_block(
        self,
        active: BoolArray,
        positions_m: FloatArray,
        targets_m: FloatArray,
        obstacles_m: FloatArray,
        obstacle_mask: BoolArray | None,
    ) -> BoolArray:
        """``blocked`` by the remembered points alone."""
        p = self.params
        out = np.zeros(positions_m.shape[0], dtype=bool)
        if p.nav_sight_m <= 0.0 or obstacles_m.shape[1] == 0:
            return out
        rows = np.flatnonzero(active)
        first = min(_SIGHT_FIRST, obstacles_m.shape[1])
        near_m = min(p.nav_sight_points_m, p.nav_sight_m)
        group = max(1, _SIGHT_CELLS // obstacles_m.shape[1])  # (group, M) temporaries stay small
        for lo in range(0, rows.size, group):
            r = rows[lo : lo + group]
            to_goal = targets_m[r] - positions_m[r]
            dist = np.sqrt(np.einsum("ad,ad->a", to_goal, to_goal))
            unit = to_goal / np.maximum(dist, _TINY)[:, None]
            obs = obstacles_m[r]
            rel = obs - positions_m[r][:, None, :]
            with np.errstate(invalid="ignore", over="ignore"):  # unknown rows may be non-finite: they compare False
                along = np.einsum("amd,ad->am", rel, unit)
            hit, off2 = self._line_hits(rel, along, unit, np.minimum(dist, p.nav_sight_m), obstacle_mask, r)
            if near_m > 0.0:
                out[r] = _any(self._line_hits(rel, along, unit, np.minimum(dist, near_m), obstacle_mask, r)[0], axis=1)
            some = np.flatnonzero(_any(hit, axis=1) & ~out[r])
            if some.size == 0:
                continue
            order = np.where(hit[some], along[some], np.inf)
            picks = np.argpartition(order, first - 1, axis=1)[:, :first]  # (S, F) the first hits along the line
            real = np.take_along_axis(hit[some], picks, axis=1)
            pts = obs[some[:, None], picks]  # (S, F, D)
            # A pick's neighbours (within 0.45 m of a point within C of the segment) lie within C + 0.45 m of it:
            # only those are compared (``_AROUND_SLACK_M`` over the rounding of these few metres).
            around = off2[some] < self._around2  # NaN compares False
            if obstacle_mask is not None:
                around &= obstacle_mask[r[some]]
            cand, valid = compact_rows(obs[some], around)
            with np.errstate(invalid="ignore", over="ignore"):
                gap = cand[:, None, :, :] - pts[:, :, None, :]  # (S, F, W, D)
                d2 = np.einsum("sfmd,sfmd->sfm", gap, gap)
            close = (d2 < _SURFACE_M * _SURFACE_M) & (d2 > 0.0) & valid[:, None, :]
            surface = (np.add.reduce(close, axis=2) >= 2) & real
            out[r[some]] = _any(surface, axis=1)
        return out

    def _line_hits(
        self,
        rel: FloatArray,
        along: FloatArray,
        unit: FloatArray,
        end: FloatArray,
        obstacle_mask: BoolArray | None,
        rows: IntArray,
    ) -> tuple[BoolArray, FloatArray]:
        """(R, M) whether each point lies within C of the line's piece from one step ahead to ``end`` (R,) [m], and
        its squared distance to that piece; ``rel`` (R, M, D) the points minus the agents, ``along`` (R, M) their
        coordinates along the line, ``unit`` (R, D) its direction."""
        start = np.minimum(self.params.step_m, end)
        with np.errstate(invalid="ignore", over="ignore"):  # unknown rows may be non-finite: they compare False
            t = np.clip(along, start[:, None], end[:, None])
            off = rel - t[:, :, None] * unit[:, None, :]
            off2: FloatArray = np.einsum("amd,amd->am", off, off)
        hit: BoolArray = off2 < self._c2
        if obstacle_mask is not None:
            hit &= obstacle_mask[rows]
        return hit, off2
