"""The obstacle memory as the autopilot's proximity sectors: OBSTACLE_DISTANCE's 72 distances, pure.

ArduPilot's ``AP_Proximity_MAV.cpp`` (``handle_obstacle_distance_msg``) reads element ``j`` at the body bearing
``j * increment + angle_offset`` (clockwise from the nose, whatever ``frame`` says), skips 0, UINT16_MAX and
readings outside ``[min_distance, max_distance]``, and replaces its whole boundary with each message. So every
message carries the complete picture, in body FRD: element ``j`` is the nearest remembered point whose body
bearing lies within half a sector of ``j * 5`` deg.

Per sector: the nearest point [cm] (clamped up to ``min_distance``: a point that close is an obstacle, and the
autopilot would drop a smaller value); with no point, ``max_distance + 1`` ("no obstacle", MAVLink) when the
direction was measured recently, else UINT16_MAX ("unknown").
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
import numpy.typing as npt

from apf_companion.perception.types import FloatArray

__all__ = ["FORWARD_SECTORS", "ForwardSectors", "obstacle_sectors_cm"]

FORWARD_SECTORS = 72  # OBSTACLE_DISTANCE.distances
SECTOR_DEG = 5.0  # 360 / 72
MIN_DISTANCE_CM = 10  # smaller ranges are reported as this (the autopilot drops readings below min_distance)
UINT16_MAX = 65535
_MAX_DISTANCE_CM = UINT16_MAX - 2  # max_distance + 1 must stay below UINT16_MAX ("unknown")


@dataclass(frozen=True, slots=True)
class ForwardSectors:
    """One OBSTACLE_DISTANCE's payload: distances [cm] by body sector, and the limits that classify them."""

    distances_cm: tuple[int, ...]
    min_distance_cm: int
    max_distance_cm: int

    @property
    def obstacles(self) -> int:
        """Sectors with an obstacle."""
        return sum(1 for d in self.distances_cm if d <= self.max_distance_cm)


def obstacle_sectors_cm(
    points_ned_m: FloatArray,
    pos_ned_m: FloatArray,
    yaw_rad: float,
    *,
    max_range_m: float,
    height_window_m: float,
    measured: Callable[[float], bool],
) -> ForwardSectors:
    """The 72 body-FRD sector distances of ``points_ned_m`` ((N, 3) local NED) seen from ``pos_ned_m`` at heading
    ``yaw_rad`` (ATTITUDE.yaw: 0 north, clockwise).

    Points more than ``height_window_m`` above or below the vehicle, or farther than ``max_range_m``
    horizontally, are left out (a planar scan). ``measured(bearing_ned_rad)`` says whether a direction was
    measured recently: an empty sector is then "no obstacle", else "unknown".
    """
    max_cm = min(_MAX_DISTANCE_CM, max(MIN_DISTANCE_CM + 1, round(max_range_m * 100.0)))
    pts = np.asarray(points_ned_m, dtype=np.float64).reshape(-1, 3)
    rel = pts - np.asarray(pos_ned_m, dtype=np.float64)
    dist_m = np.hypot(rel[:, 0], rel[:, 1])
    keep = np.isfinite(dist_m) & (np.abs(rel[:, 2]) <= height_window_m) & (dist_m * 100.0 <= max_cm)
    rel, dist_m = rel[keep], dist_m[keep]
    body_deg = np.degrees(np.arctan2(rel[:, 1], rel[:, 0]) - yaw_rad)
    sector: npt.NDArray[np.intp] = np.floor(np.mod(body_deg + SECTOR_DEG / 2.0, 360.0) / SECTOR_DEG).astype(np.intp)
    sector = np.minimum(sector, FORWARD_SECTORS - 1)
    nearest = np.full(FORWARD_SECTORS, np.inf)
    np.minimum.at(nearest, sector, dist_m)
    out: list[int] = []
    for j, d_m in enumerate(nearest):
        if math.isfinite(d_m):
            out.append(min(max_cm, max(MIN_DISTANCE_CM, round(d_m * 100.0))))
        else:
            bearing_ned = yaw_rad + math.radians(j * SECTOR_DEG)
            out.append(max_cm + 1 if measured(bearing_ned) else UINT16_MAX)
    return ForwardSectors(tuple(out), MIN_DISTANCE_CM, max_cm)
