"""bapf-nav's move geometry on rows of agents: which moves to the bacteria points keep the clearance (the swept
test), the clearance terms of the score, and the DIRECT look-ahead penalties (``BapfNavPlanner._decide``).

One agent's DIRECT and ESCAPE steps compute the same values with fewer calls (``navone.DirectStep``); the tests
compare both bit for bit.
"""

from __future__ import annotations

import math

import numpy as np
import numpy.typing as npt

from apf_companion.planning.clearance import MoveSweep, clearance_terms, lookahead_probes, near_obstacles
from apf_companion.planning.params import PlannerParams

__all__ = ["MoveGeometry", "obstacle_reach_m"]

FloatArray = npt.NDArray[np.float64]
BoolArray = npt.NDArray[np.bool_]

#: Agents per group (see ``MoveGeometry.__call__``). Session 29, bapf-nav's study rows at 1000 trials under cProfile:
#: 16 -> 3.10 s in the groups, 24 -> 2.86, 32 -> 2.80-2.82, 48 -> 2.82, 64 -> 2.78; 32 keeps the temporaries smaller.
_GROUP = 32
_any = np.logical_or.reduce
_all = np.logical_and.reduce
_sum = np.add.reduce

Geometry = tuple[BoolArray, FloatArray, FloatArray, FloatArray, FloatArray]


def obstacle_reach_m(params: PlannerParams) -> float:
    """How far from the agent an obstacle can matter this step [m]: one move plus the farther of the sweep with
    its look-ahead probe (C + ``nav_lookahead_m``) and the clearance term's reach (exp(-7) < 1e-3 beyond)."""
    soft_m = math.sqrt(7.0 / params.nav_clearance_decay_per_m2)
    return params.step_m + max(params.clearance_m + params.nav_lookahead_m, soft_m)


class MoveGeometry:
    """The geometry of the moves of rows of agents to their bacteria points.

    Parameters
    ----------
    params : the planner's parameters; offsets_m : (K, D) bacteria offsets [m].
    """

    def __init__(self, params: PlannerParams, offsets_m: FloatArray) -> None:
        self.params = params
        self._c2 = params.clearance_m**2
        self._sweep_moves = MoveSweep(offsets_m)
        self._reach_m = obstacle_reach_m(params)

    def __call__(
        self,
        positions_m: FloatArray,
        obstacles_m: FloatArray,
        obstacle_mask: BoolArray | None,
        to_goal: FloatArray,
        g_k: FloatArray,
        direct: BoolArray,
    ) -> Geometry:
        """Feasible moves (A, K), their swept squared clearance (A, K), clearance terms (A, K) and (A,), look-ahead
        penalties (A, K; DIRECT agents).

        Agents go in groups of ``_GROUP``, each with the obstacles near its own agents: the (M, A, K) work arrays
        stay small (megabyte temporaries cost page faults on every call, several times the arithmetic), and a
        group pays only for its own crowd. An agent's result does not depend on its group.
        """
        n_agents = g_k.shape[0]
        if n_agents <= _GROUP:  # one group (always for the service's single agent): its arrays as they are
            return self._group(positions_m, obstacles_m, obstacle_mask, to_goal, g_k, direct)
        parts = []
        for lo in range(0, n_agents, _GROUP):
            g = slice(lo, min(lo + _GROUP, n_agents))
            mask = None if obstacle_mask is None else obstacle_mask[g]
            parts.append(self._group(positions_m[g], obstacles_m[g], mask, to_goal[g], g_k[g], direct[g]))
        feasible, seg2, clear_k, clear_0, look_k = (np.concatenate(arrays) for arrays in zip(*parts, strict=True))
        return feasible, seg2, clear_k, clear_0, look_k

    def _group(
        self,
        positions_m: FloatArray,
        obstacles_m: FloatArray,
        obstacle_mask: BoolArray | None,
        to_goal: FloatArray,
        g_k: FloatArray,
        direct: BoolArray,
    ) -> Geometry:
        """The geometry of one group of agents."""
        p = self.params
        rel, valid = near_obstacles(positions_m, obstacles_m, obstacle_mask, self._reach_m)
        if rel.shape[1] == 0:
            seg2 = np.full(g_k.shape, np.inf)
            zeros = np.zeros(g_k.shape)
            return np.ones(g_k.shape, dtype=bool), seg2, zeros, np.zeros(g_k.shape[0]), zeros
        lookahead = p.nav_lookahead_m > 0.0 and p.nav_lookahead_penalty_m > 0.0 and _any(direct, axis=None)
        probes = lookahead_probes(to_goal, g_k, p.nav_lookahead_m) if lookahead else None
        r2 = _padded_sq_norm(rel, valid)
        seg2, end2, look2 = self._sweep_moves(rel, valid, r2, probes)
        feasible, clear_k, clear_0 = self._sweep(r2, seg2, end2)
        if look2 is None:
            return feasible, seg2, clear_k, clear_0, np.zeros(g_k.shape)
        # The probe comes closer than the clearance: DIRECT agents pay the penalty.
        look_k = np.where((look2 < self._c2) & direct[:, None], p.nav_lookahead_penalty_m, 0.0)
        return feasible, seg2, clear_k, clear_0, look_k

    def _sweep(self, r2: FloatArray, seg2: FloatArray, end2: FloatArray) -> tuple[BoolArray, FloatArray, FloatArray]:
        """Feasible moves (A, K): the whole segment keeps the clearance (or, from inside it, gets no closer and
        ends out); the Eq. (2)-form clearance term at the points (A, K) and at the agent (A,), in metres of path.
        ``r2`` (A, M) and ``end2`` (M, A, K): squared distances of the obstacles to the agent and the points, +inf
        in the rows of padding obstacles (``_padded_sq_norm``; MoveSweep's end2 is r2 + ..., so inf there too):
        their clearance terms are gain exp(-inf) = 0 and they are never the nearest."""
        p = self.params
        n_agents = r2.shape[0]
        if p.nav_clearance_gain_m == 0.0:
            clear_k, clear_0 = np.zeros(seg2.shape), np.zeros(n_agents)
        else:
            terms = clearance_terms(end2, p.nav_clearance_decay_per_m2, p.nav_clearance_gain_m)
            at_agent = clearance_terms(r2, p.nav_clearance_decay_per_m2, p.nav_clearance_gain_m)
            clear_k, clear_0 = np.add.reduce(terms, axis=0), _sum(at_agent, axis=1)
        d0 = r2.min(axis=1, initial=np.inf)
        ok = seg2 >= self._c2
        inside = d0 < self._c2
        if _any(inside, axis=None):
            out = (seg2 >= d0[:, None]) & (np.minimum.reduce(end2, axis=0) > d0[:, None])
            ok = np.where(inside[:, None], out, ok)
        return np.asarray(ok), clear_k, clear_0


def _padded_sq_norm(rel: FloatArray, valid: BoolArray) -> FloatArray:
    """(A, M) |rel|^2 of the near obstacles, +inf in padding rows. 2D: the two products written out (einsum's sum
    bit for bit, one rounding either order, and several times faster on the short coordinate axis); 3D: einsum."""
    if rel.shape[2] == 2:
        r2 = rel[:, :, 0] * rel[:, :, 0]
        r2 += rel[:, :, 1] * rel[:, :, 1]
    else:
        r2 = np.einsum("amd,amd->am", rel, rel)
    if rel.shape[0] > 1 and not _all(valid, axis=None):  # one agent: near_obstacles returns only real rows
        np.copyto(r2, np.inf, where=~valid)
    return np.asarray(r2, dtype=np.float64)
