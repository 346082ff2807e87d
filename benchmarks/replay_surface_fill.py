"""Replay the service's perception along a path through the bundled worlds, with and without surface fill.

Run: ``OPENBLAS_NUM_THREADS=1 python benchmarks/replay_surface_fill.py [--world NAME ...] [--clearance 0.4]``.
Not collected by pytest. For each world: the full-knowledge shortest path keeping ``--clearance`` from the true
obstacles (``sim.study.optimal.optimal_path``) is flown at 0.2 m per scan (2 m/s at 10 Hz); each scan is the
simulator's 72 x 5-degree sector sensor (nearest surface in each window, 8 m) and goes through the service's
``PerceptionFrontEnd`` (clearing, surface fill as set, memory merge 0.2 m, expiry 10 s). Printed per world and
setting, over all steps:

- ``hole``: the largest distance from a true-surface sample within ``--reach`` of the vehicle, in line of
  sight and seen at most 83 degrees off its normal, to the nearest remembered point (worst step). A hole wider
  than 0.35 m is a gap of more than 2 x (0.25 m + 0.1 m) in the remembered surface, which a point-based
  clearance check lets a path through (or a surface the sensor reports only at grazing, a corner or an
  occlusion edge).
- ``steps>0.35``: the fraction of steps with such a hole.
- ``free>0.2``: remembered points within the reach lying more than 0.2 m from every true surface (obstacles
  where there are none; the sector returns themselves sit up to about 0.2 m off a wall seen obliquely), summed
  over the steps.

``--trajectory sim_result.json`` (with one ``--world``): replay a flown trajectory instead (the
``trajectory_ned_m`` that ``apf-sim fly --out DIR`` writes to ``DIR/sim_result.json``, one scan per sample).

``--rules``: instead, the fill of single scans at 300 random free positions per world, with the rule's both-sides
condition and with one side only: fill points per scan, and how many lie more than 0.3 m (0.2 m) from every
true surface.
"""

from __future__ import annotations

import argparse
import json
import math
import time

import numpy as np

from apf_companion.perception import (
    PerceptionFrontEnd,
    PerceptionParams,
    Pose,
    RangeScan,
    ScanFrame,
    surface_fill_points,
)
from apf_companion.perception.types import FloatArray
from sim.study.optimal import optimal_path
from sim.world import World, load_world
from sim.world.files import example_world_path
from sim.world.geometry import clearance_many_m, surface_samples_ne_m

SECTORS_RAD = np.deg2rad(5.0 * np.arange(72))
STEP_M = 0.2
HOLE_M = 0.35  # half of 2 x (0.25 m collision radius + 0.1 m margin)
WORLDS = ("wall-gap", "u-trap-goal", "rooms", "corridor-bend", "forest-dense", "forest")


def _resample(path_ne: FloatArray, step_m: float) -> FloatArray:
    seg = np.hypot(*np.diff(path_ne, axis=0).T)
    s = np.concatenate([[0.0], np.cumsum(seg)])
    at = np.arange(0.0, s[-1], step_m)
    return np.column_stack([np.interp(at, s, path_ne[:, 0]), np.interp(at, s, path_ne[:, 1])])


def _surface_with_tangents(world: World, spacing_m: float) -> tuple[FloatArray, FloatArray]:
    """True-surface samples and unit tangents (from the neighbouring samples along each outline)."""
    samples = surface_samples_ne_m(world, spacing_m)
    t = np.roll(samples, -1, axis=0) - np.roll(samples, 1, axis=0)
    norm = np.hypot(t[:, 0], t[:, 1])
    ok = norm <= 3.0 * spacing_m  # both neighbours on the same outline
    return samples[ok], t[ok] / norm[ok, None]


def _visible(world: World, pos: FloatArray, samples: FloatArray, tangents: FloatArray) -> FloatArray:
    """Samples in line of sight, seen at most 83 degrees off the surface normal (a wall is then measured up to
    8 x the distance along it, as in docs/worlds.md's porosity table; beyond that no 5-degree sensor resolves it)."""
    rel = samples - pos
    dist = np.hypot(rel[:, 0], rel[:, 1])
    ray = world.ray_cast_m(pos, np.arctan2(rel[:, 1], rel[:, 0]))
    # Rays stop at a wall's centre line: a face sample is visible when nothing is hit well before it.
    along = np.abs(np.einsum("ij,ij->i", rel, tangents)) / np.maximum(dist, 1e-9)
    keep = (ray >= dist - 0.05) & (along <= math.cos(math.radians(7.0)))
    return np.asarray(samples[keep], dtype=np.float64)


