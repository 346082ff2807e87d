"""A-BAPF: bacteria APF with an adaptive mu_o,k per bacteria point (Diab et al. 2023, Eqs. (13)-(15)).

Diab, Mohammadkarimi, Rajan, "Artificial Potential Field-Based Path Planning for Cluttered Environments",
IEEE Aerospace 2023, DOI 10.1109/AERO55745.2023.10115857.

Notes
-----
Theorem (exact rule). For a bacteria point with at least one obstacle at squared distance rho_n > 0,
J_k(mu) = J_t + sum_n alpha_o exp(-mu rho_n) has derivative -sum_n alpha_o rho_n exp(-mu rho_n) < 0, so it is
strictly decreasing in mu and the argmin of Eq. (14) over [mu_min : mu_max] is mu_max. (The paper calls J_k
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

In both rules the move test is Eq. (15) with J_a(r) of Eq. (4) at the fixed mu_o.
"""

from __future__ import annotations

import math

import numpy as np
import numpy.typing as npt

from apf_companion.planning.bacteria import _INV_PHI, _LOG_HALF_ULP, BacteriaPlanner
from apf_companion.planning.params import AbapfRule, AbapfSearch
from apf_companion.planning.potentials import log_sum_exp

__all__ = ["AbapfPlanner", "golden_section_mu", "grid_first_mu", "log_total_repulsion"]

FloatArray = npt.NDArray[np.float64]
BoolArray = npt.NDArray[np.bool_]


def log_total_repulsion(dist_sq_points_m2: FloatArray, mu_per_m2: FloatArray, *, alpha_o: float) -> FloatArray:
    """log J_o(r_b,k, mu_o,k) of Eq. (13): log-sum-exp over obstacles (first axis) of log alpha_o - mu rho.

    ``dist_sq_points_m2`` (N, ..., K), ``mu_per_m2`` (..., K). Returns (..., K).
    """
    terms = math.log(alpha_o) - mu_per_m2[None] * dist_sq_points_m2
    return log_sum_exp(terms, axis=0)


def grid_first_mu(
    dist_sq_points_m2: FloatArray, threshold_log: FloatArray, *, alpha_o: float, mu_min: int, mu_max: int
) -> FloatArray:
    """Smallest integer mu in [mu_min, mu_max] with log J_o(mu) <= threshold (mu_max if none), by bisection.

    log J_o is non-increasing in mu, so the predicate is monotone and bisection over the integer grid returns
    exactly the first grid point that satisfies it.
    """
    shape = threshold_log.shape
    lo = np.full(shape, mu_min - 1, dtype=np.int64)  # predicate false (sentinel below the grid)
    hi = np.full(shape, mu_max, dtype=np.int64)  # answer, or mu_max when no grid point satisfies it
    while True:
        open_ = hi - lo > 1
        if not open_.any():
            break
        mid = (lo + hi) // 2
        ok = log_total_repulsion(dist_sq_points_m2, mid.astype(np.float64), alpha_o=alpha_o) <= threshold_log
        hi = np.where(open_ & ok, mid, hi)
        lo = np.where(open_ & ~ok, mid, lo)
    return hi.astype(np.float64)


def golden_section_mu(
    dist_sq_points_m2: FloatArray,
    threshold_log: FloatArray | None,
    *,
    alpha_o: float,
    mu_min: int,
    mu_max: int,
) -> FloatArray:
    """Golden-section search of Eq. (14) over [mu_min, mu_max], ties to the left (first minimum).

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
    """A-BAPF (Eqs. (13)-(15)); rule and search from ``PlannerParams.abapf_rule`` / ``abapf_search``."""

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
