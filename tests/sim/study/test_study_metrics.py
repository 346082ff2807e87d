"""Study metrics and worlds on hand-made cases."""

from __future__ import annotations

import math

import numpy as np
import pytest

from apf_companion.errors import ConfigError
from sim.study.config import DEFAULT_DENSITIES, Density, DetectionRule, StudyConfig, mu_sweep_grid
from sim.study.metrics import Outcome, TrialRecords, safety_per_trial, summarize, wilson_interval
from sim.study.worlds import draw_worlds


def _records(outcomes: list[Outcome], iterations: list[int], safety: list[float]) -> TrialRecords:
    n = len(outcomes)
    return TrialRecords(
        outcome=np.array(outcomes, dtype=np.int8),
        iterations=np.array(iterations, dtype=np.int32),
        safety_m=np.array(safety),
        n_obstacles=np.full(n, 10, dtype=np.int32),
        n_detected=np.full(n, 3, dtype=np.int32),
        time_ms=np.arange(n, dtype=np.float64),
    )


def test_wilson_interval_known_values() -> None:
    # Reference values: Wilson score interval, z = 1.96 (e.g. Newcombe 1998, table I: 81/263 -> 0.2553..0.3662).
    lo, hi = wilson_interval(81, 263)
    assert lo == pytest.approx(0.2553, abs=1e-4)
    assert hi == pytest.approx(0.3662, abs=1e-4)
    lo, hi = wilson_interval(0, 10)
    assert lo == 0.0
    assert hi == pytest.approx(0.2775, abs=1e-4)
    lo, hi = wilson_interval(10, 10)
    assert hi == 1.0
    assert lo == pytest.approx(0.7225, abs=1e-4)
    assert wilson_interval(0, 0) == (0.0, 1.0)


def test_summarize_counts_and_success_only_means() -> None:
    rec = _records(
        [Outcome.SUCCESS, Outcome.COLLISION, Outcome.SUCCESS, Outcome.STUCK, Outcome.TIMEOUT],
        [70, 12, 80, 30, 900],
        [2.0, 0.1, 3.0, 1.0, 5.0],
    )
    s = summarize(rec)
    assert s.trials == 5
    assert s.R_s == pytest.approx(0.4)
    assert s.M_s == pytest.approx(75.0)  # successful trials only
    assert pytest.approx(2.5) == s.S
    assert s.T_a_ms == pytest.approx(2.0)  # all trials
    assert (s.success, s.collision, s.stuck, s.timeout) == (2, 1, 1, 1)
    assert s.R_s_ci95[0] < 0.4 < s.R_s_ci95[1]
    doc = s.to_json()
    assert doc["counts"] == {"success": 2, "collision": 1, "stuck": 1, "timeout": 1}


def test_summarize_no_success_gives_nan_means() -> None:
    s = summarize(_records([Outcome.COLLISION, Outcome.STUCK], [3, 4], [1.0, 1.0]))
    assert s.R_s == 0.0
    assert math.isnan(s.M_s)
    assert math.isnan(s.S)
    assert s.to_json()["M_s"] is None


def test_safety_is_mean_over_detected_obstacles_only() -> None:
    min_dist = np.array([[1.0, 2.0, 9.0], [np.inf, np.inf, np.inf]])
    detected = np.array([[True, True, False], [False, False, False]])
    s = safety_per_trial(min_dist, detected)
    assert s[0] == pytest.approx(1.5)
    assert math.isnan(s[1])


def test_concat_keeps_order() -> None:
    a = _records([Outcome.SUCCESS], [1], [1.0])
    b = _records([Outcome.STUCK, Outcome.SUCCESS], [2, 3], [2.0, 3.0])
    c = TrialRecords.concat([a, b])
    assert c.iterations.tolist() == [1, 2, 3]
    assert len(TrialRecords.concat([])) == 0


