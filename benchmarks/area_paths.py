"""bapf-nav's path through a walled world from shifted starts, with and without the world file's flying area.

Run: ``OPENBLAS_NUM_THREADS=1 python benchmarks/area_paths.py [--world wall-gap] [--shifts=-8,-5,-2,0,2,4]``
(``--shifts=...`` with the equals sign: a list that starts with a minus is otherwise taken for an option). Not
collected by pytest. The flights are ``tests/planning/test_planning_nav.py``'s harness: the planner's own ``step``
with ``sim.world.scan.ScanMemory``, a ray-cast scanner of 72 rays (5 degrees) reaching 8 m, every return remembered
(merged on a 0.1 m lattice), no noise. Start and goal are the world file's, moved east by each shift, so that either
end of a long wall can be the nearer one. Printed per shift: how each flight ended, its path (m) and how far west it
got (m east); then the mean path of each column. The world file must give ``area_ne_m`` (wall-gap and rooms do; a
file path works too).
"""

from __future__ import annotations

import argparse
import os

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import numpy as np
import numpy.typing as npt

from apf_companion.planning import DecisionReason, PlannerParams, get_planner
from sim.world import World, load_world
from sim.world.scan import ScanMemory

FloatArray = npt.NDArray[np.float64]
GOAL_RADIUS_M = 0.7


def fly(world: World, shift_east_m: float, *, area: bool, max_steps: int = 1500) -> tuple[str, float, float]:
    """(how it ended, path length [m], westmost east coordinate [m]) of one flight."""
    planner = get_planner("bapf-nav", PlannerParams(nav_area_ne_m=world.area_ne_m if area else None))
    assert world.start_ne_m is not None and world.goal_ne_m is not None
    shift = np.array([0.0, shift_east_m])
    pos: FloatArray = np.array(world.start_ne_m) + shift
    goal = np.array(world.goal_ne_m) + shift
    scanner = ScanMemory(world)
    path_m, west_m = 0.0, float(pos[1])
    for _ in range(max_steps):
        if np.linalg.norm(pos - goal) <= GOAL_RADIUS_M:
            return "arrived", path_m, west_m
        cloud = scanner.scan(pos)
        decision = planner.step(pos, goal, cloud)
        if decision.reason is DecisionReason.GAVE_UP:
            return "gave up", path_m, west_m
        if decision.next_point_m is not None:
            path_m += float(np.linalg.norm(decision.next_point_m - pos))
            pos = decision.next_point_m
            west_m = min(west_m, float(pos[1]))
    return "running", path_m, west_m


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--world", default="wall-gap", help="bundled world or file with area_ne_m (default wall-gap)")
    ap.add_argument("--shifts", default="-8,-5,-2,0,2,4", help="east shifts of start and goal [m] (--shifts=-2,0,2)")
    args = ap.parse_args(argv)
    world = load_world(args.world)
    if world.area_ne_m is None:
        ap.error(f"{args.world}: the world file gives no area_ne_m")
    shifts = [float(x) for x in args.shifts.split(",")]
    print(f"{world.name}: flying area {list(world.area_ne_m)}, start {world.start_ne_m}, goal {world.goal_ne_m}\n")
    print("| shift east (m) | over the area: end, path (m), westmost (m) | without: end, path (m), westmost (m) |")
    print("|---|---|---|")
    totals = {True: 0.0, False: 0.0}
    for shift in shifts:
        cells = []
        for area in (True, False):
            end, path_m, west_m = fly(world, shift, area=area)
            totals[area] += path_m
            cells.append(f"{end}, {path_m:.1f}, {west_m:.1f}")
        print(f"| {shift:g} | {cells[0]} | {cells[1]} |")
    n = len(shifts)
    print(f"\nmean path: {totals[True] / n:.1f} m over the area, {totals[False] / n:.1f} m without")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
