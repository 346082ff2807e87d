"""OBSTACLE_DISTANCE forwarding's encoding: remembered points in local NED -> 72 body-FRD sectors [cm], checked
against hand-computed geometry and the rules AP_Proximity_MAV.cpp reads them with."""

from __future__ import annotations

import math

import numpy as np

from apf_companion.perception import FORWARD_SECTORS, obstacle_sectors_cm
from apf_companion.perception.forward import MIN_DISTANCE_CM, UINT16_MAX


def _at(bearing_deg: float, dist_m: float, down_m: float = -5.0) -> list[float]:
    b = math.radians(bearing_deg)
    return [dist_m * math.cos(b), dist_m * math.sin(b), down_m]


def test_sectors_are_body_frd_and_hold_the_nearest_point() -> None:
    # vehicle at (0, 0, -5) heading 90 deg (east). A point 3 m east (world 90 deg) is dead ahead: sector 0.
    # Two points at world 180 deg (south, body 90 deg: sector 18), 4 m and 2.5 m: the nearer wins.
    # A point at world 92.4 deg (body 2.4 deg) is still sector 0 (within 2.5 deg), one at body 2.6 deg is sector 1.
    pts = np.array([_at(90, 3.0), _at(180, 4.0), _at(180, 2.5), _at(92.6, 5.0), _at(92.4, 6.0)])
    out = obstacle_sectors_cm(
        pts, np.array([0.0, 0.0, -5.0]), math.pi / 2, max_range_m=8.0, height_window_m=1.0, measured=lambda b: True
    )
    assert len(out.distances_cm) == FORWARD_SECTORS
    assert (out.min_distance_cm, out.max_distance_cm) == (MIN_DISTANCE_CM, 800)
    assert out.distances_cm[0] == 300
    assert out.distances_cm[18] == 250
    assert out.distances_cm[1] == 500
    free = [d for j, d in enumerate(out.distances_cm) if j not in (0, 1, 18)]
    assert free == [801] * (FORWARD_SECTORS - 3)  # measured and empty: max_distance + 1 = "no obstacle"
    assert out.obstacles == 3


def test_height_range_clamping_and_unknown() -> None:
    pos = np.array([10.0, -4.0, -5.0])

    def rel(bearing_deg: float, dist_m: float, dz: float = 0.0) -> list[float]:
        p = _at(bearing_deg, dist_m, 0.0)
        return [pos[0] + p[0], pos[1] + p[1], pos[2] + dz]

    pts = np.array(
        [
            rel(0, 2.0, dz=1.5),  # above the height window: left out
            rel(45, 9.0),  # beyond max_range: left out
            rel(90, 0.05),  # touching: clamped up to min_distance, still an obstacle
            [math.nan, 0.0, -5.0],  # not finite: left out
        ]
    )
    measured = {0, 9}  # only sectors 0 and 9 were measured recently (heading 0: body = world)

    def fresh(bearing_ned_rad: float) -> bool:
        return round(math.degrees(bearing_ned_rad) / 5.0) % 72 in measured

    out = obstacle_sectors_cm(pts, pos, 0.0, max_range_m=8.0, height_window_m=1.0, measured=fresh)
    assert out.distances_cm[18] == MIN_DISTANCE_CM
    assert out.distances_cm[0] == 801 and out.distances_cm[9] == 801  # measured, nothing there
    assert out.distances_cm[5] == UINT16_MAX  # never measured: unknown, not free
    assert out.obstacles == 1


def test_empty_memory_and_long_range_limit() -> None:
    out = obstacle_sectors_cm(
        np.empty((0, 3)), np.zeros(3), 0.3, max_range_m=1000.0, height_window_m=1.0, measured=lambda b: True
    )
    assert out.max_distance_cm == UINT16_MAX - 2  # uint16, and max + 1 stays below "unknown"
    assert set(out.distances_cm) == {UINT16_MAX - 1}
