"""Parameter sweeps on the study's engine: R_s and path length over a grid of planner parameters and scenarios.

A sweep cell is (planner, grid point, scenario). Each cell runs ``trials`` trials as the study's fixed seeded
chunks (``sim.study.engine.make_tasks``), so every grid point sees the same obstacle fields and noise streams
(common random numbers: differences between points are the parameters', not the draws'), and a cell's outcome
counts equal those of ``apf-sim study`` with the same parameters and seed. Chunks run on any
``concurrent.futures.Executor`` (the local process pool, or Dask with ``--dask``).

A scenario is an obstacle density (random fields) or a world (a ``WorldCase`` of ``apf-sim study --world``: a
bundled name or a TOML file). ``scenario_tasks`` is the one place that turns a scenario into chunk tasks: a density
into the study's ``ChunkTask``, a world into the world study's ``WorldTask`` (``sim.study.worldstudy``), so a world
cell is seeded, sampled and judged (collisions on the true geometry) exactly as ``apf-sim study --world``, and every
grid point sees the same noise streams on it.

Path length is measured per trial and averaged over successful trials, like M_s. On random fields it is the sum of
the distances between the recorded positions at the start of consecutive iterations (start to end, noise
included); on worlds it is the engine's own per-trial path (``TrialRecords.path_m``, the sum of the moves, noise
included), the world study's "mean path".
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Sequence
from concurrent.futures import Executor
from dataclasses import dataclass
from typing import Any

import numpy as np
import numpy.typing as npt

from apf_companion.errors import ConfigError
from sim.study.config import Density, StudyConfig
from sim.study.engine import (
    ChunkTask,
    ProgressFn,
    Trace,
    chunk_generators,
    chunk_worlds,
    make_tasks,
    map_tasks,
    simulate,
)
from sim.study.metrics import Outcome, Summary, TrialRecords, summarize
from sim.study.worldstudy import WorldCase, WorldTask, make_world_tasks, run_world_chunk
from sim.sweep_grid import ParamValue, SweepParam, grid_points

FloatArray = npt.NDArray[np.float64]

Scenario = Density | WorldCase
"""Where a cell's obstacles come from (see the module docstring)."""

SweepTask = ChunkTask | WorldTask


def scenario_label(scenario: Scenario) -> str:
    """``N 20-45`` for a density, the world's name (file stem or bundled name) for a world."""
    return f"N {scenario.label}" if isinstance(scenario, Density) else scenario.label


@dataclass(frozen=True, slots=True, kw_only=True)
class SweepChunkResult:
    task: SweepTask
    records: TrialRecords
    path_length_m: FloatArray
    """(A,) length of each trial's path [m]."""


def path_lengths(trace: Trace) -> FloatArray:
    """(A,) path length of every trial of a recorded batch [m] (rows after a trial's end are NaN)."""
    pos = trace.positions_m
    if pos.shape[0] < 2:
        return np.zeros(pos.shape[1])
    seg = np.diff(pos, axis=0)
    lengths = np.sqrt(np.einsum("tad,tad->ta", seg, seg))
    out: FloatArray = np.nansum(lengths, axis=0)
    return out


def run_sweep_chunk(task: SweepTask) -> SweepChunkResult:
    """One chunk with its path lengths (module level so process pools and Dask can pickle it).

    Random fields: the same worlds and motion streams as ``engine.run_chunk`` (recording the trace draws no random
    numbers). Worlds: ``worldstudy.run_world_chunk`` itself.
    """
    if isinstance(task, WorldTask):
        records = run_world_chunk(task).records
        assert records.path_m is not None  # simulate() always measures it
        return SweepChunkResult(task=task, records=records, path_length_m=records.path_m)
    worlds = chunk_worlds(task)
    _, motion_rng = chunk_generators(task.seed, task.density, task.chunk_index)
    result = simulate(task.config, task.planner_name, worlds, motion_rng, record=True)
    assert result.trace is not None  # record=True
    return SweepChunkResult(task=task, records=result.records, path_length_m=path_lengths(result.trace))


