"""The study over world files (``apf-sim study --world FILE|NAME``): any planner, the study's rules, true geometry.

What the planners see: the walls and cylinders as obstacle points, samples of their true surfaces every
``spacing_m`` (default 0.2 m = the perception memory's merge radius, see ``sim.world.geometry``), known under the
study's detection rule (within ``sensor_range_m``; cumulative or in range, by preset). What judges them: the TRUE
geometry. A trial collides when a move passes closer than ``collision_radius_m`` to a wall capsule or cylinder
surface (swept along the straight move, so a 0.4 m step cannot tunnel through a 0.2 m wall; the paper's point
rule checks only where each iteration starts), and its clearance is the smallest such distance along its path. Start and
goal are the world file's; noise, goal radius, iteration cap and stop rules are the preset's.

Determinism: each (world, chunk) has its own motion generator, ``SeedSequence(seed, spawn_key=(WORLD_KEY,
crc32(world name), chunk))``, so the table does not depend on the number of workers, and every planner sees the
same noise streams (common random numbers). The random-field study's streams are untouched.
"""

from __future__ import annotations

import dataclasses
import functools
import math
import time
import zlib
from collections.abc import Sequence
from concurrent.futures import Executor
from dataclasses import dataclass
from pathlib import Path
from typing import TypeVar

import numpy as np

from sim.study.config import StudyConfig
from sim.study.engine import ProgressFn, map_tasks, simulate
from sim.study.metrics import Outcome, TrialRecords, summarize
from sim.study.optimal import DEFAULT_CLEARANCE_M, DEFAULT_RESOLUTION_M, optimal_path
from sim.study.worlds import WorldBatch
from sim.world import World, load_world
from sim.world.geometry import SURFACE_SPACING_M, segment_clearance_m, surface_samples_ne_m

__all__ = [
    "WORLD_KEY",
    "WorldCase",
    "WorldCell",
    "WorldTask",
    "load_case",
    "make_world_tasks",
    "run_world_chunk",
    "run_world_study",
    "without_area",
    "world_table",
]

WORLD_KEY = 0x574F524C  # "WORL": first spawn-key word of world chunks (density chunks use (N_l, N_u, c))

_T = TypeVar("_T")
_R = TypeVar("_R")


@dataclass(frozen=True, slots=True, kw_only=True)
class WorldCase:
    """One world file, ready for the study."""

    label: str
    """The name it was given on the command line (file path or bundled name)."""
    world: World
    samples_ne_m: np.ndarray
    """(K, 2) the surface samples the planners see [m]."""
    optimum_m: float
    """Full-knowledge grid optimum start -> goal at the optimum's clearance [m] (inf: none), inside the world's
    flying area and outside its keep-out zones."""
    optimum_clearance_m: float = DEFAULT_CLEARANCE_M
    optimum_resolution_m: float = DEFAULT_RESOLUTION_M


def load_case(
    name: str,
    *,
    spacing_m: float = SURFACE_SPACING_M,
    optimum_clearance_m: float = DEFAULT_CLEARANCE_M,
    optimum_resolution_m: float = DEFAULT_RESOLUTION_M,
) -> WorldCase:
    """Load a world (file or bundled name), sample its surfaces and compute its optimum."""
    world = load_world(name)
    if world.start_ne_m is None or world.goal_ne_m is None:
        from apf_companion.errors import ConfigError

        msg = f"world {name!r}: the study needs start_ne_m and goal_ne_m in the world file"
        raise ConfigError(msg)
    opt = optimal_path(world, clearance_m=optimum_clearance_m, resolution_m=optimum_resolution_m)
    label = Path(name).stem if Path(name).suffix else name
    return WorldCase(
        label=label,
        world=world,
        samples_ne_m=surface_samples_ne_m(world, spacing_m),
        optimum_m=opt.length_m,
        optimum_clearance_m=optimum_clearance_m,
        optimum_resolution_m=optimum_resolution_m,
    )


def without_area(case: WorldCase) -> WorldCase:
    """The case without its world file's flying area and keep-out zones (``--no-area``): bapf-nav's grid then moves
    with the agent, and the optimum may leave the area too."""
    if case.world.area_ne_m is None and not case.world.keepouts_ne_m:
        return case
    world = dataclasses.replace(case.world, area_ne_m=None, keepouts_ne_m=())
    opt = optimal_path(world, clearance_m=case.optimum_clearance_m, resolution_m=case.optimum_resolution_m)
    return dataclasses.replace(case, world=world, optimum_m=opt.length_m)


