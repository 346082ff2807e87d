"""Planner step time: median and p99 of one ``step`` for every planner, 30, 95 and 300 obstacles, 2D and 3D.

Run: ``python benchmarks/bench_planner_step.py [--rounds N] [--batch]``. Prints a markdown table and the machine.

Scenario: the agent in the middle of the paper's 30 m field, target (22, 22) or (22, 22, 10), obstacles drawn
uniformly within the 8 m sensor range (all "detected"). 200 different scenes are cycled so the numbers cover
near-obstacle and open-field steps alike. ``--batch`` also times ``step_batch`` for A = 4000 agents (the study
engine's lockstep call) and prints the time per agent-step.

The stateful planners (bapf-nav, bendyruler) carry memory: before each timed step they take one untimed step
from the same scene after ``reset()``, so the timed step is a steady-state step of a flight (its escape
potential, if the scene needs one, already computed), not a first step. The issue's targets: bapf-nav <= 100 us
median in 2D with 300 remembered points, and <= 3x CR-BAPF* at 30 obstacles; the last lines print both, the
first also in reference ops (the median over the time of ``a + a`` on 60 floats right then: it follows load).

Columns: median and p99 over all timed steps (wall clock, ``time.perf_counter``); "quiet median" is the median
over scenes of each scene's best round, an estimate that holds up on a shared, loaded machine. The planners
are interleaved scene by scene, so load bursts hit them alike. The header records the load average and the
time of a reference numpy op (``a + a`` on 60 floats) so runs on different machines or loads can be compared.
"""

from __future__ import annotations

import argparse
import os
import platform
import sys
import time

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import numpy as np
import numpy.typing as npt

from apf_companion.planning import ALL_PLANNER_NAMES, PlannerParams, StatefulPlanner, get_planner

FloatArray = npt.NDArray[np.float64]


def scenes(n_scenes: int, n_obstacles: int, dim: int, seed: int) -> list[tuple[FloatArray, FloatArray, FloatArray]]:
    """(position, target, obstacles) triples: obstacles uniform in the 8 m ball around the agent."""
    rng = np.random.default_rng(seed)
    target = np.full(dim, 22.0) if dim == 2 else np.array([22.0, 22.0, 10.0])
    out = []
    for _ in range(n_scenes):
        position = rng.uniform(4.0, 20.0, dim)
        direction = rng.normal(size=(n_obstacles, dim))
        direction /= np.linalg.norm(direction, axis=1, keepdims=True)
        radius = 8.0 * rng.random((n_obstacles, 1)) ** (1.0 / dim)
        obstacles = position + np.maximum(radius, 0.5) * direction
        out.append((position, target, obstacles))
    return out


def time_steps(dim: int, n_obstacles: int, rounds: int) -> dict[str, FloatArray]:
    """Seconds per ``step``, shape (rounds, scenes), for every planner.

    The planners are interleaved scene by scene within each round, so load bursts on a shared machine hit all
    of them alike.
    """
    planners = {name: get_planner(name, PlannerParams(dim=dim)) for name in ALL_PLANNER_NAMES}
    cases = scenes(200, n_obstacles, dim, seed=n_obstacles * 10 + dim)
    rng = np.random.default_rng(0)
    out = {name: np.empty((rounds, len(cases))) for name in ALL_PLANNER_NAMES}
    clock = time.perf_counter
    for planner in planners.values():  # warm-up
        for position, target, obstacles in cases[:20]:
            planner.step(position, target, obstacles, rng)
    for r in range(rounds):
        for i, (position, target, obstacles) in enumerate(cases):
            for name, planner in planners.items():
                if isinstance(planner, StatefulPlanner):  # steady state: see the module docstring
                    planner.reset()
                    planner.step(position, target, obstacles, rng)
                t0 = clock()
                planner.step(position, target, obstacles, rng)
                out[name][r, i] = clock() - t0
    return out


def reference_op_ns() -> float:
    """Best-of-5 time of ``a + a`` on 60 float64 [ns]: the machine's per-call numpy overhead, right now."""
    a = np.ones(60)
    best = np.inf
    for _ in range(5):
        t0 = time.perf_counter()
        for _ in range(20000):
            a + a
        best = min(best, (time.perf_counter() - t0) / 20000)
    return best * 1e9


