"""``apf-sim sweep``: the grid from the params dataclass, path lengths, agreement with the study, outputs."""

from __future__ import annotations

import argparse
import csv
import dataclasses
import json
from pathlib import Path

import numpy as np
import pytest

from apf_companion.errors import ConfigError
from apf_companion.planning import PlannerParams, RandomWalkRule
from sim.study.cli import eta_text
from sim.study.config import Density, StudyConfig
from sim.study.engine import Trace, run_tasks
from sim.study.worldstudy import WorldCase, load_case, run_world_study, without_area
from sim.sweep import path_lengths, plan_sweep, point_config, run_sweep, scenario_label
from sim.sweep_cli import register
from sim.sweep_grid import grid_points, parse_params, resolve_name, sweepable_fields


def _run(argv: list[str]) -> int:
    parser = argparse.ArgumentParser()
    sub = parser.add_subparsers(dest="command", required=True)
    register(sub)
    args = parser.parse_args(["sweep", *argv])
    code: int = args.func(args)
    return code


FIELDS = sweepable_fields(PlannerParams)


@pytest.mark.parametrize(
    ("name", "field"),
    [
        ("mu_o", "mu_o_per_m2"),
        ("rho_l", "rho_l_m"),
        ("rho_u", "rho_u_m"),
        ("N_b", "n_bacteria"),
        ("step", "step_m"),
        ("mu_o_per_m2", "mu_o_per_m2"),
        ("random_walk", "random_walk"),
    ],
)
def test_paper_names_resolve_to_fields(name: str, field: str) -> None:
    assert resolve_name(name, FIELDS) == field


def test_a_field_a_new_planner_adds_is_sweepable() -> None:
    @dataclasses.dataclass(frozen=True)
    class ProductParams:
        margin_m: float = 0.3
        gain: float = 1.0
        name: str = "x"  # not a number: not sweepable

    fields = sweepable_fields(ProductParams())
    assert fields == {"margin_m": float, "gain": float}
    with pytest.raises(ConfigError, match=r"'margin' is ambiguous \(margin_m, margin_s\)"):
        resolve_name("margin", {"margin_m": float, "margin_s": float})
    (p,) = parse_params(["margin=0.2,0.5"], ProductParams())
    assert (p.field, p.values) == ("margin_m", (0.2, 0.5))


def test_values_lists_ranges_ints_and_enums() -> None:
    swept = parse_params(
        ["mu_o=100,1000", "step=0.2:0.6:3", "N_b=30:60:4", "random_walk=safe-set,single-draw"], PlannerParams()
    )
    assert [p.values for p in swept] == [
        (100.0, 1000.0),
        (0.2, 0.4, 0.6),
        (30, 40, 50, 60),
        (RandomWalkRule.SAFE_SET, RandomWalkRule.SINGLE_DRAW),
    ]
    assert isinstance(swept[2].values[0], int)
    points = grid_points(swept[:2])
    assert points[:2] == [{"mu_o_per_m2": 100.0, "step_m": 0.2}, {"mu_o_per_m2": 100.0, "step_m": 0.4}]
    assert len(points) == 6


def test_all_grid_errors_reported_at_once() -> None:
    with pytest.raises(ConfigError) as err:
        parse_params(["mu=1,2", "bogus=1", "N_b=a,b", "rho_l=0.1", "rho_l=0.2", "step"], PlannerParams())
    text = str(err.value)
    assert "unknown parameter 'mu'; sweepable: alpha_t, mu_t_per_m2" in text
    assert "unknown parameter 'bogus'" in text
    assert "values of n_bacteria must be int" in text
    assert "rho_l_m given twice" in text
    assert "expects NAME=V1,V2,... or NAME=LOW:HIGH:N, got 'step'" in text


def test_invalid_grid_points_are_refused_before_running() -> None:
    config = StudyConfig.reference()
    swept = parse_params(["rho_l=0.4,5.0", "rho_u=4.5,5.0"], config.planner_params)
    with pytest.raises(ConfigError, match="invalid grid points") as err:
        plan_sweep(config, ("cr-bapf*",), swept, (Density(n_low=20, n_high=45),), 5, 0)
    text = str(err.value)
    assert "{'rho_l_m': 5.0, 'rho_u_m': 4.5}" in text
    assert "{'rho_l_m': 5.0, 'rho_u_m': 5.0}" in text
    assert "'rho_l_m': 0.4" not in text


def test_path_length_sums_the_segments_of_each_trial_until_it_ends() -> None:
    nan = np.nan
    pos = np.array(
        [
            [[0.0, 0.0], [0.0, 0.0]],
            [[3.0, 4.0], [1.0, 0.0]],
            [[3.0, 4.0], [nan, nan]],  # trial 0 did not move; trial 1 ended
            [[3.0, 5.0], [nan, nan]],
        ]
    )
    trace = Trace(positions_m=pos, reason=np.zeros((4, 2), np.int8), mu_o_k=np.zeros((4, 2)))
    np.testing.assert_allclose(path_lengths(trace), [6.0, 1.0])


