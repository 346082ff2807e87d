"""The navigation potential of bapf-nav: geodesic distance to the goal on a coarse grid of remembered obstacles.

A square grid of ``n x n`` cells (north/east; 3D planners use the horizontal slice around the agent) is laid around
the agent and the goal. A cell is blocked when its centre is closer than the planner's clearance to a remembered
obstacle point (the obstacles inflated by the clearance); cells nobody has seen are free, as D* Lite assumes of
unknown space. The potential is the 8-connected shortest-path distance (steps h and h sqrt(2)) from each cell to
the goal. It has no local minimum other than the goal: a descent on it cannot be trapped by a concave obstacle
that the agent has seen, which is what the paper's potentials (Eqs. (1), (2)) cannot promise.

Computation: vectorised fast sweeping (exact 8-connected shortest paths; the tests check it against
Dijkstra). Along one grid line with constant step cost c, the relaxation d[i] = min(d[i], min_{j<i} d[j] +
c (i - j)) is a cumulative minimum of d[j] - c j; a blocked cell must stop the propagation, so the line is cut
into segments at blocked cells by adding a large per-segment offset. One sweep runs both directions of rows,
columns and both diagonals for all agents at once; sweeps repeat until nothing changes (a path with t turns
needs about t + 1 sweeps). No Python loop runs over cells or obstacles.

The space beyond the grid is unknown, so optimistically free: the boundary cells start at their straight-line
distance to the goal, plus the grid's side when the goal lies inside the grid (a way out of the map and back is
taken only when the map has no way in), so "no path" means the agent's own region is closed.
"""

from __future__ import annotations

import math
from typing import TypeVar

import numpy as np
import numpy.typing as npt
from numpy.lib.stride_tricks import as_strided

__all__ = ["NavGrid"]

FloatArray = npt.NDArray[np.float64]
BoolArray = npt.NDArray[np.bool_]
IntArray = npt.NDArray[np.intp]
_Scalar = TypeVar("_Scalar", np.float64, np.bool_)

#: Sweep rounds at most; a path with more turns than this is cut short (its cells keep an upper bound).
_MAX_ROUNDS = 40
#: Convergence: a round that lowers no cell by more than this ends the sweeps [m].
_CONVERGED_M = 1e-9
#: Agents whose fields are computed in one array program. One: at n = 54 a field costs the same alone as in a
#: batch of 16 (the arrays are large enough), each agent stops at its own convergence instead of the slowest's,
#: and an agent's field depends on nothing but its own map (the segment offset ``big`` and the number of rounds
#: were batch-wide, which moved values by rounding, about 1e-10 m).
_BATCH = 1


