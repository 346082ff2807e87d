"""Potentials of the bacteria APF and the move decision, in the linear and in the log domain.

Diab, Mohammadkarimi, Rajan, "Artificial Potential Field-Based Path Planning for Cluttered Environments",
IEEE Aerospace 2023, DOI 10.1109/AERO55745.2023.10115857. The paper's rho is a *squared* distance; here it is
called ``dist_sq_*_m2``.

Notes
-----
With the paper's constants the potentials live at the edge of float64: exp(-mu_t rho_t) underflows to 0 beyond
27.3 m from the target and the repulsion with mu_o = 1000 is exactly 0 beyond 0.863 m. So the decision of
Eq. (6) is never taken on the linear values. Every term of J_k - J_a < 0 is a signed exponential; moving the
negative terms across gives a comparison of two sums of positive exponentials,

    alpha_t e^(-mu_t rho_t(r)) + sum_n J_o^n(r_b,k)  <  alpha_t e^(-mu_t rho_t(r_b,k)) + sum_n J_o^n(r),

and both sides are compared through their log-sum-exp, with +inf (inside rho_l, Eq. (13)) propagating and
inf < inf false (IEEE: inf - inf is NaN, and NaN < 0 is false). The linear functions below exist for reference
and tests.
"""

from __future__ import annotations

import math

import numpy as np
import numpy.typing as npt

__all__ = [
    "agent_potential",
    "branch_obstacle_potential",
    "dist_sq_threshold_above",
    "dist_sq_threshold_below",
    "log_branch_obstacle_terms",
    "log_obstacle_terms",
    "log_sum_exp",
    "log_target_term",
    "moves_downhill",
    "obstacle_potential",
    "target_potential",
    "total_obstacle_potential",
]

FloatArray = npt.NDArray[np.float64]
ArrayLike = npt.ArrayLike


def target_potential(dist_sq_target_m2: ArrayLike, *, alpha_t: float, mu_t_per_m2: float) -> FloatArray:
    """Eq. (1): J_t = -alpha_t exp(-mu_t rho_t), rho_t the squared distance to the target [m^2]."""
    return -alpha_t * np.exp(-mu_t_per_m2 * np.asarray(dist_sq_target_m2, dtype=np.float64))


def obstacle_potential(dist_sq_obstacle_m2: ArrayLike, *, alpha_o: float, mu_o_per_m2: float) -> FloatArray:
    """Eq. (2): J_o^n = alpha_o exp(-mu_o rho_o^n), rho_o^n the squared distance to obstacle n [m^2]."""
    return alpha_o * np.exp(-mu_o_per_m2 * np.asarray(dist_sq_obstacle_m2, dtype=np.float64))


def branch_obstacle_potential(
    dist_sq_obstacle_m2: ArrayLike, *, alpha_o: float, mu_o_per_m2: float, rho_l_m: float, rho_u_m: float
) -> FloatArray:
    """Eq. (13), CR-BAPF: 0 beyond rho_u, Eq. (2) for rho_l <= distance <= rho_u (inclusive), +inf inside rho_l.

    The limits compare the plain distance sqrt(rho_o^n), as the equation does.
    """
    dist_sq = np.asarray(dist_sq_obstacle_m2, dtype=np.float64)
    dist_m = np.sqrt(dist_sq)
    inner = alpha_o * np.exp(-mu_o_per_m2 * dist_sq)
    return np.where(dist_m < rho_l_m, np.inf, np.where(dist_m > rho_u_m, 0.0, inner))


def total_obstacle_potential(obstacle_terms: ArrayLike, mask: ArrayLike | None = None) -> FloatArray:
    """Eq. (3): J_o = sum over the N_d detected obstacles (last axis) of J_o^n; ``mask`` selects them."""
    terms = np.asarray(obstacle_terms, dtype=np.float64)
    if mask is not None:
        terms = np.where(np.asarray(mask, dtype=bool), terms, 0.0)
    return np.asarray(np.sum(terms, axis=-1), dtype=np.float64)


def agent_potential(target_term: ArrayLike, obstacle_total: ArrayLike) -> FloatArray:
    """Eq. (4) (agent) and Eq. (5) (bacteria point): J = J_t + J_o."""
    return np.asarray(target_term, dtype=np.float64) + np.asarray(obstacle_total, dtype=np.float64)


def log_target_term(dist_sq_target_m2: ArrayLike, *, alpha_t: float, mu_t_per_m2: float) -> FloatArray:
    """log |J_t| of Eq. (1): log alpha_t - mu_t rho_t (finite at any distance)."""
    return math.log(alpha_t) - mu_t_per_m2 * np.asarray(dist_sq_target_m2, dtype=np.float64)


def log_obstacle_terms(dist_sq_obstacle_m2: ArrayLike, *, alpha_o: float, mu_o_per_m2: ArrayLike) -> FloatArray:
    """log J_o^n of Eq. (2) (and Eq. (10) with a per-point mu_o,k): log alpha_o - mu_o rho_o^n."""
    return math.log(alpha_o) - np.asarray(mu_o_per_m2, dtype=np.float64) * np.asarray(
        dist_sq_obstacle_m2, dtype=np.float64
    )


