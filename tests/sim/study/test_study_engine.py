"""The lockstep study engine: hand-made worlds, preset rules, determinism across worker counts."""

from __future__ import annotations

import dataclasses
import math
import multiprocessing
import os
import subprocess
import sys
from concurrent.futures import ProcessPoolExecutor

import numpy as np
import numpy.typing as npt
import pytest

from apf_companion.planning import PLANNER_NAMES, BatchDecision, get_planner
from sim.study.config import Density, DetectionRule, StudyConfig
from sim.study.engine import (
    FUSED_CHUNKS,
    ChunkGroup,
    ChunkTask,
    SerialExecutor,
    chunk_worlds,
    collect_cells,
    group_tasks,
    make_tasks,
    run_chunk,
    run_group,
    run_study,
    simulate,
)
from sim.study.engine import chunk_generators as engine_chunk_generators
from sim.study.metrics import Outcome, summarize
from sim.study.worlds import WorldBatch, draw_worlds


def _world(points: npt.ArrayLike) -> WorldBatch:
    pts = np.asarray(points, dtype=np.float64).reshape(1, -1, 2)
    return WorldBatch(obstacles_m=pts, mask=np.ones(pts.shape[:2], dtype=bool))


def _quiet(config: StudyConfig) -> StudyConfig:
    return dataclasses.replace(config, noise_std_m=0.0)


def test_empty_world_reaches_goal_in_about_68_iterations() -> None:
    cfg = _quiet(StudyConfig.reference())
    res = simulate(cfg, "cr-bapf", _world(np.zeros((0, 2))), np.random.default_rng(0), record=True)
    assert res.records.outcome[0] == Outcome.SUCCESS
    # 26.87 m at ~0.4 m per move, plus the final iteration inside the goal circle (docs/paper/notes.md).
    assert 66 <= res.records.iterations[0] <= 69
    assert math.isnan(res.records.safety_m[0])
    assert res.trace is not None
    path = res.trace.positions_m[:, 0, :]
    assert path.shape[0] == res.records.iterations[0]
    assert np.linalg.norm(path[-1] - np.array(cfg.target_m)) <= cfg.goal_radius_m
    assert np.linalg.norm(path[-2] - np.array(cfg.target_m)) > cfg.goal_radius_m


def test_collision_at_start_of_iteration() -> None:
    cfg = StudyConfig.reference()
    res = simulate(cfg, "cr-bapf*", _world([[3.1, 3.0]]), np.random.default_rng(0))
    assert res.records.outcome[0] == Outcome.COLLISION
    assert res.records.iterations[0] == 1


def test_start_inside_goal_is_success_at_first_iteration() -> None:
    cfg = dataclasses.replace(StudyConfig.reference(), start_m=(21.8, 22.0))
    res = simulate(cfg, "capf", _world([[20.0, 20.0], [5.0, 5.0]]), np.random.default_rng(0))
    assert res.records.outcome[0] == Outcome.SUCCESS
    assert res.records.iterations[0] == 1
    assert res.records.safety_m[0] == pytest.approx(math.hypot(1.8, 2.0))  # only the detected one
    assert res.records.n_detected[0] == 1


def test_iteration_cap_gives_timeout() -> None:
    cfg = dataclasses.replace(StudyConfig.reference(), max_iterations=5)
    res = simulate(cfg, "bapf", _world(np.zeros((0, 2))), np.random.default_rng(0))
    assert res.records.outcome[0] == Outcome.TIMEOUT
    assert res.records.iterations[0] == 5


def test_local_minimum_ends_bapf_but_not_cr_bapf_star() -> None:
    # One obstacle 0.5 m ahead on the way to the target: every bacteria point closer to the target lies within
    # 0.64 m of it, where exp(-1000 d^2) dwarfs the target-potential gain 26 m out, so BAPF has no move.
    ahead = np.array([3.0, 3.0]) + 0.5 * np.array([1.0, 1.0]) / math.sqrt(2.0)
    cfg = _quiet(StudyConfig.reference())
    bapf = simulate(cfg, "bapf", _world([ahead]), np.random.default_rng(0))
    assert bapf.records.outcome[0] == Outcome.STUCK
    assert bapf.records.iterations[0] == 1
    star = simulate(cfg, "cr-bapf*", _world([ahead]), np.random.default_rng(0))
    assert star.records.outcome[0] != Outcome.STUCK
    assert star.records.iterations[0] > 1


