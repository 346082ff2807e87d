"""How porous is a remembered wall? The sim's 72 x 5-degree range sensor -> scan_to_points_ned -> ObstacleMemory
(merge radius 0.2 m, clearing by observed free space), replayed along a straight wall.

Measured (issue 7, "wall returns merged at 0.2 m may leave the remembered wall porous: check"): the gaps come
from the sensor's angular sampling (one point per 5-degree sector, so the spacing along a wall grows as
d / cos^2 of the angle off abeam), not from the 0.2 m merge. Within 2 m of abeam they stay below 0.7 m; within
3 m they reached 0.54 m at 1 m from the wall and 0.80 m at 0.5 m, wider than 2 * (0.25 m + 0.1 m): a point-based
planner's clearance check would let a segment through the wall there.

Session 18: the memory refreshes a point in place (it was replaced by the newest one, which dragged a wall's points
along) and the service gives each return its window's spread, so a beam along the wall no longer clears it. Without
that spread (``_fly_along``: 0.40 m at 1 m, 1.00 m at 0.5 m) clearing still opens the wall; through the service it
stays closed near the vehicle and behind it (docs/perception.md, "Walls seen along their length").
"""

from __future__ import annotations

import math

import numpy as np
import pytest

from apf_companion.perception import ObstacleMemory, PerceptionFrontEnd, PerceptionParams
from apf_companion.perception.geometry import scan_to_points_ned
from apf_companion.perception.types import Pose, RangeScan, ScanFrame
from sim.world import World

SECTORS_RAD = np.deg2rad(5.0 * np.arange(72))
WALL = World.from_obstacles(walls_ne_m=[[[10.0, -20.0], [10.0, 20.0]]], wall_thickness_m=0.2)
PASSABLE_M = 2.0 * (0.25 + 0.1)  # collision radius + a 0.1 m margin, both sides


def _scan(pos_ne: tuple[float, float], t_s: float) -> RangeScan:
    ranges = WALL.window_ranges_m(pos_ne, SECTORS_RAD, math.radians(2.5))
    ranges = np.where(ranges > 8.0, np.inf, ranges)
    return RangeScan(
        t_s=t_s, frame=ScanFrame.LOCAL_NED, bearings_rad=SECTORS_RAD, ranges_m=ranges, range_min_m=0.2, range_max_m=8.0
    )


def _observe(memory: ObstacleMemory, pos_ne: tuple[float, float], t_s: float) -> None:
    """The sector points alone (no surface fill), as measured for issue 7."""
    scan = _scan(pos_ne, t_s)
    pose = Pose(t_s=t_s, pos_ned_m=np.array([pos_ne[0], pos_ne[1], -5.0]), yaw_rad=0.0)
    memory.clear_observed(scan, pose)
    memory.add(scan_to_points_ned(scan, pose), t_s)


def _largest_gap_m(points: np.ndarray, east_m: float, reach_m: float) -> float:
    """Largest gap between neighbouring remembered wall points within ``reach_m`` of ``east_m`` along the wall."""
    on_wall = (np.abs(points[:, 0] - 10.0) < 0.5) & (np.abs(points[:, 1] - east_m) <= reach_m)
    along = np.sort(points[on_wall, 1])
    assert along.size >= 2
    return float(np.diff(along).max())


def _fly_along(face_distance_m: float, reach_m: float) -> float:
    """Worst largest gap while flying along the wall at 0.2 m per scan (2 m/s at 10 Hz), sector points only."""
    memory = ObstacleMemory(expiry_s=10.0, merge_radius_m=0.2)
    worst = 0.0
    for k in range(80):
        east = -8.0 + 0.2 * k
        _observe(memory, (9.9 - face_distance_m, east), 0.1 * k)
        if k >= 20:
            worst = max(worst, _largest_gap_m(memory.points(0.1 * k), east, reach_m))
    return worst


