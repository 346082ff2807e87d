"""A-BAPF: bacteria APF with an adaptive mu_o,k per bacteria point (Diab et al. 2023, Eqs. (9)-(12)).

Diab, Mohammadkarimi, Rajan, "Artificial Potential Field-Based Path Planning for Cluttered Environments",
IEEE Aerospace 2023, DOI 10.1109/AERO55745.2023.10115857.

Notes
-----
Theorem (exact rule). For a bacteria point with at least one obstacle at squared distance rho_n > 0,
J_k(mu) = J_t + sum_n alpha_o exp(-mu rho_n) has derivative -sum_n alpha_o rho_n exp(-mu rho_n) < 0, so it is
strictly decreasing in mu and the argmin of Eq. (11) over [mu_min : mu_max] is mu_max. (The paper calls J_k
convex in mu; it is, and also monotone.) With no known obstacle J_k is constant and the first minimum,
mu_min, is taken. ``AbapfRule.EXACT`` with ``AbapfSearch.GRID`` uses this closed form; with
``AbapfSearch.GOLDEN`` the golden-section search actually evaluates the objective (in logs) and lands on the
same answer, which the tests check.

Paper rule. In float64 J_t + J_o rounds to J_t once J_o is below about 2^-53 |J_t|, and MATLAB's ``min`` then
returns the first such mu: that is the jumping mu_o,k of the paper's figure. ``AbapfRule.PAPER`` reproduces it
exactly in logs: the smallest integer mu with log J_o(mu) <= log |J_t(r_b,k)| - 53 log 2 (mu_max if none).
The predicate is monotone in mu, so GRID finds the first grid point by bisection over the integer grid (the
same answer as scanning all of it, in about 10 evaluations) and GOLDEN by golden-section search with ties
broken to the left on max(log J_o(mu), threshold), finished on the integer grid.

The paper rule's move test needs mu_o,k only near a tie: when the threshold is reachable, 0 < J_o(mu_o,k) <=
2^-53 |J_t(r_b,k)|, so Eq. (12) holds for sure if |J_t(r)| + 2^-53 |J_t(r_b,k)| < |J_t(r_b,k)| + J_o(r) and fails
for sure if |J_t(r)| >= |J_t(r_b,k)| + J_o(r). The search runs only for points between the two (rare) and for
each agent's chosen point (its mu_o,k is reported); the result is the same as searching every point.

In both rules the move test is Eq. (12) with J_a(r) of Eq. (4) at the fixed mu_o.
"""

from __future__ import annotations

import math

import numpy as np
import numpy.typing as npt

from apf_companion.planning.bacteria import _INV_PHI, _LOG_HALF_ULP, BacteriaPlanner
from apf_companion.planning.decision import filled
from apf_companion.planning.params import AbapfRule, AbapfSearch
from apf_companion.planning.potentials import log_sum_exp

__all__ = ["AbapfPlanner", "golden_section_mu", "grid_first_mu", "log_total_repulsion"]

FloatArray = npt.NDArray[np.float64]
BoolArray = npt.NDArray[np.bool_]


def log_total_repulsion(dist_sq_points_m2: FloatArray, mu_per_m2: FloatArray, *, alpha_o: float) -> FloatArray:
    """log J_o(r_b,k, mu_o,k) of Eq. (10): log-sum-exp over obstacles (first axis) of log alpha_o - mu rho.

    ``dist_sq_points_m2`` (N, ..., K), ``mu_per_m2`` (..., K). Returns (..., K).
    """
    terms = math.log(alpha_o) - mu_per_m2[None] * dist_sq_points_m2
    return log_sum_exp(terms, axis=0)