@dataclass(frozen=True, slots=True, kw_only=True)
class SweepCell:
    """All trials of one (planner, grid point, scenario)."""

    planner_name: str
    point: dict[str, ParamValue]
    scenario: Scenario
    records: TrialRecords
    path_length_m: FloatArray

    @property
    def summary(self) -> Summary:
        return summarize(self.records)

    @property
    def mean_path_length_m(self) -> float:
        """Mean path length over successful trials [m] (NaN if none succeeded)."""
        ok = self.records.outcome == Outcome.SUCCESS
        return float(self.path_length_m[ok].mean()) if ok.any() else math.nan


@dataclass(frozen=True, slots=True, kw_only=True)
class SweepPlan:
    """Every cell of a sweep as chunk tasks: cell ``k`` is ``tasks[spans[k][0]:spans[k][1]]``."""

    cells: list[tuple[str, dict[str, ParamValue], Scenario]]
    spans: list[tuple[int, int]]
    tasks: list[SweepTask]


def point_config(config: StudyConfig, point: dict[str, ParamValue]) -> StudyConfig:
    """``config`` with the grid point's planner parameters (validated by the params dataclass)."""
    overrides: dict[str, Any] = dict(point)  # values typed per field by sweep_grid.parse_param
    params = dataclasses.replace(config.planner_params, **overrides)
    return dataclasses.replace(config, planner_params=params)


def scenario_tasks(
    config: StudyConfig, planner_name: str, scenario: Scenario, trials: int, seed: int
) -> list[SweepTask]:
    """The seeded chunks of one cell: the study's (random fields) or the world study's (worlds)."""
    if isinstance(scenario, WorldCase):
        return list(make_world_tasks(config, (planner_name,), (scenario,), trials, seed))
    return list(make_tasks(config, (planner_name,), (scenario,), trials, seed))


def check_scenarios(config: StudyConfig, scenarios: Sequence[Scenario]) -> None:
    """``ConfigError`` for no scenario, a repeated one, two worlds with one name, or worlds in a 3D preset."""
    if not scenarios:
        raise ConfigError("sweep: no densities and no worlds to run")
    labels = [scenario_label(s) for s in scenarios]
    if len(set(labels)) != len(labels):
        raise ConfigError(f"sweep: each density and world must appear once (worlds by file stem), got {labels}")
    if config.dim != 2 and any(isinstance(s, WorldCase) for s in scenarios):
        raise ConfigError(f"sweep: world files are 2D; preset {config.preset} is {config.dim}D")


def plan_sweep(
    config: StudyConfig,
    planners: Sequence[str],
    swept: Sequence[SweepParam],
    scenarios: Sequence[Scenario],
    trials: int,
    seed: int,
) -> SweepPlan:
    """Planners outer, grid points (first parameter slowest), scenarios inner. Every invalid grid point (e.g.
    rho_l >= rho_u) is reported in one ``ConfigError`` before anything runs."""
    check_scenarios(config, scenarios)
    points = grid_points(swept)
    configs: list[StudyConfig] = []
    errors: list[str] = []
    for point in points:
        try:
            configs.append(point_config(config, point))
        except ConfigError as err:
            errors.append(f"{point}: {err}")
    if errors:
        raise ConfigError("sweep: invalid grid points: " + "; ".join(errors))
    plan = SweepPlan(cells=[], spans=[], tasks=[])
    for planner_name in planners:
        for point, cfg in zip(points, configs, strict=True):
            for scenario in scenarios:
                start = len(plan.tasks)
                plan.tasks.extend(scenario_tasks(cfg, planner_name, scenario, trials, seed))
                plan.cells.append((planner_name, point, scenario))
                plan.spans.append((start, len(plan.tasks)))
    return plan


def run_sweep(
    plan: SweepPlan, executor: Executor | None = None, *, progress: ProgressFn | None = None
) -> list[SweepCell]:
    """Run every chunk of the plan on ``executor`` (default: this process, one worker) and group the cells."""
    results = map_tasks(
        run_sweep_chunk, plan.tasks, executor, workers=1 if executor is None else None, progress=progress
    )
    cells = []
    for (planner_name, point, scenario), (a, b) in zip(plan.cells, plan.spans, strict=True):
        parts = results[a:b]
        cells.append(
            SweepCell(
                planner_name=planner_name,
                point=point,
                scenario=scenario,
                records=TrialRecords.concat([p.records for p in parts]),
                path_length_m=np.concatenate([p.path_length_m for p in parts]),
            )
        )
    return cells
