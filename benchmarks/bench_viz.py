"""What the Foxglove sink adds to a service cycle (apf_companion/viz): one ``on_cycle`` per obstacle count.

Run: ``OPENBLAS_NUM_THREADS=1 python benchmarks/bench_viz.py``. Prints the machine, then the median and 99th
percentile wall time of one ``FoxgloveSink.on_cycle`` (MCAP to a temporary file, and MCAP + a WebSocket server on
a free loopback port with no client) with 0 to 8000 remembered obstacle points and a bapf-nav step of 60
candidates. Not collected by pytest.
"""

from __future__ import annotations

import os
import platform
import tempfile
import time
from pathlib import Path

import numpy as np

from apf_companion.goal import Route
from apf_companion.navigator import CycleOutput, State
from apf_companion.observe import CycleSnapshot, PlanStep
from apf_companion.perception import Pose
from apf_companion.planning import BapfNavPlanner, PlannerParams
from apf_companion.setpoint import SetpointKind, hold
from apf_companion.viz.sink import FoxgloveSink

CYCLES = 300


def snapshot(n_obstacles: int, t_s: float, rng: np.random.Generator) -> CycleSnapshot:
    planner = BapfNavPlanner(PlannerParams())
    obstacles = rng.uniform(-20.0, 20.0, (n_obstacles, 3))
    origin = np.array([1.0, 2.0])
    decision = planner.step(origin, np.array([20.0, 20.0]), obstacles[:, :2])
    plan = PlanStep(
        seq=1,
        origin_m=origin,
        target_m=np.array([20.0, 20.0]),
        candidates_m=origin + planner.bacteria_offsets_m,
        decision=decision,
    )
    out = CycleOutput(
        t_s=t_s, state=State.NAVIGATING, setpoint=hold(np.array([1.0, 2.0, -5.0]), SetpointKind.NAVIGATE),
        decision="GREEDY", distance_to_goal_m=25.0, nearest_obstacle_m=1.5, n_obstacles=n_obstacles,
    )  # fmt: skip
    return CycleSnapshot(
        out=out,
        pose=Pose(t_s=t_s, pos_ned_m=np.array([1.0, 2.0, -5.0]), yaw_rad=0.3),
        route=Route.point(20.0, 20.0, -5.0, source="bench"),
        target_ned_m=np.array([20.0, 20.0, -5.0]),
        obstacles_ned_m=obstacles,
        scan_ned_m=obstacles[:72],
        plan=plan,
    )


def main() -> None:
    print(f"{platform.processor() or platform.machine()}, {os.cpu_count()} cores, Python {platform.python_version()}")
    rng = np.random.default_rng(0)
    with tempfile.TemporaryDirectory() as tmp:
        for server in (False, True):
            for n in (0, 500, 2000, 8000):
                snap = snapshot(n, 0.0, rng)
                sink = FoxgloveSink(mcap_path=Path(tmp) / f"b-{n}-{server}.mcap", port=0 if server else None)
                times = []
                for _ in range(CYCLES):
                    t0 = time.perf_counter()
                    sink.on_cycle(snap)
                    times.append(time.perf_counter() - t0)
                sink.close()
                ms = np.array(times) * 1e3
                what = "mcap + websocket" if server else "mcap"
                print(f"{what:17s} {n:5d} obstacles: median {np.median(ms):.3f} ms, p99 {np.percentile(ms, 99):.3f} ms")


if __name__ == "__main__":
    main()