class _Spy:
    """A real planner that records, per call, the largest distance from agent to a known obstacle."""

    def __init__(self, name: str, config: StudyConfig) -> None:
        self.inner = get_planner(name, config.planner_params)
        self.max_known_dist: list[float] = []

    def step_batch(
        self,
        positions_m: npt.NDArray[np.float64],
        targets_m: npt.NDArray[np.float64],
        obstacles_m: npt.NDArray[np.float64],
        obstacle_mask: npt.NDArray[np.bool_],
        rng: np.random.Generator | None = None,
    ) -> BatchDecision:
        if obstacle_mask.any():
            d = np.linalg.norm(obstacles_m - positions_m[:, None, :], axis=-1)
            self.max_known_dist.append(float(d[obstacle_mask].max()))
        return self.inner.step_batch(positions_m, targets_m, obstacles_m, obstacle_mask, rng)


@pytest.mark.parametrize("rule", list(DetectionRule))
def test_detection_rule_cumulative_vs_in_range(rule: DetectionRule) -> None:
    # Obstacles beside the straight path: each is passed and left behind.
    pts = [[6.0, 4.5], [9.0, 7.5], [12.0, 10.5], [15.0, 13.5], [18.0, 16.5]]
    cfg = dataclasses.replace(_quiet(StudyConfig.reference()), detection=rule)
    spy = _Spy("cr-bapf*", cfg)
    res = simulate(cfg, "cr-bapf*", _world(pts), np.random.default_rng(0), planner=spy)
    assert res.records.outcome[0] == Outcome.SUCCESS
    assert res.records.n_detected[0] == 5
    far = max(spy.max_known_dist)
    if rule is DetectionRule.IN_RANGE:
        assert far <= cfg.sensor_range_m
    else:
        assert far > cfg.sensor_range_m  # remembered after leaving the sensor range


def test_reference_worlds_inside_box_paper_worlds_wider() -> None:
    d = Density(n_low=70, n_high=95)
    ref = chunk_worlds(
        ChunkTask(config=StudyConfig.reference(), planner_name="bapf", density=d, chunk_index=0, n_trials=200, seed=3)
    )
    pts = ref.obstacles_m[ref.mask]
    assert pts.min() >= 5.0
    assert pts.max() <= 20.0
    pap = chunk_worlds(
        ChunkTask(config=StudyConfig.paper(), planner_name="bapf", density=d, chunk_index=0, n_trials=200, seed=3)
    )
    pts = pap.obstacles_m[pap.mask]
    assert pts.min() < 1.0
    assert pts.max() > 29.0


def test_worlds_shared_across_planners_and_chunks_differ() -> None:
    d = Density(n_low=20, n_high=45)
    cfg = StudyConfig.reference()
    a = chunk_worlds(ChunkTask(config=cfg, planner_name="bapf", density=d, chunk_index=0, n_trials=10, seed=5))
    b = chunk_worlds(ChunkTask(config=cfg, planner_name="capf", density=d, chunk_index=0, n_trials=10, seed=5))
    c = chunk_worlds(ChunkTask(config=cfg, planner_name="bapf", density=d, chunk_index=1, n_trials=10, seed=5))
    assert np.array_equal(a.obstacles_m, b.obstacles_m)
    assert not np.array_equal(a.obstacles_m, c.obstacles_m)


@pytest.mark.parametrize("name", PLANNER_NAMES)
def test_small_run_of_each_planner_is_sane(name: str) -> None:
    cfg = StudyConfig.reference()
    cells = run_study(cfg, (name,), (Density(n_low=20, n_high=45),), 40, seed=11, executor=SerialExecutor())
    s = summarize(cells[0].records)
    assert s.trials == 40
    assert s.success + s.collision + s.stuck + s.timeout == 40
    assert s.success > 0
    assert 60.0 <= s.M_s <= cfg.max_iterations
    assert cfg.collision_radius_m < s.S < cfg.sensor_range_m
    assert np.all(cells[0].records.n_detected <= cells[0].records.n_obstacles)