def grid_first_mu(
    dist_sq_points_m2: FloatArray, threshold_log: FloatArray, *, alpha_o: float, mu_min: int, mu_max: int
) -> FloatArray:
    """Smallest integer mu in [mu_min, mu_max] with log J_o(mu) <= threshold (mu_max if none), by bisection.

    ``dist_sq_points_m2`` (N, M) finite, ``threshold_log`` (M,). log J_o is non-increasing in mu, so the
    predicate is monotone and bisection over the integer grid returns exactly the first grid point that
    satisfies it. The bracket starts from alpha_o e^(-mu rho_min) <= J_o(mu) <= N alpha_o e^(-mu rho_min), and
    both ends are checked, so rounding in the bracket can cost an iteration but never the answer.
    """
    log_alpha = math.log(alpha_o)

    def satisfied(mu: npt.NDArray[np.int64]) -> BoolArray:
        terms = log_alpha - mu.astype(np.float64)[None] * dist_sq_points_m2
        peak = np.maximum.reduce(terms, axis=0)
        terms -= peak
        np.exp(terms, out=terms)
        return np.asarray(peak + np.log(np.add.reduce(terms, axis=0)) <= threshold_log)

    rho_min = np.minimum.reduce(dist_sq_points_m2, axis=0)
    with np.errstate(divide="ignore", invalid="ignore"):
        lo_f = np.floor((log_alpha - threshold_log) / rho_min) - 2.0
        hi_f = np.ceil((log_alpha + math.log(dist_sq_points_m2.shape[0]) - threshold_log) / rho_min) + 2.0
    lo_f = np.nan_to_num(lo_f, nan=mu_min - 1.0, posinf=mu_max - 1.0, neginf=mu_min - 1.0)
    lo = np.clip(lo_f, mu_min - 1, mu_max - 1).astype(np.int64)  # predicate false here (or below the grid)
    hi_f = np.nan_to_num(hi_f, nan=float(mu_max), posinf=float(mu_max), neginf=float(mu_min))
    hi = np.clip(hi_f, lo + 1, mu_max).astype(np.int64)  # predicate true here, or mu_max (the fallback)
    check = lo >= mu_min
    if check.any():
        lo = np.where(check & satisfied(np.maximum(lo, mu_min)), mu_min - 1, lo)
    check = hi < mu_max
    if check.any():
        hi = np.where(check & ~satisfied(hi), mu_max, hi)
    while True:
        open_ = hi - lo > 1
        if not open_.any():
            break
        mid = (lo + hi) // 2
        ok = satisfied(mid)
        hi = np.where(open_ & ok, mid, hi)
        lo = np.where(open_ & ~ok, mid, lo)
    return np.asarray(hi, dtype=np.float64)


def golden_section_mu(
    dist_sq_points_m2: FloatArray,
    threshold_log: FloatArray | None,
    *,
    alpha_o: float,
    mu_min: int,
    mu_max: int,
) -> FloatArray:
    """Golden-section search of Eq. (11) over [mu_min, mu_max], ties to the left (first minimum).

    ``threshold_log`` None: the exact objective log J_o(mu) (strictly decreasing, so this converges to
    mu_max); otherwise the paper-rule objective max(log J_o(mu), threshold), whose first minimum is where the
    repulsion falls below the threshold. The bracket is shrunk below one grid step and then finished on the
    integer grid.
    """
    shape = dist_sq_points_m2.shape[1:]
    lo = np.full(shape, float(mu_min))
    hi = np.full(shape, float(mu_max))

    def objective(mu: FloatArray) -> FloatArray:
        value = log_total_repulsion(dist_sq_points_m2, mu, alpha_o=alpha_o)
        return value if threshold_log is None else np.maximum(value, threshold_log)

    width = float(mu_max - mu_min)
    n_iter = 0 if width < 1.0 else math.ceil(math.log(width / 0.5) / -math.log(_INV_PHI))
    for _ in range(n_iter):
        c = hi - _INV_PHI * (hi - lo)
        d = lo + _INV_PHI * (hi - lo)
        left = objective(c) <= objective(d)
        hi = np.where(left, d, hi)
        lo = np.where(left, lo, c)
    if threshold_log is None:
        return np.asarray(np.clip(np.rint((lo + hi) / 2.0), mu_min, mu_max), dtype=np.float64)
    # The first satisfying grid point is ceil(mu*) with mu* in [lo, hi], hi - lo < 1: try three candidates.
    result = np.full(shape, float(mu_max))
    base = np.floor(lo)
    for offset in (2.0, 1.0, 0.0):
        cand = np.clip(base + offset, mu_min, mu_max)
        ok = log_total_repulsion(dist_sq_points_m2, cand, alpha_o=alpha_o) <= threshold_log
        result = np.where(ok, cand, result)
    return result


