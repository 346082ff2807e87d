"""How far the service placed its newest scan's returns from the true surfaces, binned by the vehicle's yaw rate.

Run: ``OPENBLAS_NUM_THREADS=1 python benchmarks/scan_placement.py DIR WORLD`` after
``apf-sim fly --world WORLD --trials N --out DIR`` (it reads every ``DIR/seed-*/*.mcap`` the service recorded).
Not collected by pytest. For every third NAVIGATING cycle: the newest scan's points (``Topic.SCAN``, local NED)
and their distance to the nearest true surface of WORLD; the worst point of the scan is one sample. The yaw rate is
the cycle pose's yaw differentiated over the cycle times. Printed per bin: the number of cycles and the median and
90th percentile of the worst point's distance. A sector return lies up to range x sin(2.5 deg) off the surface it
saw (0.21 m at 5 m), so that is the floor; anything above it that grows with the yaw rate is a pose whose yaw is
not the one the scan was measured at (docs/perception.md, "Pose at measurement time").
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np

from apf_companion.viz import Topic
from sim.mcap_plot import cloud_columns, read_recording
from sim.world import load_world
from sim.world.files import example_world_path
from sim.world.geometry import clearance_many_m

BINS_DEG_S = ((0.0, 2.0), (2.0, 10.0), (10.0, 30.0), (30.0, float("inf")))
EVERY = 3  # cycles between samples


def samples(mcap: Path, world_name: str) -> list[tuple[float, float]]:
    """(yaw rate [deg/s], worst scan point's distance to a true surface [m]) per sampled cycle."""
    world = load_world(example_world_path(world_name))
    rec = read_recording(mcap)
    cycles = [(t, c) for t, c in rec.topics[Topic.CYCLE] if c.get("yaw_rad") is not None]
    if len(cycles) < 2:
        return []
    t_s = np.array([c["t_s"] for _, c in cycles])
    yaw = np.unwrap(np.array([c["yaw_rad"] for _, c in cycles]))
    rate = np.degrees(np.abs(np.gradient(yaw, t_s)))
    out = []
    for i, (t_ns, c) in enumerate(cycles):
        if i % EVERY or c["state"] != "NAVIGATING":
            continue
        scan = cloud_columns(rec.at(Topic.SCAN, t_ns), ("x", "y"))
        if len(scan):
            out.append((float(rate[i]), float(np.max(clearance_many_m(world, scan)))))
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("out_dir", type=Path, help="the --out directory of apf-sim fly")
    ap.add_argument("world", help="the bundled world flown (--world)")
    args = ap.parse_args()
    rows = [s for f in sorted(args.out_dir.glob("seed-*/*.mcap")) for s in samples(f, args.world)]
    if not rows:
        raise SystemExit(f"no recorded cycles under {args.out_dir}/seed-*/")
    r = np.array(rows)
    for lo, hi in BINS_DEG_S:
        m = (r[:, 0] >= lo) & (r[:, 0] < hi)
        if m.any():
            print(
                f"yaw rate {lo:4.0f}-{hi:<4.0f} deg/s: {int(m.sum()):5d} cycles, worst scan point off the surface "
                f"median {np.median(r[m, 1]):.2f} m, p90 {np.percentile(r[m, 1], 90):.2f} m"
            )


if __name__ == "__main__":
    main()
