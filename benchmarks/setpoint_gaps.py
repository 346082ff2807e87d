"""Setpoint gaps at the vehicle in ``apf-sim fly`` outputs, and how far the vehicle went past its last target.

For every flight directory (``OUT`` of one flight, or ``OUT/seed-*`` of a sweep) this reads the vehicle's tlog (every
frame it received and sent) and its result: each gap of at least ``--min-gap`` simulated seconds between two
SET_POSITION_TARGET_LOCAL_NED from the companion, the last setpoint's velocity feed-forward, the furthest the
vehicle went past that setpoint's target along the feed-forward during the gap, and its closest approach to an
obstacle in the gap. This is how docs/faults.md measured the overshoot in link blackouts.

Usage: python benchmarks/setpoint_gaps.py OUT [--speedup 5] [--min-gap 1.0]
"""

from __future__ import annotations

import argparse
import itertools
import json
import math
import os
import sys
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import numpy.typing as npt

os.environ.setdefault("MAVLINK20", "1")
from pymavlink import mavutil  # after MAVLINK20 is set

COMPANION_COMPID = 191
FloatArray = npt.NDArray[np.float64]


@dataclass(frozen=True, slots=True)
class Gap:
    t0_s: float  # simulated time of the last setpoint before the gap (wall time x speed-up)
    gap_s: float
    ff_m_s: float  # horizontal feed-forward speed of the last setpoint
    overshoot_m: float  # furthest past the last target along the feed-forward (0 without feed-forward)
    min_clearance_m: float  # closest obstacle centre during the gap


def _read(tlog: Path, speedup: float) -> tuple[list[tuple[float, FloatArray, FloatArray]], FloatArray, FloatArray]:
    conn = mavutil.mavlink_connection(str(tlog))
    setpoints: list[tuple[float, FloatArray, FloatArray]] = []
    times: list[float] = []
    positions: list[tuple[float, float]] = []
    while True:
        msg = conn.recv_match()
        if msg is None:
            break
        t = float(msg._timestamp) * speedup
        kind = msg.get_type()
        if kind == "SET_POSITION_TARGET_LOCAL_NED" and msg.get_srcComponent() == COMPANION_COMPID:
            setpoints.append((t, np.array([msg.x, msg.y]), np.array([msg.vx, msg.vy])))
        elif kind == "LOCAL_POSITION_NED" and msg.get_srcComponent() == 1:
            times.append(t)
            positions.append((float(msg.x), float(msg.y)))
    return setpoints, np.asarray(times, dtype=np.float64), np.asarray(positions, dtype=np.float64).reshape(-1, 2)


def gaps(flight_dir: Path, speedup: float, min_gap_s: float) -> list[Gap]:
    """The setpoint gaps of one flight (needs ``vehicle.tlog`` and ``sim_result.json`` in ``flight_dir``)."""
    setpoints, t_pos, pos = _read(flight_dir / "vehicle.tlog", speedup)
    world = json.loads((flight_dir / "sim_result.json").read_text()).get("world", {})
    obstacles = np.asarray(world.get("circles_ne_m", []), dtype=np.float64).reshape(-1, 2)
    out: list[Gap] = []
    for (t0, target, ff), (t1, _, _) in itertools.pairwise(setpoints):
        inside = (t_pos >= t0) & (t_pos <= t1)
        if t1 - t0 < min_gap_s or not inside.any():
            continue
        seg = pos[inside]
        speed = float(np.hypot(*ff))
        overshoot = float(np.max((seg - target) @ (ff / speed))) if speed > 1e-6 else 0.0
        clearance = math.inf
        if obstacles.size:
            clearance = float(np.min(np.hypot(*(seg[:, None, :] - obstacles[None]).transpose(2, 0, 1))))
        out.append(Gap(t0, t1 - t0, speed, max(overshoot, 0.0), clearance))
    return out


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("out", type=Path, help="apf-sim fly --out directory (one flight, or a sweep with seed-*/)")
    p.add_argument("--speedup", type=float, default=5.0, help="the flight's --speedup (default 5)")
    p.add_argument("--min-gap", type=float, default=1.0, help="shortest gap reported [simulated s] (default 1)")
    args = p.parse_args(argv)
    dirs = sorted(args.out.glob("seed-*"), key=lambda d: int(d.name.rsplit("-", 1)[1])) or [args.out]
    moving: list[float] = []
    for d in dirs:
        if not (d / "vehicle.tlog").exists() or not (d / "sim_result.json").exists():
            continue
        found = gaps(d, args.speedup, args.min_gap)
        outcome = json.loads((d / "result.json").read_text()).get("outcome") if (d / "result.json").exists() else "?"
        cells = [f"{g.gap_s:.2f} s ff {g.ff_m_s:.2f} m/s past {g.overshoot_m:.2f} m" for g in found]
        print(f"{d.name}: {outcome}; gaps: " + ("; ".join(cells) or "none"))
        moving += [g.overshoot_m for g in found if g.ff_m_s > 0.0]
    if moving:
        print(
            f"{len(moving)} gaps with feed-forward: overshoot past the last target min {min(moving):.2f}, "
            f"median {float(np.median(moving)):.2f}, max {max(moving):.2f} m"
        )
    return 0


if __name__ == "__main__":
    sys.exit(main())
