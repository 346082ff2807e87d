"""The bacteria-point step shared by BAPF, CR-BAPF, CR-BAPF* and A-BAPF (Diab et al. 2023, Figs. 2-3).

Each agent tests its N_b bacteria points in order of increasing distance to the target (ties: lowest index
first) and moves to the FIRST that passes Eq. (6) (not to the lowest potential); none passes is a local
minimum. All agents are processed at once by broadcasting over (A, K, N); there is no per-agent or per-obstacle
Python loop, only a loop over memory-bounded chunks of agents.

Notes
-----
Exactness and speed. The decision is taken in the log domain (``potentials.moves_downhill``), shifted per
agent by a = log |J_t(r)| so the target term of the left side is exactly 0 (LHS >= 1 in linear terms) and the
target term of the right side is mu_t * Delta_k with Delta_k = rho_t(r) - rho_t(r_b,k) computed as
(r - r_b,k) . (r + r_b,k - 2 r_t), free of cancellation at any distance. An obstacle whose every term (at the
agent and at all points within one step) is below e^-60 relative to LHS is skipped: together such terms change
either side by less than N e^-60, i.e. they can flip a decision only when the two sides agree to 1e-20
relative, far below float64 resolution. For CR-BAPF obstacles beyond rho_u + step contribute exactly 0. Both
filters are per agent, so far-away obstacles cost one distance each and nothing per bacteria point.
"""

from __future__ import annotations

import math
from typing import ClassVar

import numpy as np
import numpy.typing as npt

from apf_companion.errors import ConfigError
from apf_companion.planning.base import Planner
from apf_companion.planning.decision import BatchDecision, DecisionReason
from apf_companion.planning.params import AbapfRule, AbapfSearch, PlannerParams, RandomWalkRule
from apf_companion.planning.potentials import (
    dist_sq_threshold_above,
    dist_sq_threshold_below,
    log_sum_exp,
)

__all__ = ["BacteriaPlanner"]

FloatArray = npt.NDArray[np.float64]
BoolArray = npt.NDArray[np.bool_]
IntArray = npt.NDArray[np.int64]

#: Terms below e^_NEGLIGIBLE_LOG relative to LHS >= 1 cannot change a decision (see module Notes).
_NEGLIGIBLE_LOG = -60.0
#: Chunk size target in elements of one (A, K, N) temporary.
_CHUNK_ELEMENTS = 1 << 20
#: Paper rule of A-BAPF: repulsion <= 2^-53 |J_t| (float64 rounds J_t + J_o to J_t).
_LOG_HALF_ULP = -53.0 * math.log(2.0)
_INV_PHI = (math.sqrt(5.0) - 1.0) / 2.0