def dist_sq_threshold_below(rho_m: float) -> float:
    """Smallest float64 x >= 0 with sqrt(x) >= rho_m, so that ``sqrt(d2) < rho_m`` is exactly ``d2 < x``.

    sqrt is correctly rounded and monotone, so comparing squared distances against this threshold gives the
    same answer as comparing the plain distance (Eq. (13)) without a square root per pair.
    """
    if rho_m <= 0.0:
        return 0.0
    x = rho_m * rho_m
    while math.sqrt(x) >= rho_m:
        x = math.nextafter(x, -math.inf)
    while math.sqrt(x) < rho_m:
        x = math.nextafter(x, math.inf)
    return x


def dist_sq_threshold_above(rho_m: float) -> float:
    """Largest float64 x with sqrt(x) <= rho_m, so that ``sqrt(d2) > rho_m`` is exactly ``d2 > x``."""
    x = rho_m * rho_m
    while math.sqrt(x) > rho_m:
        x = math.nextafter(x, -math.inf)
    while math.sqrt(math.nextafter(x, math.inf)) <= rho_m:
        x = math.nextafter(x, math.inf)
    return x


def log_branch_obstacle_terms(
    dist_sq_obstacle_m2: ArrayLike,
    *,
    alpha_o: float,
    mu_o_per_m2: ArrayLike,
    rho_l_m: float,
    rho_u_m: float,
) -> FloatArray:
    """log of Eq. (13): -inf beyond rho_u (a zero term), log alpha_o - mu_o rho between, +inf inside rho_l."""
    dist_sq = np.asarray(dist_sq_obstacle_m2, dtype=np.float64)
    logs = log_obstacle_terms(dist_sq, alpha_o=alpha_o, mu_o_per_m2=mu_o_per_m2)
    inside = dist_sq < dist_sq_threshold_below(rho_l_m)
    outside = dist_sq > dist_sq_threshold_above(rho_u_m)
    return np.where(inside, np.inf, np.where(outside, -np.inf, logs))


def log_sum_exp(log_terms: ArrayLike, axis: int = -1, *, extra: ArrayLike | None = None) -> FloatArray:
    """log(sum(exp(log_terms)) [+ exp(extra)]) along ``axis``, with +inf propagating and -inf as a zero term.

    An empty sum (all terms -inf, or no terms) gives -inf. ``extra`` (broadcast against the result) is one more
    term per output, e.g. the target term of one side of Eq. (6).
    """
    x = np.asarray(log_terms, dtype=np.float64)
    if x.shape[axis] == 0:
        out = np.full(np.delete(np.array(x.shape), axis).tolist(), -np.inf)
    else:
        peak = np.maximum.reduce(x, axis=axis, keepdims=True)
        finite = np.isfinite(peak)
        safe_peak = np.where(finite, peak, 0.0)
        with np.errstate(divide="ignore", invalid="ignore"):
            total = np.add.reduce(np.exp(x - safe_peak), axis=axis, keepdims=True)
            out = np.where(finite, safe_peak + np.log(total), peak)
        out = np.squeeze(out, axis=axis)
    if extra is not None:
        out = np.logaddexp(out, np.asarray(extra, dtype=np.float64))
    return np.asarray(out, dtype=np.float64)


def moves_downhill(
    log_target_agent: ArrayLike,
    log_target_points: ArrayLike,
    log_obstacles_agent: ArrayLike,
    log_obstacles_points: ArrayLike,
) -> npt.NDArray[np.bool_]:
    """Eq. (6): J_k(r_b,k) - J_a(r) < 0, decided exactly in the log domain.

    Parameters
    ----------
    log_target_agent : (...,) log |J_t(r)| (see ``log_target_term``).
    log_target_points : (..., K) log |J_t(r_b,k)|.
    log_obstacles_agent : (..., N) log J_o^n(r); -inf for a zero or absent term, +inf inside rho_l.
    log_obstacles_points : (..., K, N) log J_o^n(r_b,k), same conventions.

    Returns
    -------
    (..., K) bool: True where the bacteria point has a strictly lower total potential than the agent.

    Notes
    -----
    J_k - J_a < 0  <=>  |J_t(r)| + J_o(r_b,k) < |J_t(r_b,k)| + J_o(r): both sides are sums of positive
    exponentials, compared through log-sum-exp. All inputs may be shifted by one common constant per agent
    (the planners subtract log |J_t(r)|) without changing the result.
    """
    lt_agent = np.asarray(log_target_agent, dtype=np.float64)
    lt_points = np.asarray(log_target_points, dtype=np.float64)
    lo_agent = np.asarray(log_obstacles_agent, dtype=np.float64)
    lo_points = np.asarray(log_obstacles_points, dtype=np.float64)
    lhs = log_sum_exp(lo_points, axis=-1, extra=lt_agent[..., None])
    rhs = log_sum_exp(lo_agent, axis=-1)[..., None]
    rhs = np.logaddexp(rhs, lt_points)
    return np.asarray(lhs < rhs)