def test_same_seed_same_results_with_one_and_two_workers() -> None:
    cfg = dataclasses.replace(StudyConfig.reference(), chunk_trials=15)
    planners = ("bapf", "cr-bapf*")
    densities = (Density(n_low=45, n_high=70),)
    one = run_study(cfg, planners, densities, 45, seed=7, executor=SerialExecutor())
    with ProcessPoolExecutor(max_workers=2, mp_context=multiprocessing.get_context("spawn")) as pool:
        two = run_study(cfg, planners, densities, 45, seed=7, executor=pool)
    assert [(c.planner_name, c.density) for c in one] == [(c.planner_name, c.density) for c in two]
    for x, y in zip(one, two, strict=True):
        for field in ("outcome", "iterations", "n_obstacles", "n_detected"):
            assert np.array_equal(getattr(x.records, field), getattr(y.records, field)), field
        assert np.array_equal(x.records.safety_m, y.records.safety_m, equal_nan=True)
    other = run_study(cfg, planners, densities, 45, seed=8, executor=SerialExecutor())
    assert not np.array_equal(one[1].records.iterations, other[1].records.iterations)


def test_a_group_of_bendyruler_chunks_equals_the_chunks_alone() -> None:
    # Each chunk keeps its own worlds and noise stream inside the lockstep group, so its records are the same to
    # the last bit (only the timing is shared); 70-95 obstacles, where some trials time out.
    cfg = dataclasses.replace(StudyConfig.reference(), chunk_trials=20, max_iterations=200)
    tasks = make_tasks(cfg, ("bendyruler",), (Density(n_low=70, n_high=95),), 60, seed=3)
    alone = [run_chunk(t) for t in tasks]
    together = run_group(ChunkGroup(tuple(tasks)))
    assert [r.task for r in together] == tasks
    for x, y in zip(alone, together, strict=True):
        for field in ("outcome", "iterations", "safety_m", "n_obstacles", "n_detected", "path_m", "clearance_m"):
            a, b = getattr(x.records, field), getattr(y.records, field)
            assert a.tobytes() == b.tobytes(), field
    assert len({r.records.safety_m.tobytes() for r in alone}) == 3  # three different chunks
    assert sum(r.wall_s for r in together) > 0.0
    # CPU time is measured per chunk, and a group's is shared like its wall time: by each chunk's iterations.
    assert all(r.cpu_s > 0.0 for r in alone)
    ratios = [r.cpu_s / r.wall_s for r in together]
    assert ratios[0] > 0.0 and all(math.isclose(x, ratios[0]) for x in ratios)
    cells = collect_cells(together)
    assert len(cells) == 1 and math.isclose(cells[0].cpu_s, sum(r.cpu_s for r in together))


def test_only_bendyruler_chunks_of_one_cell_are_grouped() -> None:
    cfg = dataclasses.replace(StudyConfig.reference(), chunk_trials=10)
    densities = (Density(n_low=20, n_high=45), Density(n_low=45, n_high=70))
    tasks = make_tasks(cfg, ("bapf", "bendyruler"), densities, 10 * (FUSED_CHUNKS + 2), seed=0)
    sizes = [(g.tasks[0].planner_name, g.tasks[0].density.n_low, len(g.tasks)) for g in group_tasks(tasks)]
    n = FUSED_CHUNKS + 2
    bapf = [("bapf", 20, 1)] * n + [("bapf", 45, 1)] * n
    bendy = [("bendyruler", 20, FUSED_CHUNKS), ("bendyruler", 20, 2), ("bendyruler", 45, FUSED_CHUNKS)]
    assert sizes == [*bapf, *bendy, ("bendyruler", 45, 2)]
    assert [t for g in group_tasks(tasks) for t in g.tasks] == tasks


class _RecordingExecutor(SerialExecutor):
    def __init__(self) -> None:
        self.submitted: list[ChunkGroup] = []

    def submit(self, fn, /, *args, **kwargs):  # type: ignore[no-untyped-def]
        self.submitted.append(args[0])
        return super().submit(fn, *args, **kwargs)


def test_the_costliest_chunks_start_first() -> None:
    cfg = dataclasses.replace(StudyConfig.reference(), chunk_trials=5, max_iterations=3)
    densities = (Density(n_low=20, n_high=45), Density(n_low=70, n_high=95))
    ex = _RecordingExecutor()
    cells = run_study(cfg, ("capf", "bapf-nav", "bendyruler"), densities, 10, seed=0, executor=ex)
    first = [(g.tasks[0].planner_name, g.tasks[0].density.n_low, len(g.tasks)) for g in ex.submitted]
    assert first[:3] == [("bendyruler", 70, 2), ("bapf-nav", 70, 1), ("bapf-nav", 70, 1)]
    assert first[-2:] == [("capf", 20, 1), ("capf", 20, 1)]
    # The results still come back in task order: planners outer, densities inner.
    assert [(c.planner_name, c.density.n_low) for c in cells] == [
        (p, d.n_low) for p in ("capf", "bapf-nav", "bendyruler") for d in densities
    ]


