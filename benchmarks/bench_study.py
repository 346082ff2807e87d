"""Benchmark of the Monte Carlo study engine: trials/s per planner and the full default study's wall time.

Run: ``python benchmarks/bench_study.py`` (quick: single-process throughput per planner and density) or
``python benchmarks/bench_study.py --full`` (also the whole default study: the paper's 5 planners, bapf-nav and
bendyruler x 3 densities x 4000 trials on all cores; target <= 30 s on 2 workers). Prints the machine and
settings next to the numbers.

``--profile`` additionally splits one chunk's time between the planner's ``step_batch`` and the engine.
"""

from __future__ import annotations

import argparse
import os
import platform
import sys
import time
from typing import Any

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import numpy as np
import numpy.typing as npt

from apf_companion.planning import ALL_PLANNER_NAMES, BatchDecision, Planner, get_planner
from sim.study.config import DEFAULT_DENSITIES, Density, StudyConfig
from sim.study.engine import (
    ChunkTask,
    chunk_generators,
    run_chunk,
    run_study,
    simulate,
)
from sim.study.metrics import summarize
from sim.study.worlds import draw_worlds


def machine_info() -> str:
    return (
        f"python {platform.python_version()}, numpy {np.__version__}, {platform.machine()}, "
        f"{os.cpu_count()} cpu(s), {platform.processor() or platform.platform()}"
    )


def throughput(config: StudyConfig, planners: tuple[str, ...], densities: tuple[Density, ...], trials: int) -> None:
    print(f"\n## Single-process throughput ({trials} trials per cell, one chunk, preset {config.preset})\n")
    print("| planner | N | trials/s | ms/trial | mean iterations | R_s |")
    print("|---|---|---|---|---|---|")
    for name in planners:
        for d in densities:
            task = ChunkTask(config=config, planner_name=name, density=d, chunk_index=0, n_trials=trials, seed=1)
            res = run_chunk(task)
            s = summarize(res.records)
            print(
                f"| {name} | {d.label} | {trials / res.wall_s:.0f} | {1e3 * res.wall_s / trials:.3f} | "
                f"{res.records.iterations.mean():.1f} | {s.R_s:.3f} |"
            )
            sys.stdout.flush()


class _TimedPlanner:
    """Wraps a planner and accumulates the time spent in step_batch (other attributes, e.g. a stateful planner's
    ``initial_state``, are the wrapped planner's)."""

    def __getattr__(self, name: str) -> Any:
        return getattr(self.inner, name)

    def __init__(self, inner: Planner) -> None:
        self.inner = inner
        self.seconds = 0.0
        self.calls = 0
        self.agent_steps = 0

    def step_batch(
        self,
        positions_m: npt.NDArray[np.float64],
        targets_m: npt.NDArray[np.float64],
        obstacles_m: npt.NDArray[np.float64],
        obstacle_mask: npt.NDArray[np.bool_],
        rng: np.random.Generator | None = None,
        **kwargs: Any,
    ) -> BatchDecision:
        t0 = time.perf_counter()
        out = self.inner.step_batch(positions_m, targets_m, obstacles_m, obstacle_mask, rng, **kwargs)
        self.seconds += time.perf_counter() - t0
        self.calls += 1
        self.agent_steps += positions_m.shape[0]
        return out


def profile(config: StudyConfig, planners: tuple[str, ...], density: Density, trials: int) -> None:
    print(f"\n## Where the time goes ({trials} trials, N {density.label}, one process)\n")
    print("| planner | total s | step_batch s | share | calls | agent-steps | us/agent-step |")
    print("|---|---|---|---|---|---|---|")
    for name in planners:
        timed = _TimedPlanner(get_planner(name, config.planner_params))
        world_rng, motion_rng = chunk_generators(1, density, 0)
        worlds = draw_worlds(world_rng, trials, density, config.obstacle_box_m, config.dim)
        t0 = time.perf_counter()
        simulate(config, name, worlds, motion_rng, planner=timed)
        total = time.perf_counter() - t0
        print(
            f"| {name} | {total:.2f} | {timed.seconds:.2f} | {timed.seconds / total:.0%} | "
            f"{timed.calls} | {timed.agent_steps} | {1e6 * timed.seconds / max(timed.agent_steps, 1):.2f} |"
        )
        sys.stdout.flush()


def full(config: StudyConfig, workers: int | None, trials: int) -> None:
    n_planners = len(ALL_PLANNER_NAMES)
    print(
        f"\n## Full default study: {n_planners} planners x 3 densities x {trials} trials, "
        f"workers={workers or os.cpu_count()}\n"
    )
    t0 = time.perf_counter()
    cells = run_study(config, ALL_PLANNER_NAMES, DEFAULT_DENSITIES, trials, seed=0, workers=workers)
    wall = time.perf_counter() - t0
    n = sum(len(c.records) for c in cells)
    print("| planner | N | R_s | chunk wall s | chunk CPU s |")
    print("|---|---|---|---|---|")
    for c in cells:
        r_s = summarize(c.records).R_s
        print(f"| {c.planner_name} | {c.density.label} | {r_s:.3f} | {c.wall_s:.2f} | {c.cpu_s:.2f} |")
    per_planner: dict[str, float] = {}
    cpu_planner: dict[str, float] = {}
    for c in cells:
        per_planner[c.planner_name] = per_planner.get(c.planner_name, 0.0) + c.wall_s
        cpu_planner[c.planner_name] = cpu_planner.get(c.planner_name, 0.0) + c.cpu_s
    print("\nchunk seconds per planner (both workers): " + ", ".join(f"{k} {v:.1f}" for k, v in per_planner.items()))
    # CPU seconds are what the chunks cost, whatever else ran on the cores; wall seconds include waiting for them.
    print(
        "chunk CPU seconds per planner (both workers): "
        + ", ".join(f"{k} {v:.1f}" for k, v in cpu_planner.items())
        + f"; total {sum(cpu_planner.values()):.1f} (<= 60 for 30 s on 2 idle cores)"
    )
    print(f"\nfull study: {n} trials in {wall:.1f} s wall clock ({n / wall:.0f} trials/s); target <= 30 s (2 workers)")
    print(f"load average at the end: {' / '.join(f'{x:.2f}' for x in os.getloadavg())} (1 / 5 / 15 min)")


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--preset", default="reference", choices=("reference", "paper"))
    parser.add_argument("--trials", type=int, default=500, help="trials per cell for the throughput table")
    parser.add_argument("--planners", default=",".join(ALL_PLANNER_NAMES))
    parser.add_argument("--full", action="store_true", help="also run the whole default study")
    parser.add_argument("--full-trials", type=int, default=4000)
    parser.add_argument("--workers", type=int, default=None)
    parser.add_argument("--profile", action="store_true", help="split chunk time: planner vs engine")
    args = parser.parse_args()
    config = StudyConfig.from_preset(args.preset)
    planners = tuple(args.planners.split(","))
    print(f"# bench_study: {machine_info()}")
    print(f"chunk_trials={config.chunk_trials}, OPENBLAS_NUM_THREADS={os.environ.get('OPENBLAS_NUM_THREADS')}")
    throughput(config, planners, DEFAULT_DENSITIES, args.trials)
    if args.profile:
        profile(config, planners, DEFAULT_DENSITIES[1], args.trials)
    if args.full:
        full(config, args.workers, args.full_trials)
    return 0


if __name__ == "__main__":
    sys.exit(main())
