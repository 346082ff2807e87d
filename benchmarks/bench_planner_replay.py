"""bapf-nav step time along real flights through the bundled worlds, by how many points the memory holds.

Run: ``python benchmarks/bench_planner_replay.py [--trials 3] [--worlds NAME,...] [--no-area]``. Prints markdown
tables. Worlds whose file gives a flying area (``area_ne_m``: wall-gap, rooms) are planned over it unless
``--no-area``.

``bench_planner_step`` times steps in synthetic scenes: N points uniform in the 8 m disc around the agent. At
300 points that disc is a thicket (about 1.5 points per square metre; with the default clearance more than half
of the escape grid is blocked), so most of its steps are escapes out of an enclosure. This benchmark times the
steps of flights instead. Each world is flown by the study engine (``apf-sim study --world``: surfaces sampled
every 0.2 m, cumulative detection within the sensor range, the study's noise and seeds, ``record=True`` for the
positions). Then each flight is replayed through ``BapfNavPlanner.step``, the single-agent call the service
makes each cycle: at every visited position, with every surface point detected up to then, in order. Every
step is timed (``time.perf_counter``). The table groups the steps by the size of the memory they were given
and by the planner's mode after the step (DIRECT: the straight-line potential; ESCAPE: the geodesic field).

The issue-7 target (bapf-nav <= 100 us median in 2D with 300 remembered points) is quoted against the
synthetic scene in ``bench_planner_step``. This benchmark shows what the same code costs at 200-400 points on
surfaces the way a flight meets them.
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

from apf_companion.planning import NavMode, NavState, StatefulPlanner, get_planner
from sim.study.config import StudyConfig
from sim.study.engine import simulate
from sim.study.worlds import WorldBatch
from sim.study.worldstudy import load_case, motion_generator, without_area, world_config
from sim.world.geometry import segment_clearance_m

FloatArray = npt.NDArray[np.float64]

#: The adversarial worlds of issue 7 and the two forests.
DEFAULT_WORLDS = ("u-trap-goal", "wall-gap", "corridor-bend", "rooms", "slit", "forest", "forest-dense")
#: Memory sizes the steps are grouped by: [lo, hi) points.
BUCKETS = ((0, 100), (100, 200), (200, 400), (400, 800), (800, 10**9))


def flights(
    world: str, trials: int, seed: int, *, area: bool = True
) -> tuple[FloatArray, FloatArray, FloatArray, StudyConfig]:
    """(T, A, 2) positions of ``trials`` study flights (NaN once a trial ended), the surface samples (K, 2),
    the goal (2,) and the study config (with the world file's flying area as bapf-nav's ``nav_area_ne_m``
    unless ``area`` is False)."""
    case = load_case(world)
    if not area:
        case = without_area(case)
    config = world_config(StudyConfig.from_preset("reference"), case.world)
    samples = case.samples_ne_m
    batch = WorldBatch(
        obstacles_m=np.broadcast_to(samples, (trials, *samples.shape)).copy(),
        mask=np.ones((trials, samples.shape[0]), dtype=bool),
    )

    def clearance(a: FloatArray, b: FloatArray) -> FloatArray:
        return segment_clearance_m(case.world, a, b)

    rng = motion_generator(seed, case.label, 0)
    result = simulate(config, "bapf-nav", batch, rng, record=True, clearance=clearance)
    assert result.trace is not None
    return result.trace.positions_m, samples, np.asarray(config.target_m, dtype=np.float64), config


def replay(
    planner: StatefulPlanner, positions: FloatArray, samples: FloatArray, goal: FloatArray, sensor_m: float
) -> tuple[list[float], list[int], list[int]]:
    """Seconds per step, memory size and mode after the step, along one flight's positions (M, 2)."""
    planner.reset()
    known = np.zeros(samples.shape[0], dtype=bool)
    times, sizes, modes = [], [], []
    clock = time.perf_counter
    for pos in positions:
        rel = samples - pos
        known |= np.einsum("kd,kd->k", rel, rel) <= sensor_m * sensor_m
        memory = samples[known]
        t0 = clock()
        planner.step(pos, goal, memory)
        times.append(clock() - t0)
        sizes.append(memory.shape[0])
        state = planner.own_state
        assert isinstance(state, NavState)
        modes.append(int(state.mode[0]))
    return times, sizes, modes


def table(rows: list[tuple[str, FloatArray]]) -> None:
    print("| steps | n | median (us) | p90 (us) | p99 (us) | max (us) |")
    print("|---|---|---|---|---|---|")
    for label, t in rows:
        if t.size == 0:
            continue
        q = np.percentile(t, [50, 90, 99, 100]) * 1e6
        print(f"| {label} | {t.size} | {q[0]:.0f} | {q[1]:.0f} | {q[2]:.0f} | {q[3]:.0f} |")


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--trials", type=int, default=3, help="flights per world (default 3)")
    ap.add_argument("--worlds", default=",".join(DEFAULT_WORLDS), help="comma-separated bundled worlds or files")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--no-area", action="store_true", help="fly without the world files' flying areas (area_ne_m)")
    args = ap.parse_args(argv)
    print(f"python {sys.version.split()[0]}, numpy {np.__version__}, {platform.machine()}, {os.cpu_count()} cpus")
    print(f"load average {' '.join(f'{x:.2f}' for x in os.getloadavg())}\n")
    all_t: list[float] = []
    all_n: list[int] = []
    all_m: list[int] = []
    per_world = []
    for world in args.worlds.split(","):
        positions, samples, goal, config = flights(world, args.trials, args.seed, area=not args.no_area)
        planner = get_planner("bapf-nav", config.planner_params)
        assert isinstance(planner, StatefulPlanner)
        planner.step(positions[0, 0], goal, samples[:0])  # warm-up: imports, first allocations
        w_t: list[float] = []
        for a in range(positions.shape[1]):
            path = positions[:, a]
            t, n, m = replay(planner, path[np.isfinite(path[:, 0])], samples, goal, config.sensor_range_m)
            w_t += t
            all_t += t
            all_n += n
            all_m += m
        fenced = ", over its flying area" if config.planner_params.nav_area_ne_m is not None else ""
        per_world.append((f"{world} (memory up to {max(all_n[-len(w_t) :])} points{fenced})", np.asarray(w_t)))
    times, sizes, modes = np.asarray(all_t), np.asarray(all_n), np.asarray(all_m)
    print(f"## bapf-nav `step` along {args.trials} flight(s) per world, by world\n")
    table(per_world)
    print("\n## by memory size and mode (all worlds)\n")
    rows = []
    for lo, hi in BUCKETS:
        sel = (sizes >= lo) & (sizes < hi)
        span = f"{lo}-{hi - 1}" if hi < 10**9 else f">= {lo}"
        rows.append((f"{span} points, all", times[sel]))
        for mode in (NavMode.DIRECT, NavMode.ESCAPE):
            rows.append((f"{span} points, {mode.name}", times[sel & (modes == mode)]))
    table(rows)
    print(f"\nafter: load average {' '.join(f'{x:.2f}' for x in os.getloadavg())}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
