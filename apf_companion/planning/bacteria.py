"""The bacteria-point step shared by BAPF, CR-BAPF, CR-BAPF* and A-BAPF (Diab et al. 2023, Figs. 2-3).

Each agent tests its N_b bacteria points in order of increasing distance to the target (ties: lowest index
first) and moves to the FIRST that passes Eq. (6) (not to the lowest potential); none passes is a local
minimum. All agents are processed at once by broadcasting; there is no per-agent or per-obstacle Python loop,
only a loop over groups of agents that have the same number of relevant obstacles (and memory-bounded chunks).

Notes
-----
Exactness. The decision is taken in the log domain (``potentials.moves_downhill``), shifted per agent by
a = log |J_t(r)| so the target term of the left side is exactly 0 (LHS >= 1 in linear terms) and the target term
of the right side is mu_t * Delta_k, with Delta_k = rho_t(r) - rho_t(r + o_k) = -(|o_k|^2 + 2 o_k . (r - r_t))
for the bacteria offset o_k: free of cancellation at any distance. Squared distances to obstacles are taken
from offsets and obstacle positions relative to the agent (no large coordinates are subtracted).

Speed. An obstacle whose every term (at the agent and at all points within one step) is below e^-60 relative to
LHS is skipped: together such terms change either side by less than N e^-60, so they can flip a decision only
when the two sides agree to 1e-20 relative, far below float64 resolution. For CR-BAPF obstacles beyond
rho_u + step contribute exactly 0. Both filters are per agent and cost one distance per obstacle; what remains
is usually a handful of obstacles. Arrays are laid out (obstacle, agent, point) so every ufunc runs along the
contiguous N_b axis (numpy is slow on tiny innermost axes such as D = 2).
"""

from __future__ import annotations

import itertools
import math
from typing import ClassVar

import numpy as np
import numpy.typing as npt

from apf_companion.errors import ConfigError
from apf_companion.planning.base import Planner
from apf_companion.planning.decision import BatchDecision, DecisionReason, filled
from apf_companion.planning.params import AbapfRule, AbapfSearch, PlannerParams, RandomWalkRule
from apf_companion.planning.potentials import dist_sq_threshold_above, dist_sq_threshold_below

__all__ = ["BacteriaPlanner"]

FloatArray = npt.NDArray[np.float64]
BoolArray = npt.NDArray[np.bool_]
IntArray = npt.NDArray[np.int64]
Int8Array = npt.NDArray[np.int8]

#: Terms below e^_NEGLIGIBLE_LOG relative to LHS >= 1 cannot change a decision (see module Notes).
_NEGLIGIBLE_LOG = -60.0
#: Chunk size target in elements of one (A, K, N) temporary.
_CHUNK_ELEMENTS = 1 << 20
#: Paper rule of A-BAPF: repulsion <= 2^-53 |J_t| (float64 rounds J_t + J_o to J_t).
_LOG_HALF_ULP = -53.0 * math.log(2.0)
_INV_PHI = (math.sqrt(5.0) - 1.0) / 2.0
# numpy constants as 0-d arrays: as ufunc operands they cost about half of what a Python float does, which
# matters in the single-agent step (tens of ufunc calls on tiny arrays).
_LOCAL_MINIMUM_CODE = np.array(DecisionReason.LOCAL_MINIMUM, dtype=np.int8)
_ZERO = np.array(0.0)
_ZERO_COUNT = np.array(0, dtype=np.int64)
_MINUS_INF = np.array(-np.inf)
#: Stand-in for the +inf log-term inside rho_l (Eq. (13)): larger than any finite log-sum-exp that can occur.
_INSIDE_LOG = np.array(1e300)


def _const(value: float) -> FloatArray:
    """A 0-d float64 array (see the constants above)."""
    return np.array(value, dtype=np.float64)


