"""Replay a flight's bapf-nav decisions from the service's recording, and print the planner's state at each plan.

Run: ``OPENBLAS_NUM_THREADS=1 python benchmarks/replay_decisions.py FLY_OUT/seed-N --goal N,E [--from S --to S]``
after ``apf-sim fly ... --out FLY_OUT`` with the ``viz`` extra (the service writes ``apf-*.mcap`` there). Not
collected by pytest. At every cycle that made a new plan (``/apf/cycle``'s ``plan_seq`` changes), the pose of that
cycle and the last remembered obstacles before it (``/apf/obstacles``) go to a fresh planner's ``step``, in
order. Printed per plan: the time, the pose, the recorded step and the replayed one, the planner's mode and how
many steps old its escape field is (0-1: recomputed for this step). Made to read a dither in
``apf-sim fly --world rooms`` (docs/planner.md, "A flying area"); the replay repeats the recorded steps where the
obstacles were recorded in the same cycle.
"""

from __future__ import annotations

import argparse
import os
from pathlib import Path

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import numpy as np

from apf_companion.planning import NavMode, NavState, PlannerParams, StatefulPlanner, get_planner
from apf_companion.viz import Topic
from sim.mcap_plot import cloud_columns, read_recording


def _pair(text: str) -> tuple[float, float]:
    north, east = (float(v) for v in text.split(","))
    return north, east


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("run", type=Path, help="a flight's output directory (holds apf-*.mcap)")
    ap.add_argument("--goal", type=_pair, required=True, metavar="N,E", help="the flight's goal (local NED m)")
    ap.add_argument("--from", dest="t_from", type=float, default=0.0, help="print plans from this time [s]")
    ap.add_argument("--to", dest="t_to", type=float, default=float("inf"), help="... up to this time [s]")
    args = ap.parse_args(argv)
    recordings = sorted(args.run.glob("apf-*.mcap"))
    if not recordings:
        ap.error(f"{args.run}: no apf-*.mcap (fly with the viz extra installed)")
    rec = read_recording(recordings[0])
    cycles = rec.topics[Topic.CYCLE.value]
    clouds = rec.topics.get(Topic.OBSTACLES.value, [])
    cloud_t = np.array([t for t, _ in clouds], dtype=np.int64)
    planner = get_planner("bapf-nav", PlannerParams())
    assert isinstance(planner, StatefulPlanner)
    goal = np.array(args.goal)
    last_seq = None
    print("| t (s) | pose (N, E) | recorded setpoint | replayed step | mode | field age (steps) | points |")
    print("|---|---|---|---|---|---|---|")
    for t, cycle in cycles:
        if cycle["plan_seq"] == last_seq:
            continue
        last_seq = cycle["plan_seq"]
        k = int(np.searchsorted(cloud_t, t, side="right")) - 1
        points = cloud_columns(clouds[k][1], ("x", "y")) if k >= 0 else np.zeros((0, 2))
        pose = np.array(cycle["pose_ned_m"][:2])
        decision = planner.step(pose, goal, points)
        state = planner.own_state
        assert isinstance(state, NavState)
        if not args.t_from <= cycle["t_s"] <= args.t_to:
            continue
        sp = cycle.get("setpoint")
        recorded = "-" if not isinstance(sp, dict) else str(np.round(sp.get("pos_ned_m", [np.nan] * 2)[:2], 2))
        step = "-" if decision.next_point_m is None else str(np.round(decision.next_point_m, 2))
        mode = NavMode(int(state.mode[0])).name
        print(
            f"| {cycle['t_s']:.1f} | {np.round(pose, 2)} | {recorded} | {step} | {mode} | "
            f"{int(state.since_field[0])} | {points.shape[0]} |"
        )
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
