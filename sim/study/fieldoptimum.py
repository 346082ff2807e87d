"""The full-knowledge optimum on the random study fields (``apf-sim study --optimum``).

The optimum is computed on a sample: the first ``n_fields`` fields of each density (trials 0.., chunk by
chunk, exactly the fields the study's trials ran on: ``chunk_worlds`` regenerates them from the seed), about
0.1 s per field at 0.1 m (``sim.study.optimal``). Each planner's mean path is compared with the optimum on the
same fields: path/A* is the mean over those fields' successful trials of (flown path / optimum to the goal
circle).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from sim.study.config import Density, StudyConfig
from sim.study.engine import CellResult, ChunkTask, chunk_worlds
from sim.study.metrics import Outcome
from sim.study.optimal import optimal_path_points
from sim.study.worldstudy import optimum_to_goal_circle

__all__ = ["FieldOptimumTask", "field_optimum_table", "field_optimum_tasks", "run_field_optimum"]


@dataclass(frozen=True, slots=True, kw_only=True)
class FieldOptimumTask:
    """The optimum on trials [first, first + n_trials) of one chunk of one density (picklable)."""

    config: StudyConfig
    density: Density
    chunk_index: int
    first: int
    n_trials: int
    chunk_trials: int
    seed: int
    clearance_m: float
    resolution_m: float


def field_optimum_tasks(
    config: StudyConfig,
    densities: Sequence[Density],
    n_fields: int,
    trials: int,
    seed: int,
    *,
    clearance_m: float,
    resolution_m: float,
    block: int = 25,
) -> list[FieldOptimumTask]:
    """Blocks of ``block`` fields covering the first ``min(n_fields, trials)`` trials of each density."""
    n = min(n_fields, trials)
    tasks = []
    for density in densities:
        start = 0
        while start < n:
            chunk, first = divmod(start, config.chunk_trials)
            size = min(block, n - start, config.chunk_trials - first)
            start += size
            chunk_size = min(config.chunk_trials, trials - chunk * config.chunk_trials)
            tasks.append(
                FieldOptimumTask(
                    config=config,
                    density=density,
                    chunk_index=chunk,
                    first=first,
                    n_trials=size,
                    chunk_trials=chunk_size,
                    seed=seed,
                    clearance_m=clearance_m,
                    resolution_m=resolution_m,
                )
            )
    return tasks


def run_field_optimum(task: FieldOptimumTask) -> np.ndarray:
    """(n_trials,) optimum length start -> target [m] on the task's fields (inf: no path)."""
    cfg = task.config
    worlds = chunk_worlds(
        ChunkTask(
            config=cfg,
            planner_name="",
            density=task.density,
            chunk_index=task.chunk_index,
            n_trials=task.chunk_trials,
            seed=task.seed,
        )
    )
    out = np.full(task.n_trials, np.inf)
    for k in range(task.n_trials):
        a = task.first + k
        pts = worlds.obstacles_m[a][worlds.mask[a]]
        opt = optimal_path_points(
            pts, cfg.start_m, cfg.target_m, clearance_m=task.clearance_m, resolution_m=task.resolution_m
        )
        out[k] = opt.length_m
    return out


def collect_optima(tasks: Sequence[FieldOptimumTask], results: Sequence[np.ndarray]) -> dict[Density, np.ndarray]:
    """Per density, the optima of its sampled fields in trial order."""
    out: dict[Density, list[np.ndarray]] = {}
    for task, res in zip(tasks, results, strict=True):
        out.setdefault(task.density, []).append(res)
    return {d: np.concatenate(parts) for d, parts in out.items()}


def field_optimum_table(cells: Sequence[CellResult], optima: dict[Density, np.ndarray], goal_radius_m: float) -> str:
    """Per (planner, density): the optimum on the sampled fields beside the planner's path on the same fields."""
    head = (
        "| planner | N | fields | A* to goal circle, mean (m) | no path | successes on them | "
        "mean path (m) | A* on those (m) | path/A* (mean ratio) |"
    )
    lines = [head, "|" + "---|" * 9]
    for cell in cells:
        opt = optima.get(cell.density)
        if opt is None:
            continue
        n = opt.size
        target = np.array([optimum_to_goal_circle(float(x), goal_radius_m) for x in opt])
        finite = np.isfinite(target)
        rec = cell.records
        ok = (rec.outcome[:n] == Outcome.SUCCESS) & finite
        path = rec.path_m[:n] if rec.path_m is not None else np.full(n, np.nan)
        mean_opt = float(target[finite].mean()) if finite.any() else math.nan
        if ok.any():
            ratio = f"{float(np.mean(path[ok] / target[ok])):.3f}"
            mp, mo = f"{float(path[ok].mean()):.2f}", f"{float(target[ok].mean()):.2f}"
        else:
            ratio = mp = mo = "–"
        lines.append(
            f"| {cell.planner_name} | {cell.density.label} | {n} | {mean_opt:.2f} | {int((~finite).sum())} | "
            f"{int(ok.sum())} | {mp} | {mo} | {ratio} |"
        )
    return "\n".join(lines)
