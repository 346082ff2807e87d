"""Perception hot-path timings: MAVLink/JSON/CDR decode, placement in NED, obstacle memory.

Run: ``OPENBLAS_NUM_THREADS=1 python benchmarks/bench_perception.py [--repeat N]``. Prints the machine,
the settings and median / p99 per call in microseconds. Not collected by pytest.
"""

from __future__ import annotations

import argparse
import math
import os
import platform
import time
from collections.abc import Callable
from functools import partial

import numpy as np
from pymavlink.dialects.v20 import ardupilotmega as mavlink

from apf_companion.perception import (
    ObstacleMemory,
    Pose,
    PoseHistory,
    RangeScan,
    ScanFrame,
    decode_laserscan_cdr,
    decode_scan_json,
    encode_laserscan_cdr,
    encode_scan_json,
    scan_from_obstacle_distance,
    scan_to_points_ned,
    surface_fill_points,
)
from apf_companion.perception.geometry import return_spread_m


def _time(fn: Callable[[], object], repeat: int) -> tuple[float, float]:
    for _ in range(min(50, repeat)):
        fn()
    samples = np.empty(repeat)
    for i in range(repeat):
        t0 = time.perf_counter()
        fn()
        samples[i] = time.perf_counter() - t0
    return float(np.median(samples) * 1e6), float(np.percentile(samples, 99) * 1e6)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--repeat", type=int, default=2000)
    args = parser.parse_args()
    rep = int(args.repeat)
    rng = np.random.default_rng(1)
    print(f"machine: {platform.machine()} {platform.processor() or ''} cpus={os.cpu_count()}")
    print(f"python {platform.python_version()}, numpy {np.__version__}, repeat={args.repeat}")
    print(f"OPENBLAS_NUM_THREADS={os.environ.get('OPENBLAS_NUM_THREADS')}")

    dists = rng.integers(30, 1200, 72).tolist()
    od = mavlink.MAVLink_obstacle_distance_message(
        1_000_000, 0, dists, 0, 20, 1000, 5.0, 0.0, mavlink.MAV_FRAME_BODY_FRD
    )
    history = PoseHistory(200)
    for i in range(200):
        history.add(Pose(t_s=i * 0.02, pos_ned_m=np.array([i * 0.01, 0.0, -5.0]), yaw_rad=0.001 * i))
    pose = history.at(3.01)
    assert pose is not None
    scan = scan_from_obstacle_distance(od, t_s=3.01)
    rows: list[tuple[str, tuple[float, float]]] = []
    rows.append(("OBSTACLE_DISTANCE(72) -> RangeScan", _time(partial(scan_from_obstacle_distance, od, t_s=3.01), rep)))
    rows.append(("PoseHistory(200).at", _time(partial(history.at, 3.013), rep)))
    rows.append(("scan_to_points_ned(72)", _time(partial(scan_to_points_ned, scan, pose), rep)))

    for n in (72, 360):
        s = RangeScan(
            t_s=0.0,
            frame=ScanFrame.BODY_FRD,
            bearings_rad=np.linspace(-math.pi, math.pi, n, endpoint=False),
            ranges_m=rng.uniform(0.3, 11.0, n),
            range_min_m=0.2,
            range_max_m=12.0,
        )
        js, cdr = encode_scan_json(s), encode_laserscan_cdr(s)
        rows.append((f"decode_scan_json({n})", _time(partial(decode_scan_json, js, t_s=0.0), rep)))
        rows.append((f"decode_laserscan_cdr({n})", _time(partial(decode_laserscan_cdr, cdr, t_s=0.0), rep)))

    points = scan_to_points_ned(scan, pose)
    # "spread": remembered points over a 60 x 60 m area; "near": all within 12 m of the vehicle (worst case).
    for size in (200, 2000):
        for layout, half_m in (("spread", 30.0), ("near", 12.0)):
            mem = ObstacleMemory(expiry_s=1e9, merge_radius_m=0.2, max_points=size + 100)
            xy = rng.uniform(-half_m, half_m, (size, 2))
            mem.add(np.column_stack([xy, np.full(size, -5.0)]), t_s=0.0)
            jitter = points + rng.normal(0, 0.05, points.shape)
            name = f"ObstacleMemory({size} {layout})"
            rows.append((f"{name}.add(72)", _time(partial(mem.add, jitter, 1.0), rep)))
            # margin 100 m: the same work as a real clearing pass, but nothing is removed between repeats.
            clear = partial(mem.clear_observed, scan, pose, margin_m=100.0)
            rows.append((f"{name}.clear_observed(72)", _time(clear, rep)))
            rows.append((f"{name}.points", _time(partial(mem.points, 2.0), rep)))

    # Points with a spread (sector returns, 0.35 m: placed at 8 m) that a free 72-beam scan sees through: every one
    # within 8 m takes the disc test over its neighbouring windows (worst case; clear_scans so large that nothing
    # is removed between repeats).
    free = RangeScan(
        t_s=1.0,
        frame=ScanFrame.LOCAL_NED,
        bearings_rad=np.deg2rad(5.0 * np.arange(72)),
        ranges_m=np.full(72, math.inf),
        range_min_m=0.2,
        range_max_m=8.0,
    )
    for size in (200, 2000):
        mem = ObstacleMemory(expiry_s=1e9, merge_radius_m=0.2, max_points=size + 100)
        xy = rng.uniform(-8.0, 8.0, (size, 2))
        mem.add(np.column_stack([xy, np.full(size, -5.0)]), t_s=0.0, spread_m=np.full(size, 0.35))
        clear = partial(mem.clear_observed, free, pose, clear_scans=10**9)
        rows.append((f"ObstacleMemory({size} near, spread 0.35).clear_observed(72 free)", _time(clear, rep)))

    # A 360-beam lidar seeing a wall arc at 10 m every cycle (8.7 cm between points): steady-state re-add.
    b = np.linspace(-math.pi / 2, math.pi / 2, 360)
    arc = np.column_stack([10.0 * np.cos(b), 10.0 * np.sin(b), np.full(360, -5.0)])
    mem = ObstacleMemory(expiry_s=1e9, merge_radius_m=0.2, max_points=2000)
    mem.add(arc, t_s=0.0)
    rows.append(("ObstacleMemory.add(360 arc, steady)", _time(partial(mem.add, arc + 0.01, 1.0), rep)))

    rows.extend(_surface_fill_rows(rep))

    width = max(len(name) for name, _ in rows)
    print(f"{'operation':<{width}}  {'p50 us':>9}  {'p99 us':>9}")
    for name, (p50, p99) in rows:
        print(f"{name:<{width}}  {p50:9.1f}  {p99:9.1f}")