def _fly_along_service(face_distance_m: float, reach_m: float, *, surface_fill: bool = True) -> float:
    """The same flight through the service's perception front end (poses, scans, surface fill as configured)."""
    front = PerceptionFrontEnd(PerceptionParams(memory_expiry_s=10.0, surface_fill=surface_fill))
    front.on_attitude(0.0)
    worst = 0.0
    for k in range(80):
        east, t_s = -8.0 + 0.2 * k, 0.1 * k
        pos_ne = (9.9 - face_distance_m, east)
        assert front.on_local_position(1000 + 100 * k, (pos_ne[0], pos_ne[1], -5.0), t_s) is not None
        front.on_scan(_scan(pos_ne, t_s))
        if k >= 20:
            worst = max(worst, _largest_gap_m(front.points(t_s), east, reach_m))
    return worst


@pytest.mark.parametrize("face_distance_m", [0.5, 1.0, 2.0])
def test_remembered_wall_is_tight_within_two_metres_of_abeam(face_distance_m: float) -> None:
    assert _fly_along(face_distance_m, reach_m=2.0) < PASSABLE_M


def test_remembered_wall_gaps_three_metres_along_at_one_metre() -> None:
    gap = _fly_along(1.0, reach_m=3.0)
    assert 0.3 < gap < PASSABLE_M  # measured 0.40 m (0.54 m with the replacing memory, to session 17)


def test_sector_points_alone_leave_a_passable_gap_three_metres_along_when_close() -> None:
    gap = _fly_along(0.5, reach_m=3.0)
    assert gap > PASSABLE_M  # measured 1.00 m: one point per window, each cleared by a later beam past it
    # The service places each return with its window's spread, so a beam along the wall no longer clears it
    # (memory.py), and the points stay where first seen: without fill, 0.65 m.
    assert _fly_along_service(0.5, reach_m=3.0, surface_fill=False) < PASSABLE_M


def _gap_behind_m(face_distance_m: float, *, surface_fill: bool = True) -> float:
    """Fly 16 m along the wall (0.2 m per scan); the largest gap between neighbouring remembered wall points over
    everything passed since the start, from the second half of the flight on."""
    front = PerceptionFrontEnd(PerceptionParams(memory_expiry_s=10.0, surface_fill=surface_fill))
    front.on_attitude(0.0)
    worst = 0.0
    for k in range(80):
        east, t_s = -8.0 + 0.2 * k, 0.1 * k
        assert front.on_local_position(1000 + 100 * k, (9.9 - face_distance_m, east, -5.0), t_s) is not None
        front.on_scan(_scan((9.9 - face_distance_m, east), t_s))
        if k >= 40:
            pts = front.points(t_s)
            along = np.sort(pts[(np.abs(pts[:, 0] - 10.0) < 0.5) & (pts[:, 1] >= -8.0) & (pts[:, 1] <= east), 1])
            worst = max(worst, float(np.diff(along).max()))
    return worst


@pytest.mark.parametrize("face_distance_m", [0.3, 0.5, 1.0, 2.0])
def test_the_wall_behind_the_vehicle_stays_closed(face_distance_m: float) -> None:
    # Issue 7's wall-gap flights: the wall already passed was seen again only at grazing incidence, its points
    # were cleared or dragged along, and 1.2-1.85 m holes opened behind the vehicle (measured on the replacing
    # memory); the planner then turned back to them. Measured now: 0.34-0.40 m.
    assert _gap_behind_m(face_distance_m) < PASSABLE_M


@pytest.mark.parametrize("face_distance_m", [0.5, 1.0, 2.0])
def test_remembered_wall_has_no_passable_gap_within_three_metres_with_surface_fill(face_distance_m: float) -> None:
    gap = _fly_along_service(face_distance_m, reach_m=3.0)
    assert gap < PASSABLE_M  # measured 0.44-0.51 m (0.22-0.23 m with the replacing memory, to session 17)
