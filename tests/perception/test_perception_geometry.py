"""Hand-computed geometry: scans to NED points with yaw, and pose interpolation."""

from __future__ import annotations

import math

import numpy as np
import pytest

from apf_companion.errors import ConfigError
from apf_companion.perception import Pose, PoseHistory, RangeScan, ScanFrame, scan_to_points_ned


def _scan(frame: ScanFrame, bearings_deg: list[float], ranges_m: list[float]) -> RangeScan:
    return RangeScan(
        t_s=0.0,
        frame=frame,
        bearings_rad=np.deg2rad(bearings_deg),
        ranges_m=np.array(ranges_m),
        range_min_m=0.1,
        range_max_m=10.0,
    )


def test_body_frd_scan_rotated_by_yaw() -> None:
    # Vehicle at (10, 5, -3) facing east (yaw 90 deg).
    pose = Pose(t_s=0.0, pos_ned_m=np.array([10.0, 5.0, -3.0]), yaw_rad=math.radians(90.0))
    scan = _scan(ScanFrame.BODY_FRD, [0.0, 90.0, -90.0, 45.0], [2.0, 3.0, 4.0, math.sqrt(2.0)])
    pts = scan_to_points_ned(scan, pose)
    expected = [
        [10.0, 7.0, -3.0],  # forward = east
        [7.0, 5.0, -3.0],  # right of an east-facing vehicle = south
        [14.0, 5.0, -3.0],  # left = north
        [9.0, 6.0, -3.0],  # forward-right = south-east
    ]
    np.testing.assert_allclose(pts, expected, atol=1e-12)


def test_local_ned_scan_ignores_yaw() -> None:
    pose = Pose(t_s=0.0, pos_ned_m=np.array([1.0, 2.0, 0.0]), yaw_rad=2.0)
    scan = _scan(ScanFrame.LOCAL_NED, [0.0, 90.0, 180.0], [1.0, 2.0, 3.0])
    np.testing.assert_allclose(
        scan_to_points_ned(scan, pose), [[2.0, 2.0, 0.0], [1.0, 4.0, 0.0], [-2.0, 2.0, 0.0]], atol=1e-12
    )


def test_only_finite_ranges_become_points() -> None:
    pose = Pose(t_s=0.0, pos_ned_m=np.zeros(3), yaw_rad=0.0)
    scan = _scan(ScanFrame.BODY_FRD, [0.0, 10.0, 20.0, 30.0], [math.nan, math.inf, 5.0, math.nan])
    pts = scan_to_points_ned(scan, pose)
    assert pts.shape == (1, 3)
    np.testing.assert_allclose(pts[0], [5.0 * math.cos(math.radians(20)), 5.0 * math.sin(math.radians(20)), 0.0])
    empty = _scan(ScanFrame.BODY_FRD, [0.0], [math.inf])
    assert scan_to_points_ned(empty, pose).shape == (0, 3)


def _pose(t: float, n: float, e: float, yaw_deg: float) -> Pose:
    return Pose(t_s=t, pos_ned_m=np.array([n, e, -1.0]), yaw_rad=math.radians(yaw_deg))


def test_pose_history_interpolates_position_and_yaw_across_pi() -> None:
    h = PoseHistory(10, hold_s=0.0)
    h.add(_pose(1.0, 0.0, 0.0, 170.0))
    h.add(_pose(2.0, 10.0, 4.0, -170.0))
    p = h.at(1.25)
    assert p is not None
    np.testing.assert_allclose(p.pos_ned_m, [2.5, 1.0, -1.0])
    # 170 -> -170 is a 20 deg turn through 180, a quarter of the way is 175 deg.
    assert math.degrees(p.yaw_rad) == pytest.approx(175.0)
    q = h.at(1.75)
    assert q is not None
    assert math.degrees(q.yaw_rad) == pytest.approx(-175.0)
    assert p.t_s == 1.25


def test_pose_history_outside_and_hold() -> None:
    h = PoseHistory(10, hold_s=0.05)
    assert h.at(1.0) is None
    h.add(_pose(1.0, 0.0, 0.0, 0.0))
    h.add(_pose(2.0, 1.0, 0.0, 0.0))
    assert h.at(0.9) is None
    assert h.at(2.1) is None
    held = h.at(2.04)
    assert held is not None
    np.testing.assert_allclose(held.pos_ned_m, [1.0, 0.0, -1.0])
    exact = h.at(1.0)
    assert exact is not None
    np.testing.assert_allclose(exact.pos_ned_m, [0.0, 0.0, -1.0])


def test_pose_history_bounded_and_ordered() -> None:
    h = PoseHistory(3, hold_s=0.0)
    for i in range(5):
        assert h.add(_pose(float(i), float(i), 0.0, 0.0))
    assert len(h) == 3
    assert h.at(1.5) is None  # fell out of the buffer
    p = h.at(3.5)
    assert p is not None
    assert p.pos_ned_m[0] == pytest.approx(3.5)
    assert not h.add(_pose(1.0, 0.0, 0.0, 0.0))
    assert h.rejected == 1
    # Same time replaces the newest pose.
    assert h.add(_pose(4.0, 40.0, 0.0, 0.0))
    latest = h.latest()
    assert latest is not None and latest.pos_ned_m[0] == 40.0
    assert len(h) == 3
    h.clear()
    assert h.latest() is None


def test_pose_history_rejects_bad_config() -> None:
    with pytest.raises(ConfigError, match="maxlen"):
        PoseHistory(0)
    with pytest.raises(ConfigError, match="hold_s"):
        PoseHistory(5, hold_s=-1.0)


def test_pose_and_scan_validation() -> None:
    with pytest.raises(ConfigError, match="pos_ned_m"):
        Pose(t_s=0.0, pos_ned_m=np.array([1.0, 2.0]), yaw_rad=0.0)
    with pytest.raises(ConfigError, match="pos_ned_m"):
        Pose(t_s=0.0, pos_ned_m=np.array([1.0, math.nan, 0.0]), yaw_rad=0.0)
    with pytest.raises(ConfigError, match="yaw_rad"):
        Pose(t_s=0.0, pos_ned_m=np.zeros(3), yaw_rad=math.inf)
    with pytest.raises(ConfigError, match="length"):
        RangeScan(
            t_s=0.0,
            frame=ScanFrame.BODY_FRD,
            bearings_rad=np.zeros(2),
            ranges_m=np.zeros(3),
            range_min_m=0.0,
            range_max_m=1.0,
        )
    with pytest.raises(ConfigError, match="range_min_m"):
        _scan(ScanFrame.BODY_FRD, [0.0], [1.0]).__class__(
            t_s=0.0,
            frame=ScanFrame.BODY_FRD,
            bearings_rad=np.zeros(1),
            ranges_m=np.ones(1),
            range_min_m=2.0,
            range_max_m=1.0,
        )
    p = Pose(t_s=0.0, pos_ned_m=np.zeros(3), yaw_rad=0.0)
    with pytest.raises(ValueError, match="read-only"):
        p.pos_ned_m[0] = 1.0