class AbapfPlanner(BacteriaPlanner):
    """A-BAPF (Eqs. (9)-(12)); rule and search from ``PlannerParams.abapf_rule`` / ``abapf_search``."""

    name = "a-bapf"
    adaptive = True

    def _smallest_point_mu(self) -> float:
        return float(self.params.mu_max)

    def _point_mu(self, dist_sq_points_m2: FloatArray, log_target_points: FloatArray) -> FloatArray | float:
        p = self.params
        if p.abapf_rule is AbapfRule.EXACT:
            if p.abapf_search is AbapfSearch.GRID:
                # Theorem in the module Notes: the grid argmin is mu_max (these agents know obstacles).
                return float(p.mu_max)
            return golden_section_mu(dist_sq_points_m2, None, alpha_o=p.alpha_o, mu_min=p.mu_min, mu_max=p.mu_max)
        threshold = log_target_points + _LOG_HALF_ULP
        if p.abapf_search is AbapfSearch.GRID:
            return grid_first_mu(dist_sq_points_m2, threshold, alpha_o=p.alpha_o, mu_min=p.mu_min, mu_max=p.mu_max)
        return golden_section_mu(dist_sq_points_m2, threshold, alpha_o=p.alpha_o, mu_min=p.mu_min, mu_max=p.mu_max)

    def _search(self, dist_sq_m2: FloatArray, threshold_log: FloatArray) -> FloatArray:
        """Paper-rule mu_o,k for M points: ``dist_sq_m2`` (N, M), ``threshold_log`` (M,)."""
        p = self.params
        if p.abapf_search is AbapfSearch.GRID:
            return grid_first_mu(dist_sq_m2, threshold_log, alpha_o=p.alpha_o, mu_min=p.mu_min, mu_max=p.mu_max)
        return golden_section_mu(dist_sq_m2, threshold_log, alpha_o=p.alpha_o, mu_min=p.mu_min, mu_max=p.mu_max)

    def _adaptive_decision(
        self, dist_sq_m2: FloatArray, log_target_agent: FloatArray, gain: FloatArray
    ) -> tuple[BoolArray, BoolArray | None, FloatArray] | None:
        """The paper rule, searching mu_o,k only where it can matter (module Notes)."""
        p = self.params
        if p.abapf_rule is not AbapfRule.PAPER:
            return None
        n_agents, n_points = gain.shape
        points = dist_sq_m2[:, :, :n_points]
        target_gain = p.mu_t_per_m2 * gain  # log |J_t(r_b,k)| - log |J_t(r)|
        threshold = (log_target_agent[:, None] + target_gain) + _LOG_HALF_ULP  # (A', K), absolute logs
        at_mu_max = log_total_repulsion(points, filled(1, float(p.mu_max), np.float64), alpha_o=p.alpha_o)
        reachable = at_mu_max <= threshold

        # Both sides shifted by a = log |J_t(r)|, as in the generic path.
        shift = log_target_agent[:, None]
        rhs = target_gain
        if p.agent_repulsion:
            agent = log_sum_exp(math.log(p.alpha_o) - p.mu_o_per_m2 * dist_sq_m2[:, :, n_points], axis=0)
            rhs = np.logaddexp((agent - log_target_agent)[:, None], target_gain)
        passing = np.where(
            reachable,
            np.logaddexp(0.0, threshold - shift) < rhs,  # sure pass (see Notes)
            np.logaddexp(0.0, at_mu_max - shift) < rhs,  # not reachable: mu_o,k = mu_max, exact
        )
        mu = np.full((n_agents, n_points), np.nan)
        mu[~reachable] = float(p.mu_max)
        band = reachable & ~passing & (rhs > 0.0)  # neither sure pass nor sure fail
        if band.any():
            rows, cols = np.nonzero(band)
            mu_band = self._search(points[:, rows, cols], threshold[rows, cols])
            lhs = np.logaddexp(
                0.0, log_total_repulsion(points[:, rows, cols], mu_band, alpha_o=p.alpha_o) - shift[rows, 0]
            )
            passing[rows, cols] = lhs < rhs[rows, cols]
            mu[rows, cols] = mu_band
        # The chosen point of each agent (first passing in order) reports its mu_o,k.
        chosen = np.where(passing, gain, -np.inf).argmax(axis=1)
        agents = np.arange(n_agents)
        need = np.flatnonzero(passing[agents, chosen] & np.isnan(mu[agents, chosen]))
        if need.size:
            cols = chosen[need]
            mu[need, cols] = self._search(points[:, need, cols], threshold[need, cols])
        return passing, None, mu
