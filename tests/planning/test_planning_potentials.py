"""Potentials against hand-computed values; the log-domain decision of Eq. (6) against mpmath."""

from __future__ import annotations

import math

import mpmath
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from apf_companion.planning import (
    agent_potential,
    branch_obstacle_potential,
    log_sum_exp,
    moves_downhill,
    obstacle_potential,
    target_potential,
    total_obstacle_potential,
)
from apf_companion.planning.potentials import (
    dist_sq_threshold_above,
    dist_sq_threshold_below,
    log_branch_obstacle_terms,
    log_obstacle_terms,
    log_target_term,
)

mpmath.mp.dps = 60


def test_target_potential_hand_values() -> None:
    # Eq. (1): -1e4 * exp(-1 * 2) = -1353.352832366127; at the start (3,3) -> (22,22): rho_t = 722.
    assert target_potential(2.0, alpha_t=1e4, mu_t_per_m2=1.0) == pytest.approx(-1353.352832366127, rel=1e-15)
    assert target_potential(0.0, alpha_t=1e4, mu_t_per_m2=1.0) == -1e4
    assert target_potential(722.0, alpha_t=1e4, mu_t_per_m2=1.0) == pytest.approx(-1e4 * math.exp(-722), rel=1e-9)
    # Beyond 27.3 m from the target the float64 value is exactly 0: why decisions are taken in logs.
    assert target_potential(27.3**2, alpha_t=1e4, mu_t_per_m2=1.0) == 0.0


def test_obstacle_potentials_hand_values() -> None:
    # Eq. (2): exp(-1000 * 0.25) = exp(-250).
    assert obstacle_potential(0.25, alpha_o=1.0, mu_o_per_m2=1000.0) == pytest.approx(2.6719e-109, rel=1e-4)
    assert obstacle_potential(0.0, alpha_o=2.0, mu_o_per_m2=1000.0) == 2.0
    # Exactly 0 beyond 0.863 m (float64 underflow).
    assert obstacle_potential(0.864**2, alpha_o=1.0, mu_o_per_m2=1000.0) == 0.0
    # Eq. (3) and Eq. (4).
    terms = np.array([0.5, 0.25, 4.0])
    assert total_obstacle_potential(terms) == 4.75
    assert total_obstacle_potential(terms, mask=[True, False, True]) == 4.5
    assert agent_potential(-10.0, 4.5) == -5.5


def test_branch_potential_limits_are_inclusive_on_the_plain_distance() -> None:
    dist_m = np.array([0.0, 0.39, 0.4, 1.0, 4.5, 4.51])
    values = branch_obstacle_potential(dist_m**2, alpha_o=1.0, mu_o_per_m2=1.0, rho_l_m=0.4, rho_u_m=4.5)
    assert values[0] == np.inf and values[1] == np.inf
    assert values[2] == pytest.approx(math.exp(-0.16))  # rho_l itself: the Eq. (2) branch
    assert values[3] == pytest.approx(math.exp(-1.0))
    assert values[4] == pytest.approx(math.exp(-20.25))  # rho_u itself: still repels
    assert values[5] == 0.0


@settings(max_examples=200, deadline=None)
@given(st.floats(min_value=1e-6, max_value=50.0), st.integers(min_value=-3, max_value=3))
def test_dist_sq_thresholds_match_the_plain_distance(rho_m: float, ulps: int) -> None:
    below = dist_sq_threshold_below(rho_m)
    above = dist_sq_threshold_above(rho_m)
    for base in (rho_m * rho_m, below, above):
        x = base
        for _ in range(abs(ulps)):
            x = math.nextafter(x, math.inf if ulps > 0 else -math.inf)
        assert (math.sqrt(x) < rho_m) == (x < below)
        assert (math.sqrt(x) > rho_m) == (x > above)