def time_batch(name: str, dim: int, n_obstacles: int, n_agents: int, repeats: int) -> float:
    """Median time of one ``step_batch`` over ``n_agents`` agents, per agent [us]."""
    planner = get_planner(name, PlannerParams(dim=dim))
    cases = scenes(n_agents, n_obstacles, dim, seed=1)
    positions = np.stack([c[0] for c in cases])
    targets = np.stack([c[1] for c in cases])
    obstacles = np.stack([c[2] for c in cases])
    mask = np.ones(obstacles.shape[:2], dtype=bool)
    rng = np.random.default_rng(0)
    samples = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        planner.step_batch(positions, targets, obstacles, mask, rng)
        samples.append(time.perf_counter() - t0)
    return float(np.median(samples) / n_agents * 1e6)


def load_line() -> str:
    """Load average and the reference op time, to put the numbers in context."""
    load = " ".join(f"{x:.2f}" for x in os.getloadavg())
    return f"load average {load}; reference op (a + a, 60 floats) {reference_op_ns():.0f} ns"


def machine() -> str:
    cpu = platform.processor() or platform.machine()
    try:
        with open("/proc/cpuinfo") as f:
            for line in f:
                if line.startswith("model name"):
                    cpu = line.split(":", 1)[1].strip()
                    break
    except OSError:
        pass
    return (
        f"{cpu}; {os.cpu_count()} cores; Python {platform.python_version()}; numpy {np.__version__}; "
        f"{platform.system()} {platform.release()}; OPENBLAS_NUM_THREADS={os.environ.get('OPENBLAS_NUM_THREADS')}"
    )


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0] if __doc__ else None)
    parser.add_argument("--rounds", type=int, default=15, help="rounds over the 200 scenes (default 15)")
    parser.add_argument("--batch", action="store_true", help="also time step_batch with A = 4000")
    args = parser.parse_args(argv)

    print(f"machine: {machine()}")
    print(f"before: {load_line()}")
    print(f"params: PlannerParams() defaults (paper Table I), N_b = 60, {args.rounds} rounds x 200 scenes\n")
    ratios: list[str] = []
    nav_us: dict[tuple[int, int], float] = {}  # (dim, obstacles) -> bapf-nav median [us]
    nav_ratio: dict[tuple[int, int], float] = {}  # (dim, obstacles) -> bapf-nav median / cr-bapf* median
    print("| planner | dim | obstacles | median (us) | p99 (us) | quiet median (us) |")
    print("|---|---|---|---|---|---|")
    for dim in (2, 3):
        for n_obstacles in (30, 95, 300):
            samples = time_steps(dim, n_obstacles, args.rounds)
            for name in ALL_PLANNER_NAMES:
                s_us = samples[name] * 1e6
                median, p99 = np.median(s_us), np.percentile(s_us, 99)
                quiet = np.median(s_us.min(axis=0))  # per scene, the best round
                print(f"| {name} | {dim}D | {n_obstacles} | {median:.1f} | {p99:.1f} | {quiet:.1f} |")
                sys.stdout.flush()
            base = np.median(samples["cr-bapf*"])
            nav_us[dim, n_obstacles] = float(np.median(samples["bapf-nav"]) * 1e6)
            nav_ratio[dim, n_obstacles] = float(np.median(samples["bapf-nav"]) / base)
            ratios.extend(
                f"{name} / cr-bapf* at {dim}D, {n_obstacles} obstacles: {np.median(samples[name]) / base:.2f}x"
                for name in ("bapf-nav", "bendyruler")
            )
    print("\n" + "\n".join(ratios))
    ref_ns = reference_op_ns()
    med300, ratio30 = nav_us[2, 300], nav_ratio[2, 30]
    print(
        f"\nissue 7 targets: bapf-nav 2D, 300 points: median {med300:.1f} us (target <= 100 us; "
        f"{1e3 * med300 / ref_ns:.0f} reference ops); bapf-nav / cr-bapf* 2D, 30 points: {ratio30:.2f}x "
        "(target <= 3x)"
    )
    if args.batch:
        print("\n| planner | dim | obstacles | step_batch A=4000, per agent (us) |")
        print("|---|---|---|---|")
        for dim in (2, 3):
            for n_obstacles in (30, 95):
                for name in ALL_PLANNER_NAMES:
                    per_agent = time_batch(name, dim, n_obstacles, 4000, repeats=5)
                    print(f"| {name} | {dim}D | {n_obstacles} | {per_agent:.2f} |")
                    sys.stdout.flush()
    print(f"\nafter: {load_line()}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