def test_worlds_counts_box_and_padding() -> None:
    rng = np.random.default_rng(1)
    d = Density(n_low=20, n_high=45)
    w = draw_worlds(rng, 2000, d, (5.0, 20.0), 2)
    assert w.obstacles_m.shape == (2000, 45, 2)
    counts = w.counts
    assert counts.min() == 20
    assert counts.max() == 45  # inclusive upper bound, reached with 2000 draws of 26 values
    assert np.all(w.obstacles_m >= 5.0)
    assert np.all(w.obstacles_m <= 20.0)
    # Continuous, not integer coordinates.
    assert np.mean(w.obstacles_m != np.round(w.obstacles_m)) > 0.99
    # The mask marks the first `count` rows.
    assert np.array_equal(w.mask, np.arange(45)[None, :] < counts[:, None])


def test_presets_rules() -> None:
    ref = StudyConfig.reference()
    pap = StudyConfig.paper()
    assert ref.obstacle_box_m == (5.0, 20.0)
    assert pap.obstacle_box_m == (0.0, 30.0)
    assert ref.detection is DetectionRule.CUMULATIVE
    assert pap.detection is DetectionRule.IN_RANGE
    assert ref.planner_params.agent_repulsion is False
    assert pap.planner_params.agent_repulsion is True
    assert ref.planner_params.random_walk.name == "SINGLE_DRAW"
    assert pap.planner_params.random_walk.name == "SAFE_SET"
    for cfg in (ref, pap):
        assert cfg.start_m == (3.0, 3.0)
        assert cfg.target_m == (22.0, 22.0)
        assert cfg.sensor_range_m == 8.0
        assert cfg.planner_params.step_m == 0.4
        assert cfg.planner_params.n_bacteria == 60
        assert cfg.noise_std_m == 0.1
        assert cfg.collision_radius_m == 0.25
        assert cfg.goal_radius_m == 0.7
        assert cfg.max_iterations == 900
    assert StudyConfig.from_preset("paper") == pap


def test_config_errors_name_the_field() -> None:
    import dataclasses

    with pytest.raises(ConfigError, match="goal_radius_m"):
        dataclasses.replace(StudyConfig.reference(), goal_radius_m=-1.0)
    with pytest.raises(ConfigError, match="obstacle_box_m"):
        dataclasses.replace(StudyConfig.reference(), obstacle_box_m=(3.0, 1.0))
    with pytest.raises(ConfigError, match="preset"):
        StudyConfig.from_preset("nope")
    with pytest.raises(ConfigError, match="density"):
        Density.parse("45-20")
    with pytest.raises(ConfigError, match="density"):
        Density.parse("abc")


def test_density_parse_and_defaults() -> None:
    assert Density.parse("20-45") == Density(n_low=20, n_high=45)
    assert Density.parse("7") == Density(n_low=7, n_high=7)
    assert [d.label for d in DEFAULT_DENSITIES] == ["20-45", "45-70", "70-95"]


def test_mu_sweep_grid() -> None:
    grid = mu_sweep_grid()
    assert len(grid) == 13
    assert grid[0] == 1.0
    assert grid[5] == pytest.approx(416.6667, abs=1e-3)  # the paper's crossover point
    assert grid[-1] == 1000.0


def test_integer_sampling_lattice_and_duplicates_masked() -> None:
    from sim.study.config import ObstacleSampling

    rng = np.random.default_rng(2)
    w = draw_worlds(rng, 300, Density(n_low=70, n_high=95), (5.0, 20.0), 2, ObstacleSampling.INTEGER)
    pts = w.obstacles_m
    assert np.array_equal(pts, np.round(pts))
    assert pts.min() == 5.0
    assert pts.max() == 20.0
    # 70-95 draws on a 16 x 16 lattice repeat points; every trial keeps each point once.
    assert w.counts.max() <= 95
    assert w.counts.mean() < 82.5
    for a in range(300):
        real = pts[a][w.mask[a]]
        assert np.unique(real, axis=0).shape[0] == real.shape[0]
        assert np.unique(pts[a][: int(w.mask[a].nonzero()[0].max()) + 1], axis=0).shape[0] == real.shape[0]
