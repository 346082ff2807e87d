"""Placing range scans in local NED."""

from __future__ import annotations

import numpy as np

from apf_companion.perception.types import FloatArray, Pose, RangeScan, ScanFrame

__all__ = ["scan_bearings_ned_rad", "scan_to_points_ned"]


def scan_bearings_ned_rad(scan: RangeScan, pose: Pose) -> FloatArray:
    """(M,) bearings of the scan's elements from north, clockwise [rad] (not wrapped).

    BODY_FRD bearings are turned by the vehicle yaw (both are clockwise from above); LOCAL_NED bearings are
    already north-referenced and ignore the pose.
    """
    if scan.frame is ScanFrame.BODY_FRD:
        return np.asarray(scan.bearings_rad + pose.yaw_rad, dtype=np.float64)
    return np.asarray(scan.bearings_rad, dtype=np.float64)


def scan_to_points_ned(scan: RangeScan, pose: Pose) -> FloatArray:
    """Obstacle points of a scan in local NED.

    For each element with a finite range ``r`` at NED bearing ``b`` (see ``scan_bearings_ned_rad``):
    ``north = n0 + r cos b``, ``east = e0 + r sin b``, ``down = d0``, where ``(n0, e0, d0)`` is
    ``pose.pos_ned_m``. The scan is taken as horizontal at the vehicle's height (roll and pitch ignored).
    Free (+inf) and unknown/invalid (NaN) elements give no point.

    Parameters
    ----------
    scan:
        The scan.
    pose:
        The vehicle pose AT THE SCAN'S MEASUREMENT TIME (``PoseHistory.at(scan.t_s)``); using the latest
        pose instead smears obstacles by the distance flown and the yaw turned since the measurement.

    Returns
    -------
    (K, 3) float64 points in local NED [m], K = number of finite ranges, in scan order.
    """
    mask = np.isfinite(scan.ranges_m)
    r = scan.ranges_m[mask]
    b = scan_bearings_ned_rad(scan, pose)[mask]
    points = np.empty((r.size, 3), dtype=np.float64)
    points[:, 0] = pose.pos_ned_m[0] + r * np.cos(b)
    points[:, 1] = pose.pos_ned_m[1] + r * np.sin(b)
    points[:, 2] = pose.pos_ned_m[2]
    return points
