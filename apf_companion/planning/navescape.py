"""bapf-nav's escape maps: per agent, the navigation potential of the remembered obstacles (``navfield``).

Owns the grid geometry and the rules of when a potential is (re)computed: on entering ESCAPE, every
``nav_replan_steps`` escape steps, when the descent stalls (new obstacles), and after marking refused downhill
cells as virtual obstacles (the grid let the potential through a gap that the swept test refuses). Blocked cells
are remembered across recomputations and carried over when the grid moves.
"""

from __future__ import annotations

import numpy as np
import numpy.typing as npt

from apf_companion.planning.navfield import NavGrid
from apf_companion.planning.navstate import NavField, NavState
from apf_companion.planning.params import PlannerParams

__all__ = ["EscapeMaps"]

FloatArray = npt.NDArray[np.float64]
BoolArray = npt.NDArray[np.bool_]
IntArray = npt.NDArray[np.intp]


class EscapeMaps:
    """The escape potentials of a planner's agents (their ``NavField`` lives in ``NavState.field``)."""

    def __init__(self, params: PlannerParams, offsets_m: FloatArray, clearance_m: float) -> None:
        self.params = params
        self.grid = NavGrid(params.nav_cell_m, params.nav_grid_m)
        self.clearance_m = clearance_m
        self._offsets = offsets_m
        self._pad_m = 2.0 * params.step_m + clearance_m + 1.0

    def potentials(
        self,
        rows: IntArray,
        positions_m: FloatArray,
        targets_m: FloatArray,
        obstacles_m: FloatArray,
        obstacle_mask: BoolArray | None,
        state: NavState,
        feasible: BoolArray,
        clear_k: FloatArray,
        clear_0: FloatArray,
    ) -> tuple[FloatArray, FloatArray, BoolArray]:
        """Geodesic potential at the points (R, K) and the agents (R,) of ``rows``, and which points pass
        (feasible and lower on potential + clearance term), recomputing stale potentials."""
        stale = np.array([state.field[r] is None for r in rows], dtype=bool)
        stale |= state.since_field[rows] >= self.params.nav_replan_steps
        if stale.any():
            self.refresh(rows[stale], positions_m, targets_m, obstacles_m, obstacle_mask, state)
        g_k, g0 = self.geodesic(rows, positions_m, targets_m, state)
        ok: BoolArray = np.asarray(feasible[rows] & (g_k + clear_k[rows] < (g0 + clear_0[rows])[:, None]))
        # Stalled on a potential that may be stale: recompute once with what is known now.
        stalled = ~ok.any(axis=1) & ~stale
        if stalled.any():
            again = rows[stalled]
            self.refresh(again, positions_m, targets_m, obstacles_m, obstacle_mask, state)
            g_k[stalled], g0[stalled] = self.geodesic(again, positions_m, targets_m, state)
            ok[stalled] = feasible[again] & (g_k[stalled] + clear_k[again] < (g0[stalled] + clear_0[again])[:, None])
        # Still nothing: the grid lets the potential through a gap the sweep refuses (a diagonal between two
        # free cells can cut an inflated obstacle). Mark the cells of the refused points that lead downhill as
        # blocked (virtual obstacles, kept with the remembered cells) and recompute once.
        dead = ~ok.any(axis=1)
        if dead.any():
            self.mark_dead_ends(rows[dead], positions_m, feasible[rows[dead]], g_k[dead], g0[dead], state)
            again = rows[dead]
            self.refresh(again, positions_m, targets_m, obstacles_m, obstacle_mask, state)
            g_k[dead], g0[dead] = self.geodesic(again, positions_m, targets_m, state)
            ok[dead] = feasible[again] & (g_k[dead] + clear_k[again] < (g0[dead] + clear_0[again])[:, None])
        return g_k, g0, ok

    def mark_dead_ends(
        self,
        rows: IntArray,
        positions_m: FloatArray,
        feasible: BoolArray,
        g_k: FloatArray,
        g0: FloatArray,
        state: NavState,
    ) -> None:
        """Block the cells of refused points that the potential says lead downhill (not the agent's own cell)."""
        grid = self.grid
        n = grid.n
        for i, r in enumerate(rows):
            f = state.field[r]
            refused = ~feasible[i] & (g_k[i] < g0[i])
            if f is None or not refused.any():
                continue
            pts = positions_m[r, :2] + self._offsets[refused, :2]
            ci, cj = grid.cell_of(f.origin_m[None], pts[None])
            own_i, own_j = grid.cell_of(f.origin_m[None], positions_m[r, :2][None, None])
            ok = (ci >= 0) & (ci < n) & (cj >= 0) & (cj < n) & ~((ci == own_i[0, 0]) & (cj == own_j[0, 0]))
            f.blocked[ci[ok] * n + cj[ok]] = True

    def refresh(
        self,
        rows: IntArray,
        positions_m: FloatArray,
        targets_m: FloatArray,
        obstacles_m: FloatArray,
        obstacle_mask: BoolArray | None,
        state: NavState,
    ) -> None:
        """Recompute the potential of ``rows`` from the obstacles known now plus the cells remembered before."""
        grid = self.grid
        xy = positions_m[rows, :2]
        goals = targets_m[rows, :2]
        origins = grid.origins(xy, goals, self._pad_m)
        old_blocked = np.zeros((rows.size, grid.size), dtype=bool)
        side = grid.n * grid.cell_m
        for i, r in enumerate(rows):
            old = state.field[r]
            if old is None:
                continue
            rel = xy[i] - old.origin_m
            if np.all(rel >= self._pad_m) and np.all(rel <= side - self._pad_m):
                origins[i] = old.origin_m  # the agent is well inside: keep the frame
                old_blocked[i] = old.blocked
            else:  # a new frame: carry the remembered cells over where the grids overlap
                old_blocked[i] = grid.shift_blocked(old.blocked, old.origin_m, origins[i])
        obs = obstacles_m[rows]
        valid: BoolArray = np.asarray(np.isfinite(obs).all(axis=2))
        if obstacle_mask is not None:
            valid &= obstacle_mask[rows]
        if self.params.dim == 3:
            valid &= np.abs(obs[:, :, 2] - positions_m[rows, 2][:, None]) <= self.clearance_m
        blocked = grid.blocked(origins, np.where(valid[..., None], obs[:, :, :2], 0.0), valid, self.clearance_m)
        blocked |= old_blocked
        dist = grid.distances(origins, blocked, goals)
        for i, r in enumerate(rows):
            state.field[r] = NavField(origin_m=origins[i].copy(), blocked=blocked[i], dist_m=dist[i])
        state.since_field[rows] = 0

    def geodesic(
        self, rows: IntArray, positions_m: FloatArray, targets_m: FloatArray, state: NavState
    ) -> tuple[FloatArray, FloatArray]:
        """Potential at the points (R, K) and at the agents (R,) of ``rows`` (inf where unreachable)."""
        offsets = self._offsets
        pts = positions_m[rows][:, None, :] + np.vstack([offsets, np.zeros((1, offsets.shape[1]))])[None]
        fields = [state.field[r] for r in rows]
        origins = np.stack([f.origin_m for f in fields])
        dists = np.stack([f.dist_m for f in fields])
        values = self.grid.sample_many(origins, dists, pts[:, :, :2])
        if self.params.dim == 3:
            dz = pts[:, :, 2] - targets_m[rows, 2][:, None]
            values = np.sqrt(values * values + dz * dz)
        return values[:, :-1], values[:, -1]