def _count_rows(flags: BoolArray) -> IntArray:
    """Number of True per row of an (A, K) bool array (a cheaper path for A = 1)."""
    if flags.shape[0] == 1:
        return np.array([np.count_nonzero(flags)])
    return np.asarray(np.add.reduce(flags, axis=1), dtype=np.int64)


def _relevant_counts(relevant: BoolArray) -> tuple[IntArray | None, int]:
    """(A,) relevant obstacles per agent (None for one agent) and their common count (0: not all equal).

    Always equal for A = 1 with obstacles; np.count_nonzero without an axis is several times cheaper for
    that single-agent step.
    """
    n_agents = relevant.shape[0]
    if n_agents == 1:
        return None, int(np.count_nonzero(relevant))
    counts = np.add.reduce(relevant, axis=1)
    return counts, int(counts[0]) if n_agents and counts.min() == counts.max() else 0


def _first_passing(passing: BoolArray, gain: FloatArray) -> tuple[IntArray, IntArray, BoolArray, Int8Array]:
    """Search order of Fig. 3: (A,) chosen point (the first passing one by increasing target distance; -1:
    none), number passing, stuck (none passes) and reason (GREEDY or LOCAL_MINIMUM)."""
    # Larger gain = closer to the target; argmax takes the lowest index among ties.
    chosen = np.where(passing, gain, _MINUS_INF).argmax(axis=1)
    n_passing = _count_rows(passing)
    stuck = n_passing == _ZERO_COUNT
    chosen[stuck] = -1
    # GREEDY = 0, LOCAL_MINIMUM = 2: the int8 view of the bool array times 2.
    reason = stuck.view(np.int8) * _LOCAL_MINIMUM_CODE
    return chosen, n_passing, stuck, reason


def _walk_uniforms(walkers: IntArray, rng: np.random.Generator | None, walk_uniforms: FloatArray | None) -> FloatArray:
    """One U[0, 1) per stuck agent: the given ones (lockstep study) or drawn from ``rng``."""
    if walk_uniforms is not None:
        return walk_uniforms[walkers]
    if rng is not None:
        return rng.random(walkers.size)
    raise ConfigError("rng is required: CR-BAPF* needs a random walk for this step")


def _random_walk(
    rule: RandomWalkRule,
    safe: BoolArray,
    n_safe: IntArray,
    walkers: IntArray,
    u: FloatArray,
) -> tuple[IntArray, IntArray]:
    """CR-BAPF* random walk: the walkers that move and their random points, from the uniforms ``u``.

    SAFE_SET (the paper's q ~ U{Q}): one of the walker's safe points uniformly (Q empty: it stays).
    SINGLE_DRAW (the authors' code): one of the N_b points uniformly, moving only when it is safe.
    """
    n_points = safe.shape[1]
    if rule is RandomWalkRule.SINGLE_DRAW:
        q = np.minimum((u * n_points).astype(np.int64), n_points - 1)
        moves = safe[walkers, q]
    else:
        n_safe_w = n_safe[walkers]
        j = np.minimum((u * n_safe_w).astype(np.int64), np.maximum(n_safe_w - 1, 0))
        q = np.argmax(np.cumsum(safe[walkers], axis=1) > j[:, None], axis=1)
        moves = n_safe_w > 0
    return walkers[moves], q[moves]