def test_cells_count_the_outcomes_of_the_study_with_the_same_parameters() -> None:
    config = dataclasses.replace(StudyConfig.reference(), chunk_trials=8)
    density = Density(n_low=45, n_high=70)
    swept = parse_params(["rho_l=0.3,0.5"], config.planner_params)
    plan = plan_sweep(config, ("bapf", "cr-bapf*"), swept, (density,), 12, 3)
    cells = run_sweep(plan)
    assert len(cells) == 4
    for cell in cells:
        from sim.study.engine import make_tasks

        study = run_tasks(make_tasks(point_config(config, cell.point), (cell.planner_name,), (density,), 12, 3))
        outcomes = np.concatenate([r.records.outcome for r in study])
        np.testing.assert_array_equal(cell.records.outcome, outcomes)
        ok = cell.records.outcome == 0
        # A successful path is at least the straight line from the start into the goal circle.
        straight = np.hypot(19.0, 19.0) - config.goal_radius_m - 0.5  # 0.5: position noise slack
        assert (cell.path_length_m[ok] >= straight).all()


def test_cli_writes_table_csv_json_and_heatmaps(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    out = tmp_path / "sweep"
    argv = [
        "--param", "mu_o=100,1000", "--param", "N_b=30,60", "--densities", "20-45,70-95",
        "--planners", "bapf,cr-bapf*", "--trials", "3", "--workers", "1", "--seed", "2", "--out", str(out),
    ]  # fmt: skip
    assert _run(argv) == 0
    stdout, stderr = capsys.readouterr()
    assert "| cr-bapf* | mu_o_per_m2=1000 n_bacteria=60 | 70-95 | 3 |" in stdout
    assert "48/48 trials" in stderr  # 2 planners x 4 points x 2 densities x 3 trials
    with (out / "sweep.csv").open() as fh:
        rows = list(csv.DictReader(fh))
    assert len(rows) == 16
    assert list(rows[0])[:6] == ["planner", "world", "n_low", "n_high", "mu_o_per_m2", "n_bacteria"]
    assert {r["world"] for r in rows} == {""}
    assert {r["n_bacteria"] for r in rows} == {"30", "60"}
    doc = json.loads((out / "sweep.json").read_text())
    assert doc["grid"] == [
        {"field": "mu_o_per_m2", "values": ["100", "1000"]},
        {"field": "n_bacteria", "values": ["30", "60"]},
    ]
    assert doc["executor"] == {"kind": "processes", "workers": 1, "address": ""}
    for csv_row, json_row in zip(rows, doc["rows"], strict=True):
        assert float(csv_row["R_s"]) == pytest.approx(json_row["R_s"])
        assert (
            int(csv_row["success"]) + int(csv_row["collision"]) + int(csv_row["stuck"]) + int(csv_row["timeout"]) == 3
        )
    for name in ("heatmap_bapf.png", "heatmap_cr-bapf-star.png"):
        assert (out / name).read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


def test_world_cells_are_the_world_studys_trials() -> None:
    config = dataclasses.replace(StudyConfig.reference(), chunk_trials=3)
    cases = (load_case("corridor-bend"), load_case("forest"))
    swept = parse_params(["rho_l=0.3,0.5"], config.planner_params)
    plan = plan_sweep(config, ("cr-bapf*",), swept, (Density(n_low=45, n_high=70), *cases), 5, 4)
    cells = run_sweep(plan)
    assert [scenario_label(c.scenario) for c in cells] == ["N 45-70", "corridor-bend", "forest"] * 2
    world_cells = [c for c in cells if isinstance(c.scenario, WorldCase)]
    for cell in world_cells:
        assert isinstance(cell.scenario, WorldCase)
        cfg = point_config(config, cell.point)
        (study,) = run_world_study(cfg, (cell.planner_name,), (cell.scenario,), 5, 4)
        np.testing.assert_array_equal(cell.records.outcome, study.records.outcome)
        np.testing.assert_array_equal(cell.records.clearance_m, study.records.clearance_m)  # the true geometry's
        np.testing.assert_array_equal(cell.path_length_m, study.records.path_m)
    # The grid point reaches the planner: the same noise streams, other paths.
    low, high = (c for c in world_cells if scenario_label(c.scenario) == "corridor-bend")
    assert (low.point, high.point) == ({"rho_l_m": 0.3}, {"rho_l_m": 0.5})
    assert not np.array_equal(low.path_length_m, high.path_length_m)


def test_a_world_s_flying_area_replaces_the_grid_it_would_sweep(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """wall-gap gives bapf-nav its arena as the flying area, whose grid replaces ``nav_grid_m``: sweeping that
    changes nothing there, and ``--no-area`` (here: the case without its area) makes it count."""
    config = dataclasses.replace(StudyConfig.reference(), chunk_trials=3)
    case = load_case("wall-gap")
    bare = without_area(case)
    swept = parse_params(["nav_grid_m=12,20"], config.planner_params)
    paths = {}
    for scenario in (case, bare):  # one world per sweep: the label keys its seeds and rows
        for c in run_sweep(plan_sweep(config, ("bapf-nav",), swept, (scenario,), 3, 0)):
            paths[c.point["nav_grid_m"], scenario is case] = c.path_length_m
    np.testing.assert_array_equal(paths[12.0, True], paths[20.0, True])
    assert not np.array_equal(paths[12.0, False], paths[20.0, False])
    argv = ["--param", "nav_grid_m=12,20", "--worlds", "wall-gap", "--planners", "bapf-nav", "--trials", "1",
            "--workers", "1", "--no-area", "--out", str(tmp_path / "sweep")]  # fmt: skip
    assert _run(argv) == 0
    assert "| bapf-nav | nav_grid_m=20 | wall-gap | 1 |" in capsys.readouterr().out


def test_cli_sweeps_worlds_instead_of_densities(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    out = tmp_path / "sweep"
    argv = ["--param", "rho_l=0.3,0.5", "--worlds", "corridor-bend, forest", "--trials", "2", "--workers", "1",
            "--out", str(out)]  # fmt: skip
    assert _run(argv) == 0
    stdout, stderr = capsys.readouterr()
    assert "| cr-bapf* | rho_l_m=0.5 | forest | 2 |" in stdout
    assert "8/8 trials" in stderr  # 2 points x 2 worlds x 2 trials: no densities unless asked for
    with (out / "sweep.csv").open() as fh:
        rows = list(csv.DictReader(fh))
    assert [(r["world"], r["n_low"], r["rho_l_m"]) for r in rows] == [
        ("corridor-bend", "", "0.3"),
        ("forest", "", "0.3"),
        ("corridor-bend", "", "0.5"),
        ("forest", "", "0.5"),
    ]
    doc = json.loads((out / "sweep.json").read_text())
    assert doc["schema"] == 2
    assert [(r["world"], r["n_low"], r["n_high"]) for r in doc["rows"][:2]] == [
        ("corridor-bend", None, None),
        ("forest", None, None),
    ]
    assert (out / "heatmap_cr-bapf-star.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


def test_world_axis_errors(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    base = ["--param", "rho_l=0.3", "--trials", "1", "--workers", "1", "--out", str(tmp_path)]
    assert _run([*base, "--worlds", "no-such-world,missing.toml"]) == 2
    err = capsys.readouterr().err
    assert "no example world 'no-such-world'" in err
    assert "cannot read world file missing.toml" in err
    assert _run([*base, "--worlds", "forest,forest"]) == 2
    assert "each density and world must appear once" in capsys.readouterr().err
    assert _run([*base, "--densities", ","]) == 2
    assert "no densities and no worlds" in capsys.readouterr().err
    assert _run([*base, "--worlds", "forest", "--surface-spacing", "0"]) == 2
    assert "--surface-spacing: need > 0" in capsys.readouterr().err
    assert not any(tmp_path.iterdir())
    config_3d = dataclasses.replace(
        StudyConfig.reference(),
        planner_params=PlannerParams.reference(dim=3),
        start_m=(3.0, 3.0, 3.0),
        target_m=(22.0, 22.0, 22.0),
    )
    swept = parse_params(["rho_l=0.3"], config_3d.planner_params)
    with pytest.raises(ConfigError, match="world files are 2D"):
        plan_sweep(config_3d, ("cr-bapf*",), swept, (load_case("forest"),), 1, 0)


def test_cli_errors(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    assert _run(["--out", str(tmp_path)]) == 2
    assert "give at least one --param" in capsys.readouterr().err
    assert _run(["--param", "rho_l=9", "--out", str(tmp_path)]) == 2
    assert "invalid grid points" in capsys.readouterr().err
    assert not any(tmp_path.iterdir())


def test_list_params(capsys: pytest.CaptureFixture[str]) -> None:
    assert _run(["--list-params"]) == 0
    out = capsys.readouterr().out
    assert "mu_o_per_m2      float           1000" in out
    assert "n_bacteria       int             60" in out


def test_progress_eta() -> None:
    assert eta_text(0, 100, 5.0) == ""
    assert eta_text(25, 100, 5.0) == " ETA 15 s"
    assert eta_text(10, 100, 60.0) == " ETA 9.0 min"
    assert eta_text(100, 100, 60.0) == ""
