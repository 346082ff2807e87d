"""How porous is a remembered wall? The sim's 72 x 5-degree range sensor -> scan_to_points_ned -> ObstacleMemory
(merge radius 0.2 m, clearing by observed free space), replayed along a straight wall.

Measured (issue 7, "wall returns merged at 0.2 m may leave the remembered wall porous: check"): the gaps come
from the sensor's angular sampling (one point per 5-degree sector, so the spacing along a wall grows as
d / cos^2 of the angle off abeam), not from the 0.2 m merge. Within 2 m of abeam they stay below 0.7 m; within
3 m they reach 0.54 m at 1 m from the wall and 0.80 m at 0.5 m, wider than 2 * (0.25 m + 0.1 m): a point-based
planner's clearance check would let a segment through the wall there.
"""

from __future__ import annotations

import math

import numpy as np
import pytest

from apf_companion.perception import ObstacleMemory
from apf_companion.perception.geometry import scan_to_points_ned
from apf_companion.perception.types import Pose, RangeScan, ScanFrame
from sim.world import World

SECTORS_RAD = np.deg2rad(5.0 * np.arange(72))
WALL = World.from_obstacles(walls_ne_m=[[[10.0, -20.0], [10.0, 20.0]]], wall_thickness_m=0.2)
PASSABLE_M = 2.0 * (0.25 + 0.1)  # collision radius + a 0.1 m margin, both sides


def _observe(memory: ObstacleMemory, pos_ne: tuple[float, float], t_s: float) -> None:
    ranges = WALL.window_ranges_m(pos_ne, SECTORS_RAD, math.radians(2.5))
    ranges = np.where(ranges > 8.0, np.inf, ranges)
    scan = RangeScan(
        t_s=t_s, frame=ScanFrame.LOCAL_NED, bearings_rad=SECTORS_RAD, ranges_m=ranges, range_min_m=0.2, range_max_m=8.0
    )
    pose = Pose(t_s=t_s, pos_ned_m=np.array([pos_ne[0], pos_ne[1], -5.0]), yaw_rad=0.0)
    memory.clear_observed(scan, pose)
    memory.add(scan_to_points_ned(scan, pose), t_s)


def _largest_gap_m(memory: ObstacleMemory, t_s: float, east_m: float, reach_m: float) -> float:
    """Largest gap between neighbouring remembered wall points within ``reach_m`` of ``east_m`` along the wall."""
    pts = memory.points(t_s)
    on_wall = (np.abs(pts[:, 0] - 10.0) < 0.5) & (np.abs(pts[:, 1] - east_m) <= reach_m)
    along = np.sort(pts[on_wall, 1])
    assert along.size >= 2
    return float(np.diff(along).max())


def _fly_along(face_distance_m: float, reach_m: float) -> float:
    """Worst largest gap while flying along the wall at 0.2 m per scan (2 m/s at 10 Hz)."""
    memory = ObstacleMemory(expiry_s=10.0, merge_radius_m=0.2)
    worst = 0.0
    for k in range(80):
        east = -8.0 + 0.2 * k
        _observe(memory, (9.9 - face_distance_m, east), 0.1 * k)
        if k >= 20:
            worst = max(worst, _largest_gap_m(memory, 0.1 * k, east, reach_m))
    return worst


@pytest.mark.parametrize("face_distance_m", [0.5, 1.0, 2.0])
def test_remembered_wall_is_tight_within_two_metres_of_abeam(face_distance_m: float) -> None:
    assert _fly_along(face_distance_m, reach_m=2.0) < PASSABLE_M


def test_remembered_wall_gaps_three_metres_along_at_one_metre() -> None:
    gap = _fly_along(1.0, reach_m=3.0)
    assert 0.3 < gap < PASSABLE_M  # measured 0.54 m


@pytest.mark.xfail(strict=True, reason="porous wall: 0.80 m gaps 3 m along when 0.5 m from it (sector sampling)")
def test_remembered_wall_has_no_passable_gap_within_three_metres_when_close() -> None:
    assert _fly_along(0.5, reach_m=3.0) < PASSABLE_M