def _groups(rows: IntArray, counts: IntArray, n_points: int) -> list[IntArray]:
    """Rows split into groups of equal obstacle count (no padding), each cut to a bounded memory size."""
    if rows.size == 1:
        return [rows]
    rows = rows[np.argsort(counts[rows], kind="stable")]
    sorted_counts = counts[rows]
    bounds = [0, *(np.flatnonzero(np.diff(sorted_counts)) + 1).tolist(), rows.size]
    groups: list[IntArray] = []
    for lo, hi in itertools.pairwise(bounds):
        chunk = max(1, _CHUNK_ELEMENTS // ((n_points + 1) * int(sorted_counts[lo])))
        groups.extend(rows[start : min(start + chunk, hi)] for start in range(lo, hi, chunk))
    return groups


def _safe_points(branching: bool, passing: BoolArray, inside: BoolArray | None) -> tuple[BoolArray | None, IntArray]:
    """CR-BAPF: (A, K) points outside rho_l of every obstacle (None: all) and (A,) their number (-1 for
    the planners without rho_l)."""
    n_agents, n_points = passing.shape
    if not branching:
        return None, filled(n_agents, -1, np.int64)
    if inside is None:  # no obstacle near any agent: every point is safe
        return None, filled(n_agents, n_points, np.int64)
    safe = ~inside
    return safe, _count_rows(safe)


class BacteriaPlanner(Planner):
    """Shared engine; subclasses choose the repulsion (Eq. (2) or (13)), adaptivity and random walk by the class
    flags below, and A-BAPF overrides the three hooks ``_point_mu``, ``_smallest_point_mu`` and
    ``_adaptive_decision`` (their defaults are BAPF's)."""

    #: CR-BAPF: branching repulsion of Eq. (13) instead of Eq. (2).
    branching: ClassVar[bool] = False
    #: CR-BAPF*: random walk when no point passes.
    random_walk: ClassVar[bool] = False
    #: A-BAPF: mu_o,k chosen per point by Eq. (11).
    adaptive: ClassVar[bool] = False

    def __init__(self, params: PlannerParams) -> None:
        super().__init__(params)
        offsets = self.bacteria_offsets_m
        n_points = offsets.shape[0]
        self._n_points = n_points
        self._log_alpha_o = _const(math.log(params.alpha_o))
        self._log_alpha_t = _const(math.log(params.alpha_t))
        self._mu_t = _const(params.mu_t_per_m2)
        self._mu_o = _const(params.mu_o_per_m2)
        self._minus_two_offsets = [np.ascontiguousarray(-2.0 * offsets[:, axis]) for axis in range(params.dim)]
        self._offset_sq = np.sum(offsets * offsets, axis=1)
        # Offsets with a NaN row at index -1: chosen index -1 (no move) gives a NaN next point for free.
        self._offsets_or_nan = np.vstack([offsets, np.full((1, params.dim), np.nan)])
        # Column K (after the N_b points) is the agent itself: offset 0, no target term inside its sum, and
        # mu_o (Eq. (4)); one pass then yields both sides of Eq. (6).
        self._columns = [np.append(offsets[:, axis], 0.0) for axis in range(params.dim)]
        self._extra = np.append(np.zeros(n_points), -np.inf)
        # Peak floor: 0 for the points (their "1" term); for the agent column a finite floor far below any
        # term, so an empty sum gives log(0) = -inf without inf - inf.
        self._peak_floor = np.append(np.zeros(n_points), -1e300)
        self._inside_d2 = _const(dist_sq_threshold_below(params.rho_l_m))
        self._outside_d2 = _const(dist_sq_threshold_above(params.rho_u_m))
        # A-BAPF with the exact rule and the grid needs no search (mu_max, see abapf.py): prune as BAPF.
        self._full_obstacles = self.adaptive and (
            params.abapf_rule is AbapfRule.PAPER or params.abapf_search is AbapfSearch.GOLDEN
        )
        mu_min = min(self._smallest_point_mu(), params.mu_o_per_m2)
        widen = (1.0 + 1e-9) ** 2
        self._reach_gain = _const(widen / mu_min)
        self._rho_l_sq = _const(widen * params.rho_l_m**2)
        self._rho_u_sq = _const(widen * params.rho_u_m**2)
        self._reach_step = _const(params.step_m + 1e-9)
        self._reach_offset = _const(math.log(params.alpha_o) - _NEGLIGIBLE_LOG)

    def _point_mu(self, dist_sq_points_m2: FloatArray, log_target_points: FloatArray) -> FloatArray | float:
        """mu_o at the bacteria points, (A', K) or a scalar, from (N', A', K) squared distances and the
        (A', K) log |J_t(r_b,k)|. Overridden by A-BAPF."""
        return self.params.mu_o_per_m2

    def _smallest_point_mu(self) -> float:
        """Lower bound of the mu_o used at the points (for the negligibility filter)."""
        return self.params.mu_o_per_m2

    def _adaptive_decision(
        self, dist_sq_m2: FloatArray, log_target_agent: FloatArray, gain: FloatArray
    ) -> tuple[BoolArray, BoolArray | None, FloatArray] | None:
        """A-BAPF may decide a group itself from the (N', A', K + 1) squared distances; None: the generic path."""
        return None

    def _reach_sq(self, log_target_agent: FloatArray) -> FloatArray:
        """(A,) squared radius around each agent beyond which obstacles cannot matter (module Notes).

        An obstacle at distance d is at least gap = d - step from every bacteria point; its terms are all below
        e^-60 once log alpha_o - mu gap^2 - a < -60, i.e. gap > sqrt((log alpha_o - a + 60) / mu). CR-BAPF
        also keeps obstacles within rho_l + step (they can make a point infinite) and drops those beyond
        rho_u + step (exactly zero). Keeping more obstacles than needed is always correct.
        """
        # The gap is taken 1e-9 relative larger (folded into the constants), a margin far above rounding:
        # never drop an obstacle that matters.
        gap_sq = (self._reach_offset - log_target_agent) * self._reach_gain
        if self.branching:
            reach_m = np.sqrt(np.minimum(np.maximum(gap_sq, self._rho_l_sq), self._rho_u_sq))
        else:
            reach_m = np.sqrt(np.maximum(gap_sq, _ZERO))
        reach_m += self._reach_step
        reach_m *= reach_m
        return reach_m

    def _target_terms(self, positions_m: FloatArray, targets_m: FloatArray) -> tuple[FloatArray, FloatArray]:
        """(A,) a = log |J_t(r)| (Eq. (1)) and (A, K) Delta_k = rho_t(r) - rho_t(r + o_k) (module Notes).

        Delta_k = -(|o_k|^2 + 2 o_k . (r - r_t)) > 0 when point k is closer to the target than the agent.
        """
        rel_t = positions_m - targets_m  # (A, D)
        log_target_agent = self._log_alpha_t - self._mu_t * np.add.reduce(rel_t * rel_t, axis=1)  # a
        gain = rel_t[:, 0, None] * self._minus_two_offsets[0]
        for axis in range(1, positions_m.shape[1]):
            gain += rel_t[:, axis, None] * self._minus_two_offsets[axis]
        gain -= self._offset_sq
        return log_target_agent, gain

    def _relevant_obstacles(
        self,
        positions_m: FloatArray,
        obstacles_m: FloatArray,
        obstacle_mask: BoolArray | None,
        log_target_agent: FloatArray,
    ) -> tuple[FloatArray, BoolArray]:
        """(D, A, N) obstacles relative to their agent and the (A, N) obstacles that can change Eq. (6).

        An obstacle is dropped when it lies beyond ``_reach_sq`` (module Notes) or is masked out; A-BAPF with
        the full obstacle set keeps every known one.
        """
        # One (A, N) slab per axis (contiguous when it pays off).
        by_axis = obstacles_m.transpose(2, 0, 1)
        if positions_m.shape[0] > 8:
            by_axis = np.ascontiguousarray(by_axis)
        rel_o = by_axis - positions_m.T[:, :, None]
        dist_sq_agent = np.add.reduce(rel_o * rel_o, axis=0)
        if self._full_obstacles:
            relevant = np.ones(dist_sq_agent.shape, dtype=bool) if obstacle_mask is None else obstacle_mask
        else:
            relevant = dist_sq_agent <= self._reach_sq(log_target_agent)[:, None]
            if obstacle_mask is not None:
                relevant &= obstacle_mask
        return rel_o, relevant

    def _initial_point_mu(
        self, n_agents: int, obstacles_m: FloatArray, obstacle_mask: BoolArray | None
    ) -> FloatArray | None:
        """A-BAPF: (A, K) mu_o,k before Eq. (11) is evaluated, mu_max with known obstacles else mu_min; None
        for the other planners."""
        if not self.adaptive:
            return None
        p = self.params
        known = obstacle_mask.any(axis=1) if obstacle_mask is not None else np.full(n_agents, obstacles_m.size > 0)
        return np.repeat(np.where(known, float(p.mu_max), float(p.mu_min))[:, None], self._n_points, 1)

    def _decide_by_groups(
        self,
        rel_o: FloatArray,
        relevant: BoolArray,
        counts: IntArray | None,
        log_target_agent: FloatArray,
        gain: FloatArray,
        mu_points: FloatArray | None,
    ) -> tuple[BoolArray, BoolArray | None]:
        """Eq. (6) when agents have different numbers of relevant obstacles: ``_decide`` per group of equal
        count; an agent without any passes every point closer to the target (LHS = 0 < RHS = mu_t Delta).

        Returns (passing (A, K), inside rho_l (A, K) or None); fills ``mu_points`` in place.
        """
        passing = gain > _ZERO
        inside: BoolArray | None = None
        rows = np.flatnonzero(counts) if counts is not None else None  # None: one agent, no obstacle
        if counts is None or rows is None or not rows.size:
            return passing, inside
        if self.branching:
            inside = np.zeros(gain.shape, dtype=bool)  # None means no point is inside rho_l
        for idx in _groups(rows, counts, self._n_points):
            n_obs = int(counts[idx[0]])
            cols = np.nonzero(relevant[idx])[1].reshape(idx.size, n_obs)
            gathered = rel_o[:, idx[:, None], cols].transpose(0, 2, 1)
            ok, bad, mu = self._decide(gathered, log_target_agent[idx], gain[idx])
            passing[idx] = ok
            if inside is not None and bad is not None:
                inside[idx] = bad
            if mu_points is not None:
                mu_points[idx] = mu
        return passing, inside

    def _step_batch(
        self,
        positions_m: FloatArray,
        targets_m: FloatArray,
        obstacles_m: FloatArray,
        obstacle_mask: BoolArray | None,
        rng: np.random.Generator | None,
        walk_uniforms: FloatArray | None,
    ) -> BatchDecision:
        n_agents, dim = positions_m.shape
        log_target_agent, gain = self._target_terms(positions_m, targets_m)
        rel_o, relevant = self._relevant_obstacles(positions_m, obstacles_m, obstacle_mask, log_target_agent)
        counts, n_same = _relevant_counts(relevant)
        mu_points = self._initial_point_mu(n_agents, obstacles_m, obstacle_mask)
        inside: BoolArray | None
        if n_same:
            gathered = rel_o[:, relevant].reshape(dim, n_agents, n_same).transpose(0, 2, 1)
            passing, inside, mu = self._decide(gathered, log_target_agent, gain)
            if mu_points is not None:
                mu_points[:] = mu
        else:
            passing, inside = self._decide_by_groups(rel_o, relevant, counts, log_target_agent, gain, mu_points)
        return self._select(positions_m, passing, inside, gain, mu_points, rng, walk_uniforms)

    def _decide(
        self,
        rel_obstacles_m: FloatArray,
        log_target_agent: FloatArray,
        gain: FloatArray,
    ) -> tuple[BoolArray, BoolArray | None, FloatArray | float]:
        """Eq. (6) for A' agents with N' obstacles each: (passing (A', K), inside rho_l (A', K), mu at points).

        ``rel_obstacles_m``: (D, N', A') obstacle minus agent; ``log_target_agent`` (A',);
        ``gain`` (A', K). Work arrays are (N', A', K + 1); column K is the agent.
        """
        p = self.params
        n_points = self._n_points
        columns = self._columns
        diff = columns[0] - rel_obstacles_m[0][:, :, None]
        dist_sq = diff * diff
        for axis in range(1, len(columns)):
            np.subtract(columns[axis], rel_obstacles_m[axis][:, :, None], out=diff)
            diff *= diff
            dist_sq += diff

        if self.adaptive:
            shortcut = self._adaptive_decision(dist_sq, log_target_agent, gain)
            if shortcut is not None:
                return shortcut
        shift = (self._log_alpha_o - log_target_agent)[None, :, None]
        mu: FloatArray | float = self._mu_o
        if self.adaptive:
            log_target_points = log_target_agent[:, None] + self._mu_t * gain
            mu_k = self._point_mu(dist_sq[:, :, :n_points], log_target_points)
            mu = mu_k
            mu_all = np.empty((gain.shape[0], n_points + 1))
            mu_all[:, :n_points] = mu_k
            mu_all[:, n_points] = p.mu_o_per_m2
            terms = mu_all * dist_sq
        else:
            terms = mu * dist_sq
        np.subtract(shift, terms, out=terms)  # shifted log J_o^n: (N', A', K + 1)
        if self.branching:
            np.copyto(terms, _MINUS_INF, where=dist_sq > self._outside_d2)
            # Inside rho_l the term is +inf (Eq. (13)); a huge finite stand-in keeps the sums free of inf - inf
            # and still dominates every finite side, so each comparison below ends as with +inf.
            np.copyto(terms, _INSIDE_LOG, where=dist_sq < self._inside_d2)
        # Column k < K: log(1 + sum exp(terms)) (1 = shifted |J_t(r)|); column K: log(sum exp(agent terms)).
        peak = np.maximum(np.maximum.reduce(terms, axis=0), self._peak_floor)
        terms -= peak
        np.exp(terms, out=terms)
        total = np.add.reduce(terms, axis=0)
        total += np.exp(self._extra - peak)
        with np.errstate(divide="ignore"):  # an empty sum (no repulsion at the agent) is log 0 = -inf, as intended
            sides = np.log(total)
        sides += peak
        inside = sides >= _INSIDE_LOG if self.branching else None
        rhs = self._mu_t * gain
        if p.agent_repulsion:
            rhs = np.logaddexp(sides[:, n_points, None], rhs)
        passing = sides[:, :n_points] < rhs
        return passing, None if inside is None else inside[:, :n_points], mu

    def _select(
        self,
        positions_m: FloatArray,
        passing: BoolArray,
        inside: BoolArray | None,
        gain: FloatArray,
        mu_points: FloatArray | None,
        rng: np.random.Generator | None,
        walk_uniforms: FloatArray | None,
    ) -> BatchDecision:
        """First passing point in order of increasing target distance; else random walk or local minimum.

        ``inside`` (A, K): bacteria points within rho_l of a known obstacle (CR-BAPF); None: none are.
        """
        n_agents = passing.shape[0]
        chosen, n_passing, stuck, reason = _first_passing(passing, gain)
        safe, n_safe = _safe_points(self.branching, passing, inside)
        if self.random_walk:
            walkers = np.flatnonzero(stuck)
            if walkers.size:
                u = _walk_uniforms(walkers, rng, walk_uniforms)
                all_safe = safe if safe is not None else np.ones(passing.shape, dtype=bool)
                walkers, q = _random_walk(self.params.random_walk, all_safe, n_safe, walkers, u)
                chosen[walkers] = q
                reason[walkers] = DecisionReason.RANDOM_WALK
                stuck[walkers] = False

        next_points = positions_m + self._offsets_or_nan[chosen]  # chosen = -1: the NaN row
        if mu_points is not None:
            mu_o_k = mu_points[np.arange(n_agents), chosen]
            mu_o_k[stuck] = np.nan
        else:
            mu_o_k = filled(n_agents, np.nan, np.float64)
        return BatchDecision(
            next_points_m=next_points,
            reason=reason,
            chosen_index=chosen,
            mu_o_k=mu_o_k,
            n_passing=n_passing,
            n_safe=n_safe,
        )