def test_safety_matches_recomputation_from_the_visited_positions() -> None:
    # S (Eq. (16)) recomputed independently: for each obstacle that ever came within sensor range of a visited
    # position, its minimum distance to the visited positions; mean over those obstacles.
    cfg = StudyConfig.reference()
    density = Density(n_low=45, n_high=70)
    world_rng, motion_rng = engine_chunk_generators(9, density, 0)
    worlds = draw_worlds(world_rng, 12, density, cfg.obstacle_box_m)
    res = simulate(cfg, "cr-bapf*", worlds, motion_rng, record=True)
    assert res.trace is not None
    for a in range(12):
        path = res.trace.positions_m[:, a]
        path = path[~np.isnan(path[:, 0])]
        assert path.shape[0] == res.records.iterations[a]
        obs = worlds.obstacles_m[a][worlds.mask[a]]
        min_d = np.linalg.norm(path[:, None, :] - obs[None], axis=-1).min(axis=0)
        seen = min_d <= cfg.sensor_range_m
        assert res.records.n_detected[a] == seen.sum()
        assert res.records.safety_m[a] == pytest.approx(min_d[seen].mean(), rel=1e-12)


def test_engine_runs_in_3d() -> None:
    # docs/paper/notes.md decision 6: the same rules in 3D (bacteria points on a sphere); the engine is dim-generic.
    from apf_companion.planning import PlannerParams

    cfg = dataclasses.replace(
        StudyConfig.reference(),
        planner_params=PlannerParams.reference(dim=3, n_bacteria=120),
        start_m=(3.0, 3.0, 3.0),
        target_m=(22.0, 22.0, 22.0),
    )
    cells = run_study(cfg, ("cr-bapf*",), (Density(n_low=200, n_high=300),), 12, seed=0, executor=SerialExecutor())
    s = summarize(cells[0].records)
    assert s.success >= 9
    assert 75.0 <= s.M_s <= 200.0  # (32.9 m - 0.7 m) / 0.4 m = 81 moves without noise
    assert cfg.collision_radius_m < s.S < cfg.sensor_range_m


_START_METHOD_PROBE = """
import dataclasses, sys, threading
from sim.study.config import Density, StudyConfig
from sim.study.engine import SerialExecutor, os_thread_count, run_study, start_method
if sys.argv[1] == "thread":
    stop = threading.Event()
    threading.Thread(target=stop.wait, daemon=True).start()
method, threads = start_method(), os_thread_count()
cfg = dataclasses.replace(StudyConfig.reference(), chunk_trials=15)
args = (cfg, ("cr-bapf*", "bapf-nav"), (Density(n_low=45, n_high=70),), 30, 7)
one = run_study(*args, executor=SerialExecutor())
two = run_study(*args, workers=2)  # the default pool
same = all(
    getattr(x.records, f).tobytes() == getattr(y.records, f).tobytes()
    for x, y in zip(one, two, strict=True)
    for f in ("outcome", "iterations", "safety_m", "path_m", "clearance_m")
)
print(method, threads, same)
"""


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="/proc/self/status")
@pytest.mark.parametrize(("case", "expected"), [("plain", "fork"), ("thread", "spawn")])
def test_default_pool_forks_only_a_single_threaded_process(case: str, expected: str) -> None:
    # In a fresh interpreter (this process runs pytest-xdist's threads): a single-threaded process forks its
    # workers, one with a second thread (a Python one here; OpenBLAS's own when OPENBLAS_NUM_THREADS > 1) spawns
    # them; either way the records equal the in-process run's to the last bit.
    env = {**os.environ, "OPENBLAS_NUM_THREADS": "1"}
    out = subprocess.run(
        [sys.executable, "-c", _START_METHOD_PROBE, case], env=env, capture_output=True, text=True, check=True
    ).stdout.split()
    assert out == [expected, "1" if case == "plain" else "2", "True"]