def test_log_terms_agree_with_the_linear_ones() -> None:
    d2 = np.array([0.0, 0.1, 0.16, 1.0, 20.25, 21.0])
    lin = branch_obstacle_potential(d2, alpha_o=2.0, mu_o_per_m2=3.0, rho_l_m=0.4, rho_u_m=4.5)
    logs = log_branch_obstacle_terms(d2, alpha_o=2.0, mu_o_per_m2=3.0, rho_l_m=0.4, rho_u_m=4.5)
    with np.errstate(divide="ignore"):
        np.testing.assert_allclose(np.log(lin), logs)
    np.testing.assert_allclose(np.exp(log_obstacle_terms(d2, alpha_o=2.0, mu_o_per_m2=3.0)), 2 * np.exp(-3 * d2))
    assert log_target_term(722.0, alpha_t=1e4, mu_t_per_m2=1.0) == pytest.approx(math.log(1e4) - 722.0)


def test_log_sum_exp_edge_cases() -> None:
    assert log_sum_exp(np.array([-np.inf, -np.inf])) == -np.inf
    assert log_sum_exp(np.zeros(0)) == -np.inf
    assert log_sum_exp(np.array([1.0, np.inf])) == np.inf
    assert log_sum_exp(np.array([-np.inf, 2.0])) == 2.0
    assert log_sum_exp(np.array([0.0, 0.0]), extra=0.0) == pytest.approx(math.log(3.0))
    # No underflow: exp(-1e6) summed twice.
    assert log_sum_exp(np.array([-1e6, -1e6])) == pytest.approx(-1e6 + math.log(2.0))


def test_moves_downhill_hand_cases() -> None:
    # No obstacles: a point is downhill iff it is closer to the target.
    lt_agent = log_target_term(4.0, alpha_t=1e4, mu_t_per_m2=1.0)
    lt_points = log_target_term(np.array([3.0, 5.0, 4.0]), alpha_t=1e4, mu_t_per_m2=1.0)
    empty_a = np.zeros(0)
    empty_p = np.zeros((3, 0))
    assert moves_downhill(lt_agent, lt_points, empty_a, empty_p).tolist() == [True, False, False]
    # Inside rho_l at the point: never; inside rho_l at the agent (J_a = inf): any finite point passes;
    # both infinite: inf - inf is NaN, not < 0.
    inf_p = np.array([[np.inf], [-np.inf], [np.inf]])
    assert moves_downhill(lt_agent, lt_points, np.array([-np.inf]), inf_p).tolist() == [False, False, False]
    assert moves_downhill(lt_agent, lt_points, np.array([np.inf]), inf_p).tolist() == [False, True, False]
    # Far from the target, where the naive float64 form gives 0 - 0 and refuses every move.
    far_agent = log_target_term(40.0**2, alpha_t=1e4, mu_t_per_m2=1.0)
    far_point = log_target_term(np.array([39.6**2]), alpha_t=1e4, mu_t_per_m2=1.0)
    assert moves_downhill(far_agent, far_point, empty_a, np.zeros((1, 0))).tolist() == [True]
    naive = target_potential(39.6**2, alpha_t=1e4, mu_t_per_m2=1.0) - target_potential(
        40.0**2, alpha_t=1e4, mu_t_per_m2=1.0
    )
    assert not naive < 0


def exact_gap(
    d2_target_agent: float,
    d2_target_point: float,
    log_obs_agent: np.ndarray,
    log_obs_point: np.ndarray,
    alpha_t: float,
    mu_t: float,
) -> tuple[mpmath.mpf, mpmath.mpf]:
    """(LHS, RHS) of |J_t(r)| + J_o(b) < |J_t(b)| + J_o(r), exactly from the float inputs."""

    def side(target_d2: float, logs: np.ndarray) -> mpmath.mpf:
        total = mpmath.mpf(alpha_t) * mpmath.exp(-mpmath.mpf(mu_t) * mpmath.mpf(target_d2))
        for v in logs:
            total += mpmath.inf if v == np.inf else (0 if v == -np.inf else mpmath.exp(mpmath.mpf(float(v))))
        return total

    return side(d2_target_agent, log_obs_point), side(d2_target_point, log_obs_agent)


