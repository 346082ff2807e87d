"""The navigation potential of bapf-nav: geodesic distance to the goal on a coarse grid of remembered obstacles.

A square grid of ``n x n`` cells (north/east; 3D planners use the horizontal slice around the agent) is laid around
the agent and the goal. A cell is blocked when its centre is closer than the planner's clearance to a remembered
obstacle point (the obstacles inflated by the clearance); cells nobody has seen are free, as D* Lite assumes of
unknown space. The potential is the 8-connected shortest-path distance (steps h and h sqrt(2)) from each cell to
the goal. It has no local minimum other than the goal: a descent on it cannot be trapped by a concave obstacle
that the agent has seen, which is what the paper's potentials (Eqs. (1), (2)) cannot promise.

Computation: the occupancy stencil (``navoccupancy``) and Dijkstra's algorithm on the grid's graph
(``navsearch.FieldSearch``, which owns the graph); this module holds the grid's geometry: its frames, cells and
the bilinear lookup of a field.

The space beyond the grid is unknown, so optimistically free: the boundary cells start at their straight-line
distance to the goal, plus the grid's side when the goal lies inside the grid (a way out of the map and back is
taken only when the map has no way in), so "no path" means the agent's own region is closed.

A grid over a given flying area (``PlannerParams.nav_area_ne_m``) has a fixed corner, blocks its cells outside the
area and has no exits: beyond its edge is outside the area, so the goal's cells are the only seeds, and a goal
outside the area has none (no way). An area wider than ``MAX_AREA_CELLS`` cells (a fence round a field of hundreds
of metres) gets the moving grid instead, with its cells outside the area blocked: its edge cells inside the area
are exits, as without an area.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np
import numpy.typing as npt

from apf_companion.planning.area import FlyingArea, KeepOuts, area_bounds
from apf_companion.planning.navoccupancy import stencil_blocked
from apf_companion.planning.navsearch import FieldSearch
from apf_companion.planning.navzones import ZoneCells
from apf_companion.planning.params import MAX_AREA_CELLS

__all__ = ["NavGrid"]

FloatArray = npt.NDArray[np.float64]
BoolArray = npt.NDArray[np.bool_]
IntArray = npt.NDArray[np.intp]


class NavGrid:
    """The square navigation grid (shared by all agents of a planner): its geometry, and the occupancy and fields
    computed on it (``navoccupancy``, ``search``).

    Parameters
    ----------
    cell_m : cell size h [m].
    side_m : side of the square grid [m]; n = ceil(side / h) cells a side.
    """

    def __init__(
        self,
        cell_m: float,
        side_m: float,
        area_ne_m: FlyingArea | None = None,
        keepouts_ne_m: KeepOuts = (),
        zone_margin_m: float = 0.0,
    ) -> None:
        self.cell_m = float(cell_m)
        #: The flying area (a rectangle or a polygon, ``area``) [m], or None. The grid covers it (its bounds) when
        #: they fit in ``MAX_AREA_CELLS`` cells a side; otherwise, and without an area, a grid of side ``side_m``
        #: moves with the agent and its edge cells are exits.
        self.area_ne_m = area_ne_m
        #: The grid's corner when it covers a flying area (on the lattice of multiples of the cell size), else None.
        self.fixed_origin_m: FloatArray | None = None
        self.n = math.ceil(side_m / cell_m - 1e-9)
        if area_ne_m is not None:
            bounds = area_bounds(area_ne_m)
            low = np.array(bounds[:2], dtype=np.float64)
            high = np.array(bounds[2:], dtype=np.float64)
            origin = np.floor(low / self.cell_m) * self.cell_m
            n = max(math.ceil(float(x) / self.cell_m - 1e-9) for x in high - origin)
            if n <= MAX_AREA_CELLS:
                self.fixed_origin_m, self.n = origin, n
        self.size = self.n * self.n
        #: The cells the area and the keep-out zones (``nav_keepout_ne_m``) close, with a band of
        #: ``zone_margin_m`` along their edges (``navzones``).
        self.zones = ZoneCells(area_ne_m, keepouts_ne_m, zone_margin_m, self.cell_m, self.n)
        edge = np.zeros((self.n, self.n), dtype=bool)
        edge[0, :] = edge[-1, :] = edge[:, 0] = edge[:, -1] = True
        #: The boundary cells (the exits into unknown space) and their centres (E, 2) from the grid's corner [m].
        self.edge_cells = np.flatnonzero(edge)
        edge_i, edge_j = np.divmod(self.edge_cells, self.n)
        self.edge_centres_m = np.stack([(edge_i + 0.5) * self.cell_m, (edge_j + 0.5) * self.cell_m], axis=1)
        #: The Dijkstra search of this grid's fields (the owner of its graph).
        self.search = FieldSearch(self)

    @property
    def exits(self) -> bool:
        """Whether the edge cells are exits into unknown space (a moving grid: no flying area, or a wide one)."""
        return self.fixed_origin_m is None

    def origins(self, positions_xy_m: FloatArray, goals_xy_m: FloatArray, pad_m: float) -> FloatArray:
        """(B, 2) lower corners of grids that hold the agent (and the goal when it fits, else the way to it).

        The grid is centred between agent and goal, but never farther than ``side / 2 - max(pad, side / 3)`` from
        the agent: at least a third of the side stays behind it (a trap it has to back out of lies there).
        Corners lie on the lattice of multiples of the cell size, so grids of one agent overlap cell for cell
        (``shift_blocked``).
        """
        if self.fixed_origin_m is not None:
            return np.broadcast_to(self.fixed_origin_m, positions_xy_m.shape).copy()
        side = self.n * self.cell_m
        delta = goals_xy_m - positions_xy_m
        dist = np.sqrt(np.einsum("bd,bd->b", delta, delta))
        half_room = max(side / 2.0 - max(pad_m, side / 3.0), 0.0)
        reach = np.minimum(dist / 2.0, half_room)
        with np.errstate(invalid="ignore", divide="ignore"):
            unit = np.where(dist[:, None] > 0.0, delta / dist[:, None], 0.0)
        centre = positions_xy_m + unit * reach[:, None]
        return np.asarray(np.floor((centre - side / 2.0) / self.cell_m) * self.cell_m, dtype=np.float64)

    def shift_blocked(self, blocked: BoolArray, old_origin_m: FloatArray, new_origin_m: FloatArray) -> BoolArray:
        """One agent's remembered cells (n^2,) moved from the grid at ``old_origin_m`` to ``new_origin_m``."""
        n = self.n
        di, dj = np.rint((new_origin_m - old_origin_m) / self.cell_m).astype(int)
        out = np.zeros((n, n), dtype=bool)
        if abs(di) >= n or abs(dj) >= n:
            return out.ravel()
        old = blocked.reshape(n, n)
        out[max(0, -di) : n - max(0, di), max(0, -dj) : n - max(0, dj)] = old[
            max(0, di) : n - max(0, -di), max(0, dj) : n - max(0, -dj)
        ]
        return out.ravel()

    def cell_of(self, origins_m: FloatArray, points_xy_m: FloatArray) -> tuple[IntArray, IntArray]:
        """Cell indices (i, j) of points (B, ..., 2) in grids with lower corners (B, 2); may be out of range."""
        shape = (origins_m.shape[0],) + (1,) * (points_xy_m.ndim - 2)
        rel = (points_xy_m - origins_m.reshape(*shape, 2)) / self.cell_m
        with np.errstate(invalid="ignore"):
            ij = np.floor(rel)
        ij = np.nan_to_num(ij, nan=-1.0, posinf=-1.0, neginf=-1.0)
        ij = np.clip(ij, -1, self.n)
        return ij[..., 0].astype(np.intp), ij[..., 1].astype(np.intp)

    def flat_cell(self, origin_m: FloatArray, point_xy_m: FloatArray) -> int:
        """The cell (flat index) of one point in one grid, -1 off the grid."""
        i, j = self.cell_of_one(origin_m, point_xy_m)
        return i * self.n + j if 0 <= i < self.n and 0 <= j < self.n else -1

    def cell_of_one(self, origin_m: FloatArray, point_xy_m: FloatArray) -> tuple[int, int]:
        """``cell_of`` of one point in one grid, on Python floats (the same IEEE arithmetic: a difference and a
        quotient, floored; non-finite is -1; clipped to [-1, n])."""
        out = []
        for d in range(2):
            rel = (float(point_xy_m[d]) - float(origin_m[d])) / self.cell_m
            out.append(min(max(math.floor(rel), -1), self.n) if math.isfinite(rel) else -1)
        return out[0], out[1]

    def blocked(
        self, origins_m: FloatArray, obstacles_xy_m: FloatArray, valid: BoolArray, radius_m: float
    ) -> BoolArray:
        """(B, n^2) cells whose centre lies closer than ``radius_m`` to a valid obstacle point.

        ``obstacles_xy_m`` (B, N, 2), ``valid`` (B, N). Each point marks a small stencil of cells (vectorised).
        """
        return self.blocked_within(origins_m, obstacles_xy_m, valid, (radius_m,))[0]

    def blocked_within(
        self, origins_m: FloatArray, obstacles_xy_m: FloatArray, valid: BoolArray, radii_m: tuple[float, ...]
    ) -> list[BoolArray]:
        """``blocked`` for several radii at once (``navoccupancy.stencil_blocked``)."""
        return stencil_blocked(self.n, self.cell_m, origins_m, obstacles_xy_m, valid, radii_m)

    def distances(self, origins_m: FloatArray, blocked: BoolArray, goals_xy_m: FloatArray) -> FloatArray:
        """(B, n^2) geodesic distance from each cell centre to the goal [m]; inf for blocked/unreachable cells
        (``search``)."""
        return self.search.distances(origins_m, blocked, goals_xy_m)

    def sample(self, origin_m: FloatArray, dist_m: FloatArray, points_xy_m: FloatArray) -> FloatArray:
        """Bilinear value of one field at points (P, 2), over the finite corners only; inf outside or enclosed."""
        return np.asarray(self.sample_many(origin_m[None], dist_m[None], points_xy_m[None])[0], dtype=np.float64)

    def corner_cells(self, origin_m: FloatArray, points_xy_m: FloatArray) -> IntArray:
        """The cells (flat indices) whose values ``sample`` weighs (weight > 0) at points (P, 2) of one grid."""
        cells, w = self._corners((points_xy_m - origin_m) / self.cell_m - 0.5)
        out: IntArray = cells[w > 0.0]
        return out

    def sample_many(
        self, origins_m: FloatArray, dists_m: FloatArray | Sequence[FloatArray], points_xy_m: FloatArray
    ) -> FloatArray:
        """``sample`` for R fields at once: origins (R, 2), fields (R, n^2) or R arrays (n^2,), points (R, P, 2)
        -> (R, P).

        Element for element the same arithmetic as one field at a time, so the values do not depend on R. Fields
        given one by one are read where the points need them, not stacked first (a copy of every cell of R fields:
        most of the cost at the study's R).
        """
        n, h = self.n, self.cell_m
        rel = (points_xy_m - origins_m[:, None, :]) / h - 0.5
        cells, w = self._corners(rel)
        if isinstance(dists_m, np.ndarray):
            val = dists_m[np.arange(origins_m.shape[0])[None, :, None], cells]
        elif len(dists_m) == 0:
            val = np.empty(cells.shape)
        else:
            val = np.stack([dist[cells[:, i]] for i, dist in enumerate(dists_m)], axis=1)
        ok = np.isfinite(val) & (w > 0.0)
        term = np.where(ok, w * np.where(ok, val, 0.0), 0.0)
        weight = np.where(ok, w, 0.0)
        # Summed corner by corner in this order (not a reduction, whose order numpy may change).
        num = term[0] + term[1] + term[2] + term[3]
        den = weight[0] + weight[1] + weight[2] + weight[3]
        inside = (rel[..., 0] >= -0.5) & (rel[..., 0] <= n - 0.5) & (rel[..., 1] >= -0.5) & (rel[..., 1] <= n - 0.5)
        with np.errstate(invalid="ignore", divide="ignore"):
            out = np.where(inside & (den > 0.0), num / den, np.inf)
        return np.asarray(out, dtype=np.float64)

    def _corners(self, rel: FloatArray) -> tuple[IntArray, FloatArray]:
        """The bilinear corners of points ``rel`` (..., 2) in cells less half a cell: their flat cells (clamped to the
        grid) and weights, (4, ...) each, in the order (i0, j0), (i0, j0 + 1), (i0 + 1, j0), (i0 + 1, j0 + 1)."""
        n = self.n
        i0 = np.floor(rel[..., 0]).astype(np.intp)
        j0 = np.floor(rel[..., 1]).astype(np.intp)
        fi = rel[..., 0] - i0
        fj = rel[..., 1] - j0
        ii = (np.minimum(np.maximum(i0, 0), n - 1), np.minimum(np.maximum(i0 + 1, 0), n - 1))
        jj = (np.minimum(np.maximum(j0, 0), n - 1), np.minimum(np.maximum(j0 + 1, 0), n - 1))
        wi, wj = (1.0 - fi, fi), (1.0 - fj, fj)
        cells = np.stack([ii[a] * n + jj[b] for a in (0, 1) for b in (0, 1)])
        w = np.stack([wi[a] * wj[b] for a in (0, 1) for b in (0, 1)])
        return cells, w