@dataclass(frozen=True, slots=True, kw_only=True)
class WorldTask:
    """One fixed, seeded chunk of trials on one world (picklable)."""

    config: StudyConfig
    planner_name: str
    case: WorldCase
    chunk_index: int
    n_trials: int
    seed: int


@dataclass(frozen=True, slots=True, kw_only=True)
class WorldChunkResult:
    task: WorldTask
    records: TrialRecords
    wall_s: float


def world_config(config: StudyConfig, world: World) -> StudyConfig:
    """The study's rules with the world's start and goal (2D), and its flying area and keep-out zones, if it has
    them, as bapf-nav's ``nav_area_ne_m`` and ``nav_keepout_ne_m`` (the other planners do not read them)."""
    assert world.start_ne_m is not None and world.goal_ne_m is not None
    params = config.planner_params
    if world.area_ne_m is not None:
        params = dataclasses.replace(params, nav_area_ne_m=world.area_ne_m)
    if world.keepouts_ne_m:
        params = dataclasses.replace(params, nav_keepout_ne_m=world.keepouts_ne_m)
    return dataclasses.replace(
        config, start_m=tuple(world.start_ne_m), target_m=tuple(world.goal_ne_m), planner_params=params
    )


def motion_generator(seed: int, label: str, chunk_index: int) -> np.random.Generator:
    key = (WORLD_KEY, zlib.crc32(label.encode()), chunk_index)
    return np.random.default_rng(np.random.SeedSequence(seed, spawn_key=key))


def run_world_chunk(task: WorldTask) -> WorldChunkResult:
    """Run one chunk of trials on one world (top-level so process pools can pickle it)."""
    t0 = time.perf_counter()
    case = task.case
    samples = case.samples_ne_m
    batch = WorldBatch(
        obstacles_m=np.broadcast_to(samples, (task.n_trials, *samples.shape)).copy(),
        mask=np.ones((task.n_trials, samples.shape[0]), dtype=bool),
    )
    world = case.world

    def clearance(from_ne_m: np.ndarray, to_ne_m: np.ndarray) -> np.ndarray:
        return segment_clearance_m(world, from_ne_m, to_ne_m)

    cfg = world_config(task.config, world)
    rng = motion_generator(task.seed, case.label, task.chunk_index)
    result = simulate(cfg, task.planner_name, batch, rng, clearance=clearance)
    return WorldChunkResult(task=task, records=result.records, wall_s=time.perf_counter() - t0)


def make_world_tasks(
    config: StudyConfig, planners: Sequence[str], cases: Sequence[WorldCase], trials: int, seed: int
) -> list[WorldTask]:
    """``trials`` per (planner, world), in fixed chunks of ``config.chunk_trials``."""
    return [
        WorldTask(
            config=config,
            planner_name=name,
            case=case,
            chunk_index=c,
            n_trials=min(config.chunk_trials, trials - start),
            seed=seed,
        )
        for name in planners
        for case in cases
        for c, start in enumerate(range(0, trials, config.chunk_trials))
    ]


@dataclass(frozen=True, slots=True, kw_only=True)
class WorldCell:
    """All trials of one (planner, world), chunks in order."""

    planner_name: str
    case: WorldCase
    records: TrialRecords
    wall_s: float


def run_world_study(
    config: StudyConfig,
    planners: Sequence[str],
    cases: Sequence[WorldCase],
    trials: int,
    seed: int,
    executor: Executor | None = None,
    *,
    workers: int | None = None,
    progress: ProgressFn | None = None,
) -> list[WorldCell]:
    """``trials`` per (planner, world); one ``WorldCell`` each, planners outer, worlds inner."""
    tasks = make_world_tasks(config, planners, cases, trials, seed)
    results = map_tasks(run_world_chunk, tasks, executor, workers=workers, progress=progress)
    groups: dict[tuple[str, str], list[WorldChunkResult]] = {}
    for r in results:
        groups.setdefault((r.task.planner_name, r.task.case.label), []).append(r)
    cells = []
    for parts in groups.values():
        parts.sort(key=lambda r: r.task.chunk_index)
        cells.append(
            WorldCell(
                planner_name=parts[0].task.planner_name,
                case=parts[0].task.case,
                records=TrialRecords.concat([p.records for p in parts]),
                wall_s=sum(p.wall_s for p in parts),
            )
        )
    return cells