class NavGrid:
    """Geometry and algorithms of the square navigation grid (shared by all agents of a planner).

    Parameters
    ----------
    cell_m : cell size h [m].
    side_m : side of the square grid [m]; n = ceil(side / h) cells a side.

    Notes
    -----
    The sweeps work on one buffer per agent: n rows of 3n values, the grid's row i in the middle third and
    blocked padding on both sides. Rows and columns are plain views of it; the two diagonal families are
    strided views (row stride 3n - 1 or 3n + 1), in which every column is one diagonal of the grid and the
    padding separates the diagonals. So every family is swept along an axis of a view, with no gather/scatter.
    """

    def __init__(self, cell_m: float, side_m: float) -> None:
        self.cell_m = float(cell_m)
        self.n = math.ceil(side_m / cell_m - 1e-9)
        self.size = self.n * self.n
        edge = np.zeros((self.n, self.n), dtype=bool)
        edge[0, :] = edge[-1, :] = edge[:, 0] = edge[:, -1] = True
        self._edge = edge.reshape(1, -1)

    # --- frames ---------------------------------------------------------------------------------------------

    def origins(self, positions_xy_m: FloatArray, goals_xy_m: FloatArray, pad_m: float) -> FloatArray:
        """(B, 2) lower corners of grids that hold the agent (and the goal when it fits, else the way to it).

        The grid is centred between agent and goal, but never farther than ``side / 2 - max(pad, side / 3)`` from
        the agent: at least a third of the side stays behind it (a trap it has to back out of lies there).
        Corners lie on the lattice of multiples of the cell size, so grids of one agent overlap cell for cell
        (``shift_blocked``).
        """
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
        n_batch = origins_m.shape[0]
        out = np.zeros((n_batch, self.size), dtype=bool)
        if obstacles_xy_m.shape[1] == 0 or not valid.any():
            return out
        h = self.cell_m
        reach = math.ceil(radius_m / h) + 1
        grid_i, grid_j = np.meshgrid(np.arange(-reach, reach + 1), np.arange(-reach, reach + 1), indexing="ij")
        di, dj = grid_i.ravel(), grid_j.ravel()
        b, m = np.nonzero(valid)
        rel = (obstacles_xy_m[b, m] - origins_m[b]) / h  # (P, 2) in cells
        base_i = np.floor(rel[:, 0]).astype(np.intp)
        base_j = np.floor(rel[:, 1]).astype(np.intp)
        ci = base_i[:, None] + di[None, :]
        cj = base_j[:, None] + dj[None, :]
        ddx = (ci + 0.5 - rel[:, 0:1]) * h
        ddy = (cj + 0.5 - rel[:, 1:2]) * h
        hit = (ddx * ddx + ddy * ddy < radius_m * radius_m) & (ci >= 0) & (ci < self.n) & (cj >= 0) & (cj < self.n)
        rows = np.broadcast_to(b[:, None], ci.shape)[hit]
        out[rows, ci[hit] * self.n + cj[hit]] = True
        return out

    # --- the potential --------------------------------------------------------------------------------------

    def distances(self, origins_m: FloatArray, blocked: BoolArray, goals_xy_m: FloatArray) -> FloatArray:
        """(B, n^2) geodesic distance from each cell centre to the goal [m]; inf for blocked/unreachable cells."""
        out = np.empty((origins_m.shape[0], self.size))
        for lo in range(0, origins_m.shape[0], _BATCH):
            hi = min(lo + _BATCH, origins_m.shape[0])
            out[lo:hi] = self._distances(origins_m[lo:hi], blocked[lo:hi], goals_xy_m[lo:hi])
        return out

    def _seeds(self, origins_m: FloatArray, blocked: BoolArray, goals_xy_m: FloatArray) -> FloatArray:
        """Initial values: the goal's cell and its neighbours (freed), or the boundary when the goal is outside."""
        n, h = self.n, self.cell_m
        n_batch = origins_m.shape[0]
        centres = (np.arange(n) + 0.5) * h
        cx = origins_m[:, 0, None, None] + centres[None, :, None]
        cy = origins_m[:, 1, None, None] + centres[None, None, :]
        euclid = np.hypot(cx - goals_xy_m[:, 0, None, None], cy - goals_xy_m[:, 1, None, None]).reshape(n_batch, -1)
        gi, gj = self.cell_of(origins_m, goals_xy_m[:, None, :])
        gi, gj = gi[:, 0], gj[:, 0]
        inside = (gi >= 0) & (gi < n) & (gj >= 0) & (gj < n)
        # The goal's cell and its 8 neighbours (those in the grid), for goals inside the grid.
        cells = np.arange(n)
        near_i = (np.abs(cells[None, :] - gi[:, None]) <= 1) & inside[:, None]
        near_j = np.abs(cells[None, :] - gj[:, None]) <= 1
        near = near_i[:, :, None] & near_j[:, None, :]
        rows = np.flatnonzero(inside)
        blocked[rows, gi[rows] * n + gj[rows]] = False  # the goal itself is always reachable in the grid
        seeds = np.where(near.reshape(n_batch, -1) & ~blocked, euclid, np.inf)
        detour = np.where(inside, self.n * h, 0.0)[:, None]
        on_edge = self._edge & ~blocked
        return np.minimum(seeds, np.where(on_edge, euclid + detour, np.inf))

    def _views(self, buf: npt.NDArray[_Scalar]) -> list[tuple[npt.NDArray[_Scalar], int, float]]:
        """(view, line axis, step cost) of the four line families on a (B, 3 n^2) buffer (class Notes)."""
        n = self.n
        width = 3 * n
        grid = buf.reshape(buf.shape[0], n, width)[:, :, n : 2 * n]
        item = buf.itemsize
        s0 = buf.strides[0]
        anti = as_strided(buf[:, n:], shape=(buf.shape[0], n, 2 * n - 1), strides=(s0, (width - 1) * item, item))
        diag = as_strided(buf, shape=(buf.shape[0], n, 2 * n - 1), strides=(s0, (width + 1) * item, item))
        h = self.cell_m
        return [(grid, 2, h), (grid, 1, h), (anti, 1, h * math.sqrt(2.0)), (diag, 1, h * math.sqrt(2.0))]

    def _distances(self, origins_m: FloatArray, blocked: BoolArray, goals_xy_m: FloatArray) -> FloatArray:
        n = self.n
        n_batch = origins_m.shape[0]
        blocked = blocked.copy()
        seeds = self._seeds(origins_m, blocked, goals_xy_m)
        finite = seeds[np.isfinite(seeds)]
        if finite.size == 0:
            return seeds
        d = np.full((n_batch, 3 * n * n), np.inf)
        blk = np.ones((n_batch, 3 * n * n), dtype=bool)
        d_views, b_views = self._views(d), self._views(blk)
        d_grid = d_views[0][0]
        d_grid[...] = seeds.reshape(n_batch, n, n)
        b_views[0][0][...] = blocked.reshape(n_batch, n, n)
        # Larger than any distance a line can carry: offsets of different segments never mix, and a cell
        # reached only across a blocked cell gets a value >= big / 2, which stands for "not reached".
        big = 4.0 * (float(finite.max()) + math.sqrt(2.0) * self.cell_m * (self.size + 3 * n))
        half = big / 2.0
        prepared = []
        for (view, axis, cost), (bview, _, _) in zip(d_views, b_views, strict=True):
            shape = [1, 1, 1]
            shape[axis] = view.shape[axis]
            pos = (np.arange(view.shape[axis], dtype=np.float64) * cost).reshape(shape)
            fwd = pos + np.cumsum(bview, axis=axis, dtype=np.float64) * big  # counts: exact in float64
            bwd = pos + np.cumsum(np.flip(bview, axis), axis=axis, dtype=np.float64) * big
            # Work buffers allocated once: fresh megabyte temporaries on every sweep cost page faults.
            prepared.append((view, np.flip(view, axis), axis, fwd, bwd, np.empty(view.shape)))
        before = np.empty(d_grid.shape)
        work = np.empty(d_grid.shape, dtype=bool)
        for _ in range(_MAX_ROUNDS):
            np.minimum(d_grid, half, out=before)
            for view, rview, axis, fwd, bwd, cand in prepared:
                np.subtract(view, fwd, out=cand)
                np.minimum.accumulate(cand, axis=axis, out=cand)
                cand += fwd
                np.minimum(view, cand, out=view)
                np.subtract(rview, bwd, out=cand)
                np.minimum.accumulate(cand, axis=axis, out=cand)
                cand += bwd
                np.minimum(rview, cand, out=rview)
            # Blocked cells are not reset to inf: the value a sweep gives one is >= big (it lies across a segment
            # boundary), so it never wins against a reached cell and reads as "not reached", like inf.
            before -= _CONVERGED_M
            if not np.less(d_grid, before, out=work).any():
                break
        out = d_grid.reshape(n_batch, -1).copy()
        out[out >= half] = np.inf
        return out

    # --- lookup ---------------------------------------------------------------------------------------------

    def sample(self, origin_m: FloatArray, dist_m: FloatArray, points_xy_m: FloatArray) -> FloatArray:
        """Bilinear value of one field at points (P, 2), over the finite corners only; inf outside or enclosed."""
        return np.asarray(self.sample_many(origin_m[None], dist_m[None], points_xy_m[None])[0], dtype=np.float64)

    def sample_many(self, origins_m: FloatArray, dists_m: FloatArray, points_xy_m: FloatArray) -> FloatArray:
        """``sample`` for R fields at once: origins (R, 2), fields (R, n^2), points (R, P, 2) -> (R, P).

        Element for element the same arithmetic as one field at a time, so the values do not depend on R.
        """
        n, h = self.n, self.cell_m
        rel = (points_xy_m - origins_m[:, None, :]) / h - 0.5
        i0 = np.floor(rel[..., 0]).astype(np.intp)
        j0 = np.floor(rel[..., 1]).astype(np.intp)
        fi = rel[..., 0] - i0
        fj = rel[..., 1] - j0
        num = np.zeros(points_xy_m.shape[:2])
        den = np.zeros(points_xy_m.shape[:2])
        rows = np.arange(origins_m.shape[0])[:, None]
        for oi, wi in ((0, 1.0 - fi), (1, fi)):
            for oj, wj in ((0, 1.0 - fj), (1, fj)):
                ii = np.clip(i0 + oi, 0, n - 1)
                jj = np.clip(j0 + oj, 0, n - 1)
                val = dists_m[rows, ii * n + jj]
                w = wi * wj
                ok = np.isfinite(val) & (w > 0.0)
                num += np.where(ok, w * np.where(ok, val, 0.0), 0.0)
                den += np.where(ok, w, 0.0)
        inside = (rel[..., 0] >= -0.5) & (rel[..., 0] <= n - 0.5) & (rel[..., 1] >= -0.5) & (rel[..., 1] <= n - 0.5)
        with np.errstate(invalid="ignore", divide="ignore"):
            out = np.where(inside & (den > 0.0), num / den, np.inf)
        return np.asarray(out, dtype=np.float64)
