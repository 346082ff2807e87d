"""Full-knowledge optimum timings (sim/study/optimal.py): per random reference field and per bundled world.

Run: ``OPENBLAS_NUM_THREADS=1 python benchmarks/bench_optimal.py [--fields N]``. Prints the machine, then the
median and max wall time per field at the 0.2 m (``--optimum`` default on random fields) and 0.1 m grids, and
per bundled world at 0.1 m, with the optimum lengths. Not collected by pytest.
"""

from __future__ import annotations

import argparse
import os
import platform
import time

import numpy as np

from sim.study.config import Density, StudyConfig
from sim.study.engine import ChunkTask, chunk_worlds
from sim.study.optimal import optimal_path, optimal_path_points
from sim.world import EXAMPLES_DIR, load_world


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--fields", type=int, default=20, help="random fields per density (default 20)")
    args = parser.parse_args()
    print(f"{platform.processor() or platform.machine()}, {os.cpu_count()} cores, Python {platform.python_version()}")
    cfg = StudyConfig.reference()
    for label in ("20-45", "45-70", "70-95"):
        d = Density.parse(label)
        worlds = chunk_worlds(
            ChunkTask(config=cfg, planner_name="", density=d, chunk_index=0, n_trials=args.fields, seed=0)
        )
        for resolution in (0.2, 0.1):
            times, lengths = [], []
            for a in range(args.fields):
                pts = worlds.obstacles_m[a][worlds.mask[a]]
                t0 = time.perf_counter()
                opt = optimal_path_points(pts, cfg.start_m, cfg.target_m, resolution_m=resolution)
                times.append(time.perf_counter() - t0)
                lengths.append(opt.length_m)
            print(
                f"field N {label} grid {resolution} m: median {1e3 * np.median(times):6.1f} ms, "
                f"max {1e3 * np.max(times):6.1f} ms per field; mean optimum {np.mean(lengths):.2f} m "
                f"({args.fields} fields)"
            )
    for path in sorted(EXAMPLES_DIR.glob("*.toml")):
        world = load_world(path)
        t0 = time.perf_counter()
        opt = optimal_path(world)
        print(f"world {world.name:14s} grid 0.1 m: {1e3 * (time.perf_counter() - t0):7.1f} ms, {opt.length_m:.2f} m")


if __name__ == "__main__":
    main()
