"""The cells of bapf-nav's escape grid that its flying area and keep-out zones close (``NavGrid``'s fields).

A cell is closed when its centre lies outside the flying area or in a keep-out zone (``hard``), and also when it
lies closer than the margin to an edge of either (``band``): the zones' edges are kept at the planner's clearance
C as obstacles are, so the field never leads along a fence line that position noise would cross (ArduPilot breaches
at the line itself, ``libraries/AC_Fence/AC_PolyFence_loader.cpp`` ``breached``). Near the goal the band gives way
(cells within the margin of the goal keep only ``hard``): a goal the user put near an edge stays reachable.

The cells depend on the grid's corner only: a fixed grid (over a flying area) computes them once, a moving grid
once per corner (an agent's grids keep their corner for many fields).
"""

from __future__ import annotations

import numpy as np
import numpy.typing as npt

from apf_companion.planning.area import FlyingArea, KeepOuts, area_polygon, near_edges, outside_zones

__all__ = ["ZoneCells"]

FloatArray = npt.NDArray[np.float64]
BoolArray = npt.NDArray[np.bool_]


class ZoneCells:
    """The closed cells of one grid's zones (module docstring).

    Parameters
    ----------
    area_ne_m : the flying area or None; keepouts_ne_m : the keep-out zones; margin_m : the band's width [m];
    cell_m : the cell size [m]; n : cells a side.
    """

    def __init__(
        self, area_ne_m: FlyingArea | None, keepouts_ne_m: KeepOuts, margin_m: float, cell_m: float, n: int
    ) -> None:
        self.area_ne_m = area_ne_m
        self.keepouts_ne_m = keepouts_ne_m
        self.margin_m = margin_m
        self.cell_m = cell_m
        self.n = n
        #: Whether there is anything to close.
        self.active = area_ne_m is not None or bool(keepouts_ne_m)
        self._memo: tuple[tuple[float, float], BoolArray, BoolArray] | None = None
        # The offsets (cells) of the goal's neighbourhood in which the band gives way.
        k = int(np.ceil(margin_m / cell_m))
        di, dj = np.meshgrid(np.arange(-k, k + 1), np.arange(-k, k + 1), indexing="ij")
        near = np.hypot(di, dj) * cell_m <= margin_m + 1e-9
        self._goal_di, self._goal_dj = di[near], dj[near]

    def goal_closed(self, goal_xy_m: FloatArray) -> bool:
        """Whether a goal lies outside the area or in a keep-out zone: no way to it."""
        return bool(outside_zones(self.area_ne_m, self.keepouts_ne_m, float(goal_xy_m[0]), float(goal_xy_m[1])))

    def close(self, origin_m: FloatArray, blocked: BoolArray, goal_cell: tuple[int, int]) -> None:
        """Close the zones' cells in one field's ``blocked`` (n^2,), in place; the band gives way around
        ``goal_cell`` (row, column; may lie off the grid)."""
        hard, closed = self._cells(origin_m)
        n = self.n
        i = goal_cell[0] + self._goal_di
        j = goal_cell[1] + self._goal_dj
        on = (i >= 0) & (i < n) & (j >= 0) & (j < n)
        near = i[on] * n + j[on]
        kept = blocked[near] | hard[near]  # the goal's neighbourhood: obstacles and hard cells only
        blocked |= closed
        blocked[near] = kept

    def _cells(self, origin_m: FloatArray) -> tuple[BoolArray, BoolArray]:
        """(hard, closed), each (n^2,), of the grid at ``origin_m``: the cells outside the area or in a keep-out
        zone, and those with the band along the edges; the latest corner's are kept."""
        key = (float(origin_m[0]), float(origin_m[1]))
        if self._memo is not None and self._memo[0] == key:
            return self._memo[1], self._memo[2]
        centres = origin_m[:, None] + (np.arange(self.n) + 0.5)[None, :] * self.cell_m  # (2, n)
        north, east = centres[0][:, None], centres[1][None, :]
        hard = outside_zones(self.area_ne_m, self.keepouts_ne_m, north, east)
        zones = self.keepouts_ne_m if self.area_ne_m is None else (area_polygon(self.area_ne_m), *self.keepouts_ne_m)
        closed = hard.copy()
        for zone in zones:
            closed |= near_edges(zone, north, east, self.margin_m)
        out = (hard.ravel(), closed.ravel())
        self._memo = (key, *out)
        return out