def replay(world: World, path_ne: FloatArray, *, fill: bool, reach_m: float) -> tuple[float, float, int]:
    front = PerceptionFrontEnd(PerceptionParams(memory_expiry_s=10.0, max_range_m=8.0, surface_fill=fill))
    front.on_attitude(0.0)
    surface, tangents = _surface_with_tangents(world, 0.05)
    worst, holed, free = 0.0, 0, 0
    for k, pos in enumerate(path_ne):
        t_s = 0.1 * k
        front.on_local_position(1000 + 100 * k, (pos[0], pos[1], -5.0), t_s)
        r = world.window_ranges_m(pos, SECTORS_RAD, math.radians(2.5))
        r = np.where(r > 8.0, np.inf, r)
        front.on_scan(
            RangeScan(
                t_s=t_s,
                frame=ScanFrame.LOCAL_NED,
                bearings_rad=SECTORS_RAD,
                ranges_m=r,
                range_min_m=0.2,
                range_max_m=8.0,
            )
        )
        pts = front.points(t_s)[:, :2]
        near = np.hypot(*(surface - pos).T) <= reach_m
        vis = _visible(world, pos, surface[near], tangents[near])
        if vis.shape[0] and pts.shape[0]:
            d2 = ((vis[:, None, :] - pts[None, :, :]) ** 2).sum(axis=2)
            hole = float(np.sqrt(d2.min(axis=1)).max())
            worst = max(worst, hole)
            holed += hole > HOLE_M
        near_p = pts[np.hypot(*(pts - pos).T) <= reach_m]
        if near_p.shape[0]:
            free += int(np.count_nonzero(clearance_many_m(world, near_p) > 0.2))
    return worst, holed / max(len(path_ne), 1), free


def compare_rules(name: str, positions: int = 300) -> None:
    """Single-scan fill at random free positions: both sides collinear (the rule) vs one side."""
    world = load_world(example_world_path(name))
    rng = np.random.default_rng(0)
    placed = 0
    filled = {True: 0, False: 0}
    off_03 = {True: 0, False: 0}
    off_02 = {True: 0, False: 0}
    while placed < positions:
        pos = rng.uniform([-5.0, -12.0], [30.0, 12.0])
        if clearance_many_m(world, pos)[0] < 0.3:
            continue
        placed += 1
        r = world.window_ranges_m(pos, SECTORS_RAD, math.radians(2.5))
        scan = RangeScan(
            t_s=0.0,
            frame=ScanFrame.LOCAL_NED,
            bearings_rad=SECTORS_RAD,
            ranges_m=np.where(r > 8.0, np.inf, r),
            range_min_m=0.2,
            range_max_m=8.0,
        )
        pose = Pose(t_s=0.0, pos_ned_m=np.array([pos[0], pos[1], -5.0]), yaw_rad=0.0)
        for both in (True, False):
            fill = surface_fill_points(scan, pose, both_sides=both)
            filled[both] += fill.shape[0]
            if fill.shape[0]:
                c = clearance_many_m(world, fill[:, :2])
                off_03[both] += int(np.count_nonzero(c > 0.3))
                off_02[both] += int(np.count_nonzero(c > 0.2))
    for both in (True, False):
        rule = "both sides" if both else "one side"
        print(f"{name:<14} {rule:<10} {filled[both] / positions:6.1f} {off_03[both]:8d} {off_02[both]:8d}")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--world", action="append", choices=WORLDS)
    parser.add_argument("--clearance", type=float, default=0.4, help="path clearance from true obstacles [m]")
    parser.add_argument("--reach", type=float, default=3.0, help="measure within this of the vehicle [m]")
    parser.add_argument("--rules", action="store_true", help="compare the both-sides rule with one side")
    parser.add_argument("--trajectory", help="sim_result.json of an apf-sim fly run (replay it instead)")
    args = parser.parse_args()
    if args.rules:
        print("300 random free positions per world, one 72 x 5-degree scan each")
        print(f"{'world':<14} {'rule':<10} {'fill/scan':>6} {'>0.3 m':>8} {'>0.2 m':>8}")
        for name in args.world or WORLDS:
            compare_rules(name)
        return
    source = args.trajectory or f"shortest paths at clearance {args.clearance} m, {STEP_M} m per scan"
    print(f"{source}, reach {args.reach} m")
    print(f"{'world':<14} {'steps':>5}  {'fill':<5} {'hole m':>7} {'steps>0.35':>10} {'free>0.2':>8}")
    for name in args.world or WORLDS:
        world = load_world(example_world_path(name))
        if args.trajectory:
            with open(args.trajectory, encoding="utf-8") as f:
                steps = np.asarray(json.load(f)["trajectory_ned_m"], dtype=np.float64)[:, :2]
        else:
            path = optimal_path(world, clearance_m=args.clearance)
            if path.path_ne_m.shape[0] == 0:
                print(f"{name:<14} no path at clearance {args.clearance} m")
                continue
            steps = _resample(path.path_ne_m, STEP_M)
        for fill in (False, True):
            t0 = time.perf_counter()
            hole, frac, free = replay(world, steps, fill=fill, reach_m=args.reach)
            took = time.perf_counter() - t0
            print(f"{name:<14} {len(steps):>5}  {fill!s:<5} {hole:7.2f} {frac:10.1%} {free:8d}   ({took:.1f} s)")


if __name__ == "__main__":
    main()