def _wall_scan(n: int, face_distance_m: float) -> tuple[RangeScan, Pose]:
    """A full-circle n-element scan of a straight wall ``face_distance_m`` north of the vehicle (exact rays)."""
    b = np.linspace(0.0, 2.0 * math.pi, n, endpoint=False)
    with np.errstate(divide="ignore"):
        r = np.where(np.cos(b) > 0.0, face_distance_m / np.cos(b), np.inf)
    r = np.where(r > 8.0, np.inf, r)
    scan = RangeScan(t_s=0.0, frame=ScanFrame.LOCAL_NED, bearings_rad=b, ranges_m=r, range_min_m=0.2, range_max_m=8.0)
    return scan, Pose(t_s=0.0, pos_ned_m=np.array([0.0, 0.0, -5.0]), yaw_rad=0.0)


def _surface_fill_rows(rep: int) -> list[tuple[str, tuple[float, float]]]:
    """Surface fill: the function alone, and a scan's placement + memory write without and with it."""
    rows: list[tuple[str, tuple[float, float]]] = []
    for n in (72, 360):
        scan, pose = _wall_scan(n, 0.5)
        rows.append((f"surface_fill_points({n}, wall 0.5 m)", _time(partial(surface_fill_points, scan, pose), rep)))
        mem = ObstacleMemory(expiry_s=1e9, merge_radius_m=0.2, max_points=2000)

        def place(fill: bool, scan: RangeScan = scan, pose: Pose = pose, mem: ObstacleMemory = mem) -> None:
            pts = scan_to_points_ned(scan, pose)
            spread = return_spread_m(scan)
            if fill:
                fill_pts = surface_fill_points(scan, pose)
                pts = np.concatenate([pts, fill_pts])
                spread = np.concatenate([spread, np.zeros(fill_pts.shape[0])])
            mem.clear_observed(scan, pose)
            mem.add(pts, 1.0, spread_m=spread)

        place(True)
        npts = scan_to_points_ned(scan, pose).shape[0]
        nfill = surface_fill_points(scan, pose).shape[0]
        rows.append((f"place+clear+add({n}: {npts} returns)", _time(partial(place, False), rep)))
        rows.append((f"place+fill+clear+add({n}: +{nfill} filled)", _time(partial(place, True), rep)))
    return rows


if __name__ == "__main__":
    main()
