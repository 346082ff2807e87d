"""The Dijkstra search behind bapf-nav's escape potential (``navfield``): one field per call, on a graph built
once per grid.

Dijkstra's algorithm (scipy's compiled ``csgraph.dijkstra``; the tests check it against a plain heap search) on the
8-connected grid plus one extra source node, whose edge to each seed cell weighs that cell's initial value. The
graph, its structure included, is built once per grid (the source's row has a slot for every cell that can be a
seed); a field only writes weights: h or h sqrt(2) into a free cell, inf into a blocked one and into a slot that
seeds nothing (Dijkstra never relaxes an infinite edge, so a blocked cell is never reached), and the goal's cells
into their slots. No Python loop runs over cells or obstacles.
"""

from __future__ import annotations

import math
from typing import TYPE_CHECKING

import numpy as np
import numpy.typing as npt
from scipy.sparse import csr_matrix
from scipy.sparse.csgraph import dijkstra

if TYPE_CHECKING:
    from apf_companion.planning.navfield import NavGrid

__all__ = ["FieldSearch"]

FloatArray = npt.NDArray[np.float64]
BoolArray = npt.NDArray[np.bool_]
IntArray = npt.NDArray[np.intp]
#: Dijkstra's search limit [m]: finite, so a way over an infinite (blocked) edge is never queued.
_LIMIT_M = 1e300
#: Slots of the source's row for the goal's cell and its 8 neighbours (unused ones loop back to the source at inf).
_GOAL_SLOTS = 9


class FieldSearch:
    """The geodesic fields of one ``NavGrid``: the owner of its graph and of the weights each field writes.

    Notes
    -----
    The graph has a node per cell (index i n + j) and the source node n^2; rows of its CSR matrix list a cell's
    in-grid neighbours (``indices``, ``indptr`` and the step costs ``edge_cost``); the last row, the source's
    edges, has ``_GOAL_SLOTS`` slots for the goal's cells, then one per edge cell. The matrix is built once and
    each field writes its weights (and the goal slots' cells) into it, which saves the matrix's construction and
    checks per field (about 15 % of a field): a search computes one field at a time (not thread-safe).
    """

    def __init__(self, grid: NavGrid) -> None:
        self._grid = grid
        # The edge cells' centres as contiguous columns, for the seeds of every field (``_seeds``).
        self._edge_north_m = grid.edge_centres_m[:, 0].copy()
        self._edge_east_m = grid.edge_centres_m[:, 1].copy()
        src, dst, self.edge_cost = _grid_edges(grid.n, grid.cell_m)
        # The CSR arrays in scipy's index type (int32: fewer than 2^31 edges at 4096 cells a side), so that the
        # matrix of a field is made without converting them. Row pointers of the cells' rows; the source's row
        # (the seeds) is appended per field.
        self.indices = dst.astype(np.int32)
        self.indptr = np.concatenate([[0], np.cumsum(np.bincount(src, minlength=grid.size))]).astype(np.int32)
        self._in_edges = _in_edges(dst, grid.size)
        # The whole graph, weights written per field (``distances``): the edges, the goal slots, the edge cells'
        # slots, and a scratch slot that the padding of ``_in_edges`` (-1) writes to.
        self._n_edges = int(dst.size)
        n_source = _GOAL_SLOTS + grid.edge_cells.size
        self._weights = np.empty(self._n_edges + n_source + 1)
        indices = np.concatenate(
            [self.indices, np.full(_GOAL_SLOTS, grid.size, dtype=np.int32), grid.edge_cells.astype(np.int32)]
        )
        indptr = np.append(self.indptr, np.int32(self.indptr[-1] + n_source))
        self._graph = csr_matrix((self._weights[:-1], indices, indptr), shape=(grid.size + 1, grid.size + 1))

    def distances(self, origins_m: FloatArray, blocked: BoolArray, goals_xy_m: FloatArray) -> FloatArray:
        """(B, n^2) geodesic distance from each cell centre to the goal [m]; inf for blocked/unreachable cells."""
        size = self._grid.size
        out = np.full(blocked.shape, np.inf)
        goal_slots = self._link()
        weights = self._weights
        for b in range(origins_m.shape[0]):
            blk = blocked[b].copy()
            if not self._seeds(origins_m[b], blk, goals_xy_m[b], goal_slots):
                continue
            # An edge into a blocked cell is infinite (edges out of one need not be: it is never reached).
            weights[: self._n_edges] = self.edge_cost
            weights[self._in_edges[np.flatnonzero(blk)]] = np.inf
            # The finite limit keeps ways over infinite edges out of the heap: cells behind them stay inf.
            out[b] = dijkstra(self._graph, directed=True, indices=size, limit=_LIMIT_M)[:size]
        return out

    def _link(self) -> IntArray:
        """Point the matrix's weights at ``_weights`` and return the goal slots' cells, a view of its indices. Done
        at each use, not kept: a copy of the grid (``copy.deepcopy``, pickling) copies views into separate arrays."""
        self._graph.data = self._weights[:-1]
        slots: IntArray = self._graph.indices[self._n_edges : self._n_edges + _GOAL_SLOTS]
        return slots

    def _seeds(self, origin_m: FloatArray, blocked: BoolArray, goal_xy_m: FloatArray, goal_slots: IntArray) -> bool:
        """Write one field's source weights: the goal's cell (freed in ``blocked``) and its 8 neighbours at the
        straight-line distance, when the goal is inside the grid, and the boundary (above); inf where a cell is
        blocked (no seed). An edge cell near the goal has two slots: the lower value wins. ``goal_slots``: the goal
        slots' cells in the graph (``_link``). Whether any cell is a seed."""
        grid = self._grid
        n, h = grid.n, grid.cell_m
        ne = self._n_edges
        gi, gj = grid.cell_of_one(origin_m, goal_xy_m)
        goal_slots[:] = grid.size  # unused: the source's own node, at inf
        goal_values = self._weights[ne : ne + _GOAL_SLOTS]
        goal_values[:] = np.inf
        if grid.zones.active:
            if grid.zones.goal_closed(goal_xy_m):
                return False  # no way to a goal outside the flying area or in a keep-out zone
            grid.zones.close(origin_m, blocked, (gi, gj))  # before the goal's cell is freed below: it stays reachable
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
        if grid.exits:
            north, east = self._edge_north_m, self._edge_east_m
            euclid = np.hypot(origin_m[0] + north - goal_xy_m[0], origin_m[1] + east - goal_xy_m[1])
            np.add(euclid, detour, out=edge_values)
            edge_values[blocked[grid.edge_cells]] = np.inf
        else:
            edge_values[:] = np.inf
        return bool(np.isfinite(self._weights[ne:-1]).any())


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
