"""``apf-sim study`` end to end (in-process, one worker): table, JSON schema, CSV, figures, errors."""

from __future__ import annotations

import argparse
import csv
import json
from pathlib import Path

import numpy as np
import pytest

from sim.study.cli import register


def _run(argv: list[str]) -> int:
    parser = argparse.ArgumentParser()
    sub = parser.add_subparsers(dest="command", required=True)
    register(sub)
    args = parser.parse_args(["study", *argv])
    code: int = args.func(args)
    return code


def test_json_schema_csv_and_table(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    out_json = tmp_path / "s.json"
    out_csv = tmp_path / "s.csv"
    code = _run(
        [
            "--trials", "30", "--densities", "20-45,70-95", "--planners", "bapf,cr-bapf*",
            "--workers", "1", "--seed", "4", "--chunk-trials", "20",
            "--json", str(out_json), "--csv", str(out_csv),
        ]
    )  # fmt: skip
    assert code == 0
    out, err = capsys.readouterr()
    assert "| cr-bapf* | 20-45 | 30 |" in out
    assert "0.935" in out  # the paper's value beside ours
    assert "120/120 trials" in err  # progress bar on stderr (4 cells x 30 trials)

    doc = json.loads(out_json.read_text())
    assert doc["schema"] == 1
    assert doc["preset"] == "reference"
    assert doc["seed"] == 4
    assert doc["trials_per_cell"] == 30
    assert doc["rules"]["detection"] == "cumulative"
    assert doc["rules"]["random_walk"] == "single-draw"
    results = doc["results"]
    assert [(r["planner"], r["density"]) for r in results] == [
        ("bapf", [20, 45]),
        ("bapf", [70, 95]),
        ("cr-bapf*", [20, 45]),
        ("cr-bapf*", [70, 95]),
    ]
    for r in results:
        assert set(r) == {"planner", "density", "trials", "R_s", "R_s_ci95", "M_s", "S", "T_a_ms", "counts", "paper"}
        assert r["trials"] == 30
        assert sum(r["counts"].values()) == 30
        assert r["R_s"] == pytest.approx(r["counts"]["success"] / 30)
        lo, hi = r["R_s_ci95"]
        assert 0.0 <= lo <= r["R_s"] <= hi <= 1.0
        assert r["T_a_ms"] > 0.0
        assert r["paper"]["R_s"] > 0.0
    assert doc["mu_sweep"] == []

    with out_csv.open() as fh:
        rows = list(csv.DictReader(fh))
    assert len(rows) == 4 * 30
    assert {row["outcome"] for row in rows} <= {"success", "collision", "stuck", "timeout"}
    first = [row for row in rows if row["planner"] == "bapf" and row["n_low"] == "20"]
    assert sum(row["outcome"] == "success" for row in first) == results[0]["counts"]["success"]
    # Per-trial times split the chunk time by iterations; their mean is the cell's T_a.
    assert sum(float(row["time_ms"]) for row in first) / 30 == pytest.approx(results[0]["T_a_ms"], rel=1e-3)
    long_trial = max(first, key=lambda row: int(row["iterations"]))
    short_trial = min(first, key=lambda row: int(row["iterations"]))
    assert float(long_trial["time_ms"]) >= float(short_trial["time_ms"])


def test_mu_sweep_and_plots(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    plots = tmp_path / "plots"
    out_json = tmp_path / "s.json"
    code = _run(
        [
            "--trials", "10", "--densities", "45-70", "--planners", "cr-bapf*", "--workers", "1",
            "--mu-sweep", "--mu-trials", "8", "--json", str(out_json), "--plots", str(plots), "--no-progress",
        ]
    )  # fmt: skip
    assert code == 0
    out, err = capsys.readouterr()
    assert "R_s versus mu_o" in out
    assert err.count("trials") == 0  # --no-progress
    doc = json.loads(out_json.read_text())
    sweep = doc["mu_sweep"]
    assert [s["mu_o_per_m2"] for s in sweep][:2] == [1.0, pytest.approx(1000.0 / 12.0)]
    assert len(sweep) == 13
    assert {r["planner"] for s in sweep for r in s["results"]} == {"bapf", "cr-bapf*"}
    for name in ("rs_per_planner.png", "rs_vs_mu.png", "abapf_mu.png"):
        assert (plots / name).stat().st_size > 1000
        assert (plots / name).read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


def test_bad_arguments_exit_2(capsys: pytest.CaptureFixture[str]) -> None:
    assert _run(["--planners", "nope", "--trials", "1", "--workers", "1"]) == 2
    assert "nope" in capsys.readouterr().err
    assert _run(["--densities", "9-3", "--trials", "1", "--workers", "1"]) == 2


@pytest.mark.parametrize("flag", ["--noise-std", "--noise"])
def test_noise_and_noise_std_are_one_option(flag: str, capsys: pytest.CaptureFixture[str]) -> None:
    from sim.study.cli import _config

    parser = argparse.ArgumentParser()
    register(parser.add_subparsers(dest="command", required=True))
    args = parser.parse_args(["study", flag, "0.25"])
    assert args.noise_std == 0.25 and _config(args).noise_std_m == 0.25
    assert _run([flag, "-0.1", "--trials", "1", "--workers", "1"]) == 2
    assert "--noise-std/--noise: need >= 0, got -0.1" in capsys.readouterr().err
    with pytest.raises(SystemExit):
        parser.parse_args(["study", "--help"])
    usage = " ".join(capsys.readouterr().out.split())
    assert "--noise-std M, --noise M" in usage and "--noise is the same option under another name" in usage


def test_abapf_rule_option_and_abapf_equals_bapf_at_mu_max(tmp_path: Path) -> None:
    docs = {}
    for rule in ("exact", "paper"):
        path = tmp_path / f"{rule}.json"
        argv = ["--trials", "25", "--densities", "45-70", "--planners", "a-bapf,bapf", "--workers", "1"]
        assert _run([*argv, "--abapf-rule", rule, "--json", str(path), "--no-progress"]) == 0
        docs[rule] = json.loads(path.read_text())
        assert docs[rule]["rules"]["abapf_rule"] == rule
    # J_k(mu) decreases in mu, so A-BAPF's point potentials are BAPF's at mu_o = mu_max (exact rule), or differ
    # from them by less than half an ulp of the target term (paper rule): the same decisions, the same outcomes.
    abapf_exact, bapf = docs["exact"]["results"]
    abapf_paper, _ = docs["paper"]["results"]
    assert abapf_exact["counts"] == bapf["counts"] == abapf_paper["counts"]
    assert abapf_exact["M_s"] == bapf["M_s"] == abapf_paper["M_s"]


def test_abapf_paper_rule_varies_mu_exact_rule_does_not() -> None:
    from sim.study.config import Density, StudyConfig
    from sim.study.plots import abapf_paper_rule_config, example_runs

    density = Density(n_low=45, n_high=70)
    exact = example_runs(StudyConfig.reference(), "a-bapf", density, seed=2, n_trials=6)
    paper = example_runs(abapf_paper_rule_config(StudyConfig.reference()), "a-bapf", density, seed=2, n_trials=6)
    mu_exact = exact.trace.mu_o_k[~np.isnan(exact.trace.mu_o_k)]
    mu_paper = paper.trace.mu_o_k[~np.isnan(paper.trace.mu_o_k)]
    assert set(np.unique(mu_exact)) <= {1.0, 1000.0}  # mu_min only while no obstacle is known
    assert np.unique(mu_paper).size > 20
    assert mu_paper.min() >= 1.0
    assert mu_paper.max() <= 1000.0