@pytest.mark.parametrize("seed", range(4))
def test_moves_downhill_matches_mpmath(seed: int) -> None:
    rng = np.random.default_rng(seed)
    checked = 0
    for _ in range(150):
        # Agent up to 80 m from the target (the naive form fails beyond 27.3 m); obstacles close by.
        dist_t = rng.uniform(0.0, 80.0)
        d2_agent_t = dist_t**2
        step = rng.uniform(-0.4, 0.4)
        d2_points_t = np.array([max(dist_t + step, 0.0) ** 2, (dist_t + rng.uniform(-0.4, 0.4)) ** 2])
        n = int(rng.integers(0, 6))
        mu_o = float(rng.choice([1.0, 30.0, 1000.0]))
        d2_obs_agent = rng.uniform(0.0, 6.0, n) ** 2
        d2_obs_points = rng.uniform(0.0, 6.0, (2, n)) ** 2
        branch = bool(rng.integers(0, 2))
        if branch:
            lo_a = log_branch_obstacle_terms(d2_obs_agent, alpha_o=1.0, mu_o_per_m2=mu_o, rho_l_m=0.4, rho_u_m=4.5)
            lo_p = log_branch_obstacle_terms(d2_obs_points, alpha_o=1.0, mu_o_per_m2=mu_o, rho_l_m=0.4, rho_u_m=4.5)
        else:
            lo_a = log_obstacle_terms(d2_obs_agent, alpha_o=1.0, mu_o_per_m2=mu_o)
            lo_p = log_obstacle_terms(d2_obs_points, alpha_o=1.0, mu_o_per_m2=mu_o)
        got = moves_downhill(
            log_target_term(d2_agent_t, alpha_t=1e4, mu_t_per_m2=1.0),
            log_target_term(d2_points_t, alpha_t=1e4, mu_t_per_m2=1.0),
            lo_a,
            lo_p,
        )
        for k in range(2):
            lhs, rhs = exact_gap(d2_agent_t, float(d2_points_t[k]), lo_a, lo_p[k], 1e4, 1.0)
            if mpmath.isinf(lhs) or mpmath.isinf(rhs):
                expected = bool(mpmath.isinf(rhs) and not mpmath.isinf(lhs))
            else:
                if abs(lhs - rhs) <= mpmath.mpf("1e-12") * max(lhs, rhs):
                    continue  # a tie to 12 digits: beyond what any float64 input can decide
                expected = bool(lhs < rhs)
            assert bool(got[k]) == expected, (dist_t, d2_points_t[k], lo_a, lo_p[k])
            checked += 1
    assert checked > 250


distances = st.floats(min_value=0.0, max_value=1e3, allow_nan=False)


@settings(max_examples=200, deadline=None)
@given(d1=distances, d2=distances, mu=st.floats(min_value=1e-3, max_value=1e3))
def test_potentials_are_monotone_in_distance(d1: float, d2: float, mu: float) -> None:
    near, far = sorted((d1, d2))
    # Eq. (1) rises toward 0 with distance; Eq. (2) falls toward 0; their logs are finite at any distance.
    assert target_potential(near**2, alpha_t=1e4, mu_t_per_m2=mu) <= target_potential(
        far**2, alpha_t=1e4, mu_t_per_m2=mu
    )
    assert obstacle_potential(near**2, alpha_o=1.0, mu_o_per_m2=mu) >= obstacle_potential(
        far**2, alpha_o=1.0, mu_o_per_m2=mu
    )
    logs = log_obstacle_terms(np.array([near**2, far**2]), alpha_o=1.0, mu_o_per_m2=mu)
    assert np.all(np.isfinite(logs)) and logs[0] >= logs[1]
    assert np.isfinite(log_target_term(far**2, alpha_t=1e4, mu_t_per_m2=mu))
    # Eq. (13): non-increasing in distance too (inf, then the exponential, then 0).
    branch = branch_obstacle_potential(
        np.array([near**2, far**2]), alpha_o=1.0, mu_o_per_m2=mu, rho_l_m=0.4, rho_u_m=4.5
    )
    assert branch[0] >= branch[1]