class BacteriaPlanner(Planner):
    """Shared engine; subclasses choose the repulsion (Eq. (2) or (12)), adaptivity and random walk."""

    #: CR-BAPF: branching repulsion of Eq. (12) instead of Eq. (2).
    branching: ClassVar[bool] = False
    #: CR-BAPF*: random walk when no point passes.
    random_walk: ClassVar[bool] = False
    #: A-BAPF: mu_o,k chosen per point by Eq. (14).
    adaptive: ClassVar[bool] = False

    def __init__(self, params: PlannerParams) -> None:
        super().__init__(params)
        self._log_alpha_o = math.log(params.alpha_o)
        self._log_alpha_t = math.log(params.alpha_t)
        self._inside_d2 = dist_sq_threshold_below(params.rho_l_m)
        self._outside_d2 = dist_sq_threshold_above(params.rho_u_m)
        # A-BAPF with the exact rule and the grid needs no search (mu_max, see abapf.py): prune as BAPF.
        self._full_obstacles = self.adaptive and (
            params.abapf_rule is AbapfRule.PAPER or params.abapf_search is AbapfSearch.GOLDEN
        )

    # --- hooks --------------------------------------------------------------------------------------

    def _point_mu(
        self,
        dist_sq_points_m2: FloatArray,
        log_target_points: FloatArray,
        has_obstacles: BoolArray,
    ) -> FloatArray | float:
        """mu_o used at the bacteria points: (A', K) or a scalar. Overridden by A-BAPF."""
        return self.params.mu_o_per_m2

    def _smallest_point_mu(self) -> float:
        """Lower bound of the mu_o used at the points (for the negligibility filter)."""
        return self.params.mu_o_per_m2

    # --- engine -------------------------------------------------------------------------------------

    def _relevant(self, mask: BoolArray, dist_sq_agent_m2: FloatArray, log_target_agent: FloatArray) -> BoolArray:
        """(A, N) obstacles whose terms can matter for this step (module Notes)."""
        if self._full_obstacles:
            return mask
        p = self.params
        dist_m = np.sqrt(dist_sq_agent_m2)
        # Lower bound of the distance from any bacteria point (or the agent) to the obstacle, with a margin
        # far above rounding so no obstacle that matters is filtered out.
        gap_m = np.maximum(dist_m - p.step_m - 1e-9 * (1.0 + dist_m), 0.0)
        mu = min(self._smallest_point_mu(), p.mu_o_per_m2)
        bound = self._log_alpha_o - mu * gap_m * gap_m - log_target_agent[:, None]
        keep = bound >= _NEGLIGIBLE_LOG
        if self.branching:
            keep = (keep | (gap_m <= p.rho_l_m)) & (gap_m <= p.rho_u_m)
        return mask & keep

    def _step_batch(
        self,
        positions_m: FloatArray,
        targets_m: FloatArray,
        obstacles_m: FloatArray,
        obstacle_mask: BoolArray,
        rng: np.random.Generator | None,
        walk_uniforms: FloatArray | None,
    ) -> BatchDecision:
        p = self.params
        n_agents, dim = positions_m.shape
        offsets = self.bacteria_offsets_m
        n_points = offsets.shape[0]

        points = positions_m[:, None, :] + offsets[None, :, :]  # (A, K, D)
        rel_t = positions_m - targets_m
        dist_sq_target = np.einsum("ad,ad->a", rel_t, rel_t)
        log_target_agent = self._log_alpha_t - p.mu_t_per_m2 * dist_sq_target  # a = log |J_t(r)|
        # Delta_k = rho_t(r) - rho_t(r_b,k), without cancellation; the shifted target term of the RHS.
        gain = np.einsum(
            "akd,akd->ak",
            positions_m[:, None, :] - points,
            (positions_m + positions_m - 2.0 * targets_m)[:, None, :] - (positions_m[:, None, :] - points),
        )
        shifted_target_points = p.mu_t_per_m2 * gain  # (A, K)

        rel_o = obstacles_m - positions_m[:, None, :]
        dist_sq_agent = np.einsum("and,and->an", rel_o, rel_o)  # (A, N)
        relevant = self._relevant(obstacle_mask, dist_sq_agent, log_target_agent)
        counts = relevant.sum(axis=1)

        passing: BoolArray = np.asarray(shifted_target_points > 0.0)  # no relevant obstacle: LHS = 0, RHS = mu_t Delta
        unsafe = np.zeros((n_agents, n_points), dtype=bool)
        mu_points = np.full((n_agents, n_points), np.nan)
        if self.adaptive:
            has_any = obstacle_mask.any(axis=1)
            mu_empty = np.where(has_any, float(p.mu_max), float(p.mu_min))
            mu_points[:] = mu_empty[:, None]

        rows = np.flatnonzero(counts)
        if rows.size:
            n_slots = int(counts[rows].max())
            sub = relevant[rows]
            r_i, c_i = np.nonzero(sub)
            slot = (np.cumsum(sub, axis=1) - 1)[r_i, c_i]
            # Padding obstacles sit at infinity: their terms are exactly -inf and never inside rho_l.
            packed = np.full((rows.size, n_slots, dim), np.inf)
            packed[r_i, slot] = obstacles_m[rows[r_i], c_i]
            packed_d2_agent = np.full((rows.size, n_slots), np.inf)
            packed_d2_agent[r_i, slot] = dist_sq_agent[rows[r_i], c_i]
            has_obstacles: BoolArray = np.asarray(obstacle_mask[rows].any(axis=1))
            chunk = max(1, _CHUNK_ELEMENTS // (n_points * n_slots))
            for start in range(0, rows.size, chunk):
                stop = min(start + chunk, rows.size)
                idx = rows[start:stop]
                ok, bad, mu = self._decide(
                    points[idx],
                    packed[start:stop],
                    packed_d2_agent[start:stop],
                    log_target_agent[idx],
                    shifted_target_points[idx],
                    has_obstacles[start:stop],
                )
                passing[idx] = ok
                unsafe[idx] = bad
                if self.adaptive:
                    mu_points[idx] = mu

        return self._select(points, passing, unsafe, gain, mu_points, rng, walk_uniforms)

    def _decide(
        self,
        points_m: FloatArray,
        obstacles_m: FloatArray,
        dist_sq_agent_m2: FloatArray,
        log_target_agent: FloatArray,
        shifted_target_points: FloatArray,
        has_obstacles: BoolArray,
    ) -> tuple[BoolArray, BoolArray, FloatArray | float]:
        """Eq. (6) for a chunk of agents with packed obstacles: (passing, inside rho_l, mu at points)."""
        p = self.params
        diff = points_m[:, :, None, 0] - obstacles_m[:, None, :, 0]
        dist_sq = diff * diff
        for axis in range(1, points_m.shape[-1]):
            diff = points_m[:, :, None, axis] - obstacles_m[:, None, :, axis]
            dist_sq += diff * diff  # (A', K, N')

        shift = log_target_agent[:, None, None]
        if self.adaptive:
            log_target_points = log_target_agent[:, None] + shifted_target_points
            mu: FloatArray | float = self._point_mu(dist_sq, log_target_points, has_obstacles)
        else:
            mu = p.mu_o_per_m2
        mu_b = mu[:, :, None] if isinstance(mu, np.ndarray) else mu
        terms = (self._log_alpha_o - shift) - mu_b * dist_sq
        if self.branching:
            terms[dist_sq > self._outside_d2] = -np.inf
            inside = np.any(dist_sq < self._inside_d2, axis=-1)
        else:
            inside = np.zeros(points_m.shape[:2], dtype=bool)
        # LHS: log(1 + sum exp(terms)); 1 is the shifted |J_t(r)|, so the peak is finite and >= 0.
        peak = np.maximum(np.max(terms, axis=-1), 0.0)
        lhs = peak + np.log(np.exp(-peak) + np.sum(np.exp(terms - peak[:, :, None]), axis=-1))
        lhs[inside] = np.inf

        if p.agent_repulsion:
            agent_terms = (self._log_alpha_o - log_target_agent[:, None]) - p.mu_o_per_m2 * dist_sq_agent_m2
            if self.branching:
                agent_terms[dist_sq_agent_m2 > self._outside_d2] = -np.inf
                agent_inside = np.any(dist_sq_agent_m2 < self._inside_d2, axis=-1)
            else:
                agent_inside = np.zeros(dist_sq_agent_m2.shape[0], dtype=bool)
            rhs_obstacles = log_sum_exp(agent_terms, axis=-1)
            rhs_obstacles[agent_inside] = np.inf
            rhs = np.logaddexp(rhs_obstacles[:, None], shifted_target_points)
        else:
            rhs = shifted_target_points
        return lhs < rhs, inside, mu

    def _select(
        self,
        points: FloatArray,
        passing: BoolArray,
        unsafe: BoolArray,
        gain: FloatArray,
        mu_points: FloatArray,
        rng: np.random.Generator | None,
        walk_uniforms: FloatArray | None,
    ) -> BatchDecision:
        """First passing point in order of increasing target distance; else random walk or local minimum."""
        n_agents, n_points, _ = points.shape
        # Larger gain = closer to the target; argmax takes the lowest index among ties.
        key = np.where(passing, gain, -np.inf)
        chosen = np.argmax(key, axis=1)
        n_passing = passing.sum(axis=1)
        greedy = n_passing > 0
        chosen = np.where(greedy, chosen, -1)
        reason = np.where(greedy, DecisionReason.GREEDY, DecisionReason.LOCAL_MINIMUM).astype(np.int8)
        safe = ~unsafe
        n_safe = safe.sum(axis=1) if self.branching else np.full(n_agents, -1, dtype=np.int64)

        if self.random_walk:
            stuck = np.flatnonzero(~greedy)
            if stuck.size:
                if walk_uniforms is not None:
                    u = walk_uniforms[stuck]
                elif rng is not None:
                    u = rng.random(stuck.size)
                else:
                    raise ConfigError("rng is required: CR-BAPF* needs a random walk for this step")
                if self.params.random_walk is RandomWalkRule.SINGLE_DRAW:
                    q = np.minimum((u * n_points).astype(np.int64), n_points - 1)
                    moves = safe[stuck, q]
                else:
                    counts = n_safe[stuck]
                    j = np.minimum((u * counts).astype(np.int64), np.maximum(counts - 1, 0))
                    q = np.argmax(np.cumsum(safe[stuck], axis=1) > j[:, None], axis=1)
                    moves = counts > 0
                walkers = stuck[moves]
                chosen[walkers] = q[moves]
                reason[walkers] = DecisionReason.RANDOM_WALK

        moved = chosen >= 0
        take = np.maximum(chosen, 0)
        next_points = points[np.arange(n_agents), take]
        next_points[~moved] = np.nan
        if self.adaptive:
            mu_o_k = np.where(moved, mu_points[np.arange(n_agents), take], np.nan)
        else:
            mu_o_k = np.full(n_agents, np.nan)
        return BatchDecision(
            next_points_m=next_points,
            reason=reason,
            chosen_index=chosen.astype(np.int64),
            mu_o_k=mu_o_k,
            n_passing=n_passing.astype(np.int64),
            n_safe=n_safe.astype(np.int64),
        )
