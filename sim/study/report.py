"""Study output: the markdown table beside the paper's values, the JSON summary and per-trial CSV."""

from __future__ import annotations

import csv
import json
import math
from collections.abc import Sequence
from pathlib import Path

from sim.study.config import StudyConfig
from sim.study.engine import CellResult
from sim.study.metrics import Outcome, Summary, summarize
from sim.study.paper import PAPER_ABAPF_R_S_LOWER_BOUND, paper_row

JSON_SCHEMA_VERSION = 1


def _fmt(x: float | None, digits: int) -> str:
    if x is None or math.isnan(x):
        return "–"
    return f"{x:.{digits}f}"


def markdown_table(cells: Sequence[CellResult]) -> str:
    """One row per (planner, density): ours next to the paper's Table II (``–`` where the paper has none)."""
    head = (
        "| planner | N | trials | R_s [95% CI] | paper R_s | M_s | paper M_s | S (m) | paper S | "
        "T_a (ms) | paper T_a | success/collision/stuck/timeout |"
    )
    rule = "|" + "---|" * 12
    lines = [head, rule]
    for cell in cells:
        s = summarize(cell.records)
        d = cell.density
        p = paper_row(cell.planner_name, d.n_low, d.n_high)
        paper_rs = _fmt(p.R_s, 3) if p else ""
        if p is None and cell.planner_name == "a-bapf":
            paper_rs = f"> {PAPER_ABAPF_R_S_LOWER_BOUND:.2f} (text)"
        lines.append(
            f"| {cell.planner_name} | {d.label} | {s.trials} | "
            f"{_fmt(s.R_s, 3)} [{s.R_s_ci95[0]:.3f}, {s.R_s_ci95[1]:.3f}] | {paper_rs or '–'} | "
            f"{_fmt(s.M_s, 2)} | {_fmt(p.M_s, 2) if p else '–'} | "
            f"{_fmt(s.S, 2)} | {_fmt(p.S_m, 2) if p else '–'} | "
            f"{_fmt(s.T_a_ms, 3)} | {_fmt(p.T_a_ms, 2) if p else '–'} | "
            f"{s.success}/{s.collision}/{s.stuck}/{s.timeout} |"
        )
    return "\n".join(lines)


def _cell_json(cell: CellResult, summary: Summary) -> dict[str, object]:
    d = cell.density
    out: dict[str, object] = {
        "planner": cell.planner_name,
        "density": [d.n_low, d.n_high],
    }
    out.update(summary.to_json())
    p = paper_row(cell.planner_name, d.n_low, d.n_high)
    out["paper"] = None if p is None else {"R_s": p.R_s, "M_s": p.M_s, "S": p.S_m, "T_a_ms": p.T_a_ms}
    return out


def study_json(
    config: StudyConfig,
    cells: Sequence[CellResult],
    *,
    seed: int,
    trials: int,
    wall_s: float,
    workers: int,
    mu_sweep: Sequence[tuple[float, Sequence[CellResult]]] = (),
) -> dict[str, object]:
    """The JSON document written by ``--json``: settings, one entry per (planner, density), the sweep."""
    params = config.planner_params
    return {
        "schema": JSON_SCHEMA_VERSION,
        "preset": config.preset,
        "seed": seed,
        "trials_per_cell": trials,
        "workers": workers,
        "wall_s": wall_s,
        "rules": {
            "obstacle_box_m": list(config.obstacle_box_m),
            "obstacle_sampling": config.obstacle_sampling.value,
            "detection": config.detection.value,
            "agent_repulsion": params.agent_repulsion,
            "random_walk": params.random_walk.value,
            "abapf_rule": params.abapf_rule.value,
            "alpha_t": params.alpha_t,
            "mu_o_per_m2": params.mu_o_per_m2,
            "start_m": list(config.start_m),
            "target_m": list(config.target_m),
            "sensor_range_m": config.sensor_range_m,
            "noise_std_m": config.noise_std_m,
            "collision_radius_m": config.collision_radius_m,
            "goal_radius_m": config.goal_radius_m,
            "max_iterations": config.max_iterations,
            "capf_patience": config.capf_patience,
            "chunk_trials": config.chunk_trials,
        },
        "results": [_cell_json(c, summarize(c.records)) for c in cells],
        "mu_sweep": [
            {"mu_o_per_m2": mu, "results": [_cell_json(c, summarize(c.records)) for c in sweep]}
            for mu, sweep in mu_sweep
        ],
    }


def write_json(path: Path, document: dict[str, object]) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps(document, indent=2, allow_nan=False) + "\n")


CSV_FIELDS = (
    "planner",
    "n_low",
    "n_high",
    "trial",
    "n_obstacles",
    "n_detected",
    "outcome",
    "iterations",
    "safety_m",
    "time_ms",
)


def write_csv(path: Path, cells: Sequence[CellResult]) -> None:
    """Per-trial records, one row per trial (trial = index within its (planner, density) cell)."""
    path.parent.mkdir(parents=True, exist_ok=True)
    with path.open("w", newline="") as fh:
        writer = csv.writer(fh)
        writer.writerow(CSV_FIELDS)
        for cell in cells:
            r = cell.records
            for i in range(len(r)):
                safety = float(r.safety_m[i])
                writer.writerow(
                    (
                        cell.planner_name,
                        cell.density.n_low,
                        cell.density.n_high,
                        i,
                        int(r.n_obstacles[i]),
                        int(r.n_detected[i]),
                        Outcome(int(r.outcome[i])).name.lower(),
                        int(r.iterations[i]),
                        "" if math.isnan(safety) else f"{safety:.6f}",
                        f"{float(r.time_ms[i]):.6f}",
                    )
                )