def _fmt(x: float, digits: int) -> str:
    return "–" if math.isnan(x) or math.isinf(x) else f"{x:.{digits}f}"


def _lowest(values: np.ndarray | None, pick: np.ndarray) -> float:
    if values is None or not pick.any():
        return math.nan
    return float(values[pick].min())


def cell_summary(cell: WorldCell, goal_radius_m: float) -> dict[str, object]:
    """The row of one (planner, world) as a JSON-ready dict (see ``world_table`` for the columns)."""
    s = summarize(cell.records)
    rec = cell.records
    ok = rec.outcome == Outcome.SUCCESS
    mean_path = float(rec.path_m[ok].mean()) if rec.path_m is not None and ok.any() else math.nan
    optimum = optimum_to_goal_circle(cell.case.optimum_m, goal_radius_m)
    out: dict[str, object] = {"planner": cell.planner_name, "world": cell.case.label}
    out.update(s.to_json())
    out.update(
        {
            "mean_path_m": None if math.isnan(mean_path) else mean_path,
            "optimum_m": optimum if math.isfinite(optimum) else None,
            "path_over_optimum": mean_path / optimum if math.isfinite(optimum) and ok.any() else None,
            "min_clearance_m": _nan_none(_lowest(rec.clearance_m, np.ones(len(rec), dtype=bool))),
            "min_clearance_success_m": _nan_none(_lowest(rec.clearance_m, ok)),
            "clearance_quantiles_m": _quantiles(rec.clearance_m),
            "surface_samples": int(cell.case.samples_ne_m.shape[0]),
        }
    )
    return out


def _quantiles(values: np.ndarray | None) -> dict[str, float] | None:
    """1st, 5th and 50th percentile of the trials' own lowest clearances: how often a trial comes close, where the
    minimum over all trials only says how close the worst one came (with Gaussian noise it falls with the count)."""
    if values is None or len(values) == 0:
        return None
    finite = values[np.isfinite(values)]
    if finite.size == 0:
        return None
    q = np.percentile(finite, [1.0, 5.0, 50.0])
    return {"p01": float(q[0]), "p05": float(q[1]), "p50": float(q[2])}


def _num(row: dict[str, object], key: str, digits: int) -> str:
    v = row[key]
    return "–" if not isinstance(v, float) else f"{v:.{digits}f}"


def _nan_none(x: float) -> float | None:
    return None if math.isnan(x) else x


def optimum_to_goal_circle(optimum_m: float, goal_radius_m: float) -> float:
    """The optimum to the goal circle (where a trial ends): the A* length to the goal less the goal radius
    (exact when the path's last straight segment is at least that long, as in every bundled world)."""
    return optimum_m - goal_radius_m if math.isfinite(optimum_m) else math.inf


def world_table(cells: Sequence[WorldCell], goal_radius_m: float) -> str:
    """One row per (planner, world): R_s, outcome counts, mean path (successes) beside the A* optimum to the
    goal circle and their ratio, the lowest clearance to the true geometry over all trials and over successes."""
    head = (
        "| planner | world | trials | R_s [95% CI] | success/collision/stuck/timeout | mean path (m) | A* (m) | "
        "path/A* | min clearance, all (m) | min clearance, successes (m) |"
    )
    lines = [head, "|" + "---|" * 10]
    for cell in cells:
        row = cell_summary(cell, goal_radius_m)
        lo, hi = summarize(cell.records).R_s_ci95
        counts = row["counts"]
        assert isinstance(counts, dict)
        num = functools.partial(_num, row)
        lines.append(
            f"| {cell.planner_name} | {cell.case.label} | {row['trials']} | {row['R_s']:.3f} [{lo:.3f}, {hi:.3f}] | "
            f"{counts['success']}/{counts['collision']}/{counts['stuck']}/{counts['timeout']} | "
            f"{num('mean_path_m', 2)} | {num('optimum_m', 2)} | {num('path_over_optimum', 3)} | "
            f"{num('min_clearance_m', 3)} | {num('min_clearance_success_m', 3)} |"
        )
    return "\n".join(lines)
