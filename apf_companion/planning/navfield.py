"""The navigation potential of bapf-nav: geodesic distance to the goal on a coarse grid of remembered obstacles.

A square grid of ``n x n`` cells (north/east; 3D planners use the horizontal slice around the agent) is laid around
the agent and the goal. A cell is blocked when its centre is closer than the planner's clearance to a remembered
obstacle point (the obstacles inflated by the clearance); cells nobody has seen are free, as D* Lite assumes of
unknown space. The potential is the 8-connected shortest-path distance (steps h and h sqrt(2)) from each cell to
the goal. It has no local minimum other than the goal: a descent on it cannot be trapped by a concave obstacle
that the agent has seen, which is what the paper's potentials (Eqs. (1), (2)) cannot promise.

Computation: Dijkstra's algorithm (scipy's compiled ``csgraph.dijkstra``; the tests check it against a plain
heap search) on the 8-connected grid plus one extra source node, whose edge to each seed cell (below) weighs that
cell's initial value. The graph, its structure included, is built once per grid (the source's row has a slot for
every cell that can be a seed); a field only writes weights: h or h sqrt(2) into a free cell, inf into a blocked
one and into a slot that seeds nothing (Dijkstra never relaxes an infinite edge, so a blocked cell is never
reached), and the goal's cells into their slots. No Python loop runs over cells or obstacles.

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
from scipy.sparse import csr_matrix
from scipy.sparse.csgraph import dijkstra

from apf_companion.planning.area import FlyingArea, KeepOuts, area_bounds
from apf_companion.planning.navzones import ZoneCells
from apf_companion.planning.params import MAX_AREA_CELLS

__all__ = ["NavGrid"]

FloatArray = npt.NDArray[np.float64]
BoolArray = npt.NDArray[np.bool_]
IntArray = npt.NDArray[np.intp]
#: Dijkstra's search limit [m]: finite, so a way over an infinite (blocked) edge is never queued.
_LIMIT_M = 1e300
#: Slots of the source's row for the goal's cell and its 8 neighbours (unused ones loop back to the source at inf).
_GOAL_SLOTS = 9
_all = np.logical_and.reduce


class NavGrid:
    """Geometry and algorithms of the square navigation grid (shared by all agents of a planner).

    Parameters
    ----------
    cell_m : cell size h [m].
    side_m : side of the square grid [m]; n = ceil(side / h) cells a side.

    Notes
    -----
    The graph has a node per cell (index i n + j) and the source node n^2; rows of its CSR matrix list a cell's
    in-grid neighbours (``_indices``, ``_indptr`` and the step costs ``_edge_cost``); the last row, the source's
    edges, has ``_GOAL_SLOTS`` slots for the goal's cells, then one per edge cell. The matrix is built once and
    each field writes its weights (and the goal slots' cells) into it, which saves the matrix's construction and
    checks per field (about 15 % of a field): a grid computes one field at a time (not thread-safe).
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
        # The same as contiguous columns, for the seeds of every field (``_seeds``).
        self._edge_north_m = self.edge_centres_m[:, 0].copy()
        self._edge_east_m = self.edge_centres_m[:, 1].copy()
        src, dst, self._edge_cost = _grid_edges(self.n, self.cell_m)
        # The CSR arrays in scipy's index type (int32: fewer than 2^31 edges at 4096 cells a side), so that the
        # matrix of a field is made without converting them. Row pointers of the cells' rows; the source's row
        # (the seeds) is appended per field.
        self._indices = dst.astype(np.int32)
        self._indptr = np.concatenate([[0], np.cumsum(np.bincount(src, minlength=self.size))]).astype(np.int32)
        self._in_edges = _in_edges(dst, self.size)
        # The whole graph, weights written per field (``_distances``): the edges, the goal slots, the edge cells'
        # slots, and a scratch slot that the padding of ``_in_edges`` (-1) writes to.
        self._n_edges = int(dst.size)
        n_source = _GOAL_SLOTS + self.edge_cells.size
        self._weights = np.empty(self._n_edges + n_source + 1)
        indices = np.concatenate(
            [self._indices, np.full(_GOAL_SLOTS, self.size, dtype=np.int32), self.edge_cells.astype(np.int32)]
        )
        indptr = np.append(self._indptr, np.int32(self._indptr[-1] + n_source))
        self._graph = csr_matrix((self._weights[:-1], indices, indptr), shape=(self.size + 1, self.size + 1))

    @property
    def exits(self) -> bool:
        """Whether the edge cells are exits into unknown space (a moving grid: no flying area, or a wide one)."""
        return self.fixed_origin_m is None

    # --- frames ---------------------------------------------------------------------------------------------

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

    # --- occupancy ------------------------------------------------------------------------------------------

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
        """``blocked`` for several radii at once (one stencil, the largest radius's; the same cells each)."""
        n, h = self.n, self.cell_m
        outs = [np.zeros((origins_m.shape[0], self.size), dtype=bool) for _ in radii_m]
        if obstacles_xy_m.shape[1] == 0 or not valid.any():
            return outs
        top = max(radii_m)
        # Stencil offsets s from each point's cell: a cell's centre is more than (|s| - 0.5) h away, so cells
        # with |s| >= top / h + 0.5 are never within ``top``; one more cell each way keeps rounding far off.
        half = math.ceil(top / h + 0.5)
        steps = np.arange(-half, half + 1)
        s = steps.size
        b, m = np.nonzero(valid)
        rel = (obstacles_xy_m[b, m] - origins_m[b]) / h  # (P, 2) in cells
        base = np.floor(rel).astype(np.intp)
        # Points whose whole stencil lies off the grid mark nothing: leave them out (the memory of a flight
        # reaches far beyond the grid around the agent).
        reach = _all((base >= -half) & (base < n + half), axis=1)
        if not _all(reach, axis=None):
            b, rel, base = b[reach], rel[reach], base[reach]
        ci = base[:, 0:1] + steps[None, :]  # (P, S) stencil rows
        cj = base[:, 1:2] + steps[None, :]  # (P, S) stencil columns
        ddx = (ci + 0.5 - rel[:, 0:1]) * h
        ddy = (cj + 0.5 - rel[:, 1:2]) * h
        # The stencil is separable: (P, S, S) squared distances from one row and one column term per point; rows
        # and columns outside the grid are at infinity.
        dx2 = np.where((ci >= 0) & (ci < n), ddx * ddx, np.inf)
        dy2 = np.where((cj >= 0) & (cj < n), ddy * ddy, np.inf)
        d2 = (dx2[:, :, None] + dy2[:, None, :]).ravel()
        # The cells of the largest radius (the others are among them), as flat indices into (P, S, S): one index
        # array and 1-D gathers instead of three.
        k = np.flatnonzero(d2 < top * top)
        near2 = d2[k]
        point_row, col = np.divmod(k, s)  # point * S + stencil row, stencil column
        point = point_row // s
        rows, cells = b[point], ci.ravel()[point_row] * n + cj.ravel()[point * s + col]
        for out, radius in zip(outs, radii_m, strict=True):
            if radius == top:  # every cell found
                out[rows, cells] = True
            else:
                hit = near2 < radius * radius
                out[rows[hit], cells[hit]] = True
        return outs

    # --- the potential --------------------------------------------------------------------------------------

    def distances(self, origins_m: FloatArray, blocked: BoolArray, goals_xy_m: FloatArray) -> FloatArray:
        """(B, n^2) geodesic distance from each cell centre to the goal [m]; inf for blocked/unreachable cells."""
        return self._distances(origins_m, blocked, goals_xy_m)

    def _seeds(self, origin_m: FloatArray, blocked: BoolArray, goal_xy_m: FloatArray, goal_slots: IntArray) -> bool:
        """Write one field's source weights: the goal's cell (freed in ``blocked``) and its 8 neighbours at the
        straight-line distance, when the goal is inside the grid, and the boundary (above); inf where a cell is
        blocked (no seed). An edge cell near the goal has two slots: the lower value wins. ``goal_slots``: the goal
        slots' cells in the graph (``_link``). Whether any cell is a seed."""
        n, h = self.n, self.cell_m
        ne = self._n_edges
        gi, gj = self._cell_of_one(origin_m, goal_xy_m)
        goal_slots[:] = self.size  # unused: the source's own node, at inf
        goal_values = self._weights[ne : ne + _GOAL_SLOTS]
        goal_values[:] = np.inf
        if self.zones.active:
            if self.zones.goal_closed(goal_xy_m):
                return False  # no way to a goal outside the flying area or in a keep-out zone
            self.zones.close(origin_m, blocked, (gi, gj))  # before the goal's cell is freed below: it stays reachable
        detour = 0.0
        if 0 <= gi < n and 0 <= gj < n:
            blocked[gi * n + gj] = False  # the goal itself is always reachable in the grid
            near_i = np.arange(max(gi - 1, 0), min(gi + 2, n))
            near_j = np.arange(max(gj - 1, 0), min(gj + 2, n))
            near = (near_i[:, None] * n + near_j[None, :]).ravel()
            i, j = np.divmod(near, n)
            euclid = np.hypot(origin_m[0] + (i + 0.5) * h - goal_xy_m[0], origin_m[1] + (j + 0.5) * h - goal_xy_m[1])
            goal_slots[: near.size] = near
            goal_values[: near.size] = np.where(blocked[near], np.inf, euclid + 0.0)
            detour = n * h
        edge_values = self._weights[ne + _GOAL_SLOTS : -1]
        if self.exits:
            north, east = self._edge_north_m, self._edge_east_m
            euclid = np.hypot(origin_m[0] + north - goal_xy_m[0], origin_m[1] + east - goal_xy_m[1])
            np.add(euclid, detour, out=edge_values)
            edge_values[blocked[self.edge_cells]] = np.inf
        else:
            edge_values[:] = np.inf
        return bool(np.isfinite(self._weights[ne:-1]).any())

    def flat_cell(self, origin_m: FloatArray, point_xy_m: FloatArray) -> int:
        """The cell (flat index) of one point in one grid, -1 off the grid."""
        i, j = self._cell_of_one(origin_m, point_xy_m)
        return i * self.n + j if 0 <= i < self.n and 0 <= j < self.n else -1

    def _cell_of_one(self, origin_m: FloatArray, point_xy_m: FloatArray) -> tuple[int, int]:
        """``cell_of`` of one point in one grid, on Python floats (the same IEEE arithmetic: a difference and a
        quotient, floored; non-finite is -1; clipped to [-1, n])."""
        out = []
        for d in range(2):
            rel = (float(point_xy_m[d]) - float(origin_m[d])) / self.cell_m
            out.append(min(max(math.floor(rel), -1), self.n) if math.isfinite(rel) else -1)
        return out[0], out[1]

    def _link(self) -> IntArray:
        """Point the matrix's weights at ``_weights`` and return the goal slots' cells, a view of its indices. Done
        at each use, not kept: a copy of the grid (``copy.deepcopy``, pickling) copies views into separate arrays."""
        self._graph.data = self._weights[:-1]
        slots: IntArray = self._graph.indices[self._n_edges : self._n_edges + _GOAL_SLOTS]
        return slots

    def _distances(self, origins_m: FloatArray, blocked: BoolArray, goals_xy_m: FloatArray) -> FloatArray:
        out = np.full(blocked.shape, np.inf)
        goal_slots = self._link()
        weights = self._weights
        for b in range(origins_m.shape[0]):
            blk = blocked[b].copy()
            if not self._seeds(origins_m[b], blk, goals_xy_m[b], goal_slots):
                continue
            # An edge into a blocked cell is infinite (edges out of one need not be: it is never reached).
            weights[: self._n_edges] = self._edge_cost
            weights[self._in_edges[np.flatnonzero(blk)]] = np.inf
            # The finite limit keeps ways over infinite edges out of the heap: cells behind them stay inf.
            out[b] = dijkstra(self._graph, directed=True, indices=self.size, limit=_LIMIT_M)[: self.size]
        return out

    # --- lookup ---------------------------------------------------------------------------------------------

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


def _grid_edges(n: int, cell_m: float) -> tuple[IntArray, IntArray, FloatArray]:
    """(source, destination, cost) of the 8-connected n x n grid's directed edges, sorted by source cell."""
    i, j = np.divmod(np.arange(n * n), n)
    steps = [(di, dj) for di in (-1, 0, 1) for dj in (-1, 0, 1) if di or dj]
    src = np.concatenate([np.arange(n * n)] * len(steps))
    di = np.repeat([s[0] for s in steps], n * n)
    dj = np.repeat([s[1] for s in steps], n * n)
    ii, jj = np.tile(i, len(steps)) + di, np.tile(j, len(steps)) + dj
    ok = (ii >= 0) & (ii < n) & (jj >= 0) & (jj < n)
    cost = np.where((di != 0) & (dj != 0), cell_m * math.sqrt(2.0), cell_m)
    order = np.argsort(src[ok], kind="stable")
    return src[ok][order], (ii * n + jj)[ok][order], cost[ok][order]


def _in_edges(dst: IntArray, size: int) -> IntArray:
    """(size, 8) positions of the edges into each cell (``_grid_edges``' order), padded with -1."""
    order = np.argsort(dst, kind="stable")
    counts = np.bincount(dst, minlength=size)
    slot = np.arange(dst.size) - (np.cumsum(counts) - counts)[dst[order]]
    out = np.full((size, 8), -1, dtype=np.intp)
    out[dst[order], slot] = order
    return out
