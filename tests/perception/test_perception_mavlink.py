"""Golden vectors for the MAVLink obstacle adapters (messages go through a real pymavlink pack/parse)."""

from __future__ import annotations

import math
from typing import Any

import numpy as np
import pytest
from pymavlink.dialects.v20 import ardupilotmega as mavlink

from apf_companion.errors import ProtocolError
from apf_companion.perception import (
    Pose,
    ScanFrame,
    SectorCounts,
    points_from_obstacle_distance_3d,
    scan_from_distance_sensor,
    scan_from_obstacle_distance,
)

U16 = 65535


def _wire(msg: Any) -> Any:
    """Pack ``msg`` as MAVLink 2 and parse it back, as the link would deliver it."""
    tx = mavlink.MAVLink(None, srcSystem=1, srcComponent=1)
    tx.robust_parsing = True
    rx = mavlink.MAVLink(None)
    out = rx.parse_buffer(msg.pack(tx))
    assert out is not None and len(out) == 1
    return out[0]


def obstacle_distance(
    distances: list[int],
    *,
    increment: int = 0,
    increment_f: float = 0.0,
    angle_offset: float = 0.0,
    min_cm: int = 20,
    max_cm: int = 1000,
    frame: int = mavlink.MAV_FRAME_BODY_FRD,
    time_usec: int = 1_500_000,
) -> Any:
    full = [*distances, *([U16] * (72 - len(distances)))]
    m = mavlink.MAVLink_obstacle_distance_message(
        time_usec,
        mavlink.MAV_DISTANCE_SENSOR_LASER,
        full,
        increment,
        min_cm,
        max_cm,
        increment_f,
        angle_offset,
        frame,
    )
    return _wire(m)


def test_body_frd_72_sectors_increment_5_deg() -> None:
    d = [500] * 72
    scan = scan_from_obstacle_distance(obstacle_distance(d, increment=5), t_s=2.0)
    assert scan.frame is ScanFrame.BODY_FRD
    assert len(scan) == 72
    assert scan.counts == SectorCounts(valid=72)
    np.testing.assert_allclose(scan.ranges_m, 5.0)
    # Element 18 is 90 deg clockwise = right; element 36 is behind (wrapped to -180).
    assert scan.bearings_rad[0] == pytest.approx(0.0)
    assert scan.bearings_rad[18] == pytest.approx(math.pi / 2)
    assert scan.bearings_rad[36] == pytest.approx(-math.pi)
    assert scan.bearings_rad[54] == pytest.approx(-math.pi / 2)
    assert scan.time_boot_ms == 1500
    assert scan.t_s == 2.0
    assert (scan.range_min_m, scan.range_max_m) == (0.2, 10.0)


def test_increment_f_wins_over_increment_and_sets_element_count() -> None:
    # increment (uint8) says 5 deg, increment_f says 10 deg: 36 elements at 10 deg; the rest unused.
    d = [300] * 36 + [400] * 36
    scan = scan_from_obstacle_distance(obstacle_distance(d, increment=5, increment_f=10.0), t_s=0.0)
    assert len(scan) == 36
    np.testing.assert_allclose(scan.ranges_m, 3.0)
    assert scan.bearings_rad[9] == pytest.approx(math.radians(90.0))
    assert scan.bearings_rad[35] == pytest.approx(math.radians(-10.0))


def test_fewer_elements_when_360_over_increment_is_small() -> None:
    # ArduPilot's count (AP_Proximity_MAV.cpp): 360 / |inc| + 0.5 truncated, at most 72.
    # 45 deg -> 8 elements; 7 deg -> 51.4 -> 51; 7.2 deg -> exactly 50.
    assert len(scan_from_obstacle_distance(obstacle_distance([100] * 72, increment=45), t_s=0)) == 8
    assert len(scan_from_obstacle_distance(obstacle_distance([100] * 72, increment=7), t_s=0)) == 51
    assert len(scan_from_obstacle_distance(obstacle_distance([100] * 72, increment_f=7.2), t_s=0)) == 50
    # Rounded, not floored: 50.70 -> 51 and 71.9986 -> 72 (flooring read 50 and 71).
    assert len(scan_from_obstacle_distance(obstacle_distance([100] * 72, increment_f=7.1), t_s=0)) == 51
    assert len(scan_from_obstacle_distance(obstacle_distance([100] * 72, increment_f=5.0001), t_s=0)) == 72
    assert len(scan_from_obstacle_distance(obstacle_distance([100] * 72, increment_f=-7.1), t_s=0)) == 51
    # 360 deg: 1.5 -> 1 element; 250 deg: 1.94 -> 1.
    assert len(scan_from_obstacle_distance(obstacle_distance([100] * 72, increment_f=360.0), t_s=0)) == 1
    assert len(scan_from_obstacle_distance(obstacle_distance([100] * 72, increment_f=250.0), t_s=0)) == 1
    # A small increment never reads more than the 72 elements the message has.
    assert len(scan_from_obstacle_distance(obstacle_distance([100] * 72, increment_f=2.0), t_s=0)) == 72
    # A subnormal increment (360 / inc overflows to inf) still reads 72.
    tiny = obstacle_distance([100] * 72, increment=5)
    tiny.increment_f = 1e-320
    assert len(scan_from_obstacle_distance(tiny, t_s=0)) == 72


def test_angle_offset_shifts_every_element() -> None:
    scan = scan_from_obstacle_distance(obstacle_distance([100] * 8, increment=45, angle_offset=-22.5), t_s=0.0)
    expected = [-22.5, 22.5, 67.5, 112.5, 157.5, -157.5, -112.5, -67.5]  # wrapped to [-180, 180)
    np.testing.assert_allclose(np.rad2deg(scan.bearings_rad), expected, atol=1e-9)


def test_negative_increment_f_runs_counter_clockwise() -> None:
    scan = scan_from_obstacle_distance(obstacle_distance([100] * 72, increment_f=-90.0), t_s=0.0)
    np.testing.assert_allclose(np.rad2deg(scan.bearings_rad), [0.0, -90.0, -180.0, 90.0], atol=1e-9)


@pytest.mark.parametrize(
    ("frame", "expected"),
    [
        (mavlink.MAV_FRAME_BODY_FRD, ScanFrame.BODY_FRD),
        (mavlink.MAV_FRAME_LOCAL_NED, ScanFrame.LOCAL_NED),
        (mavlink.MAV_FRAME_GLOBAL, ScanFrame.LOCAL_NED),
        (mavlink.MAV_FRAME_GLOBAL_RELATIVE_ALT, ScanFrame.LOCAL_NED),
    ],
)
def test_frame_is_honoured(frame: int, expected: ScanFrame) -> None:
    scan = scan_from_obstacle_distance(obstacle_distance([100] * 72, increment=5, frame=frame), t_s=0.0)
    assert scan.frame is expected


def test_frame_override_reads_any_frame_as_body() -> None:
    for frame in (mavlink.MAV_FRAME_GLOBAL, mavlink.MAV_FRAME_BODY_NED):
        msg = obstacle_distance([100] * 72, increment=5, frame=frame)
        scan = scan_from_obstacle_distance(msg, t_s=0.0, frame_override=ScanFrame.BODY_FRD)
        assert scan.frame is ScanFrame.BODY_FRD


def test_special_values_unknown_free_invalid_zero() -> None:
    # min 20 cm, max 1000 cm.
    d = [U16, 1001, 1000, 19, 20, 0, 5000, 250]
    scan = scan_from_obstacle_distance(obstacle_distance(d, increment=45), t_s=0.0)
    r = scan.ranges_m
    assert math.isnan(r[0])  # UINT16_MAX: unknown
    assert r[1] == math.inf  # max + 1: free
    assert r[2] == pytest.approx(10.0)  # exactly max: an obstacle
    assert math.isnan(r[3])  # below min: invalid
    assert r[4] == pytest.approx(0.2)  # exactly min: an obstacle
    assert math.isnan(r[5])  # 0: invalid by default (ArduPilot drops it)
    assert r[6] == math.inf  # far above max: free
    assert r[7] == pytest.approx(2.5)
    assert scan.counts == SectorCounts(valid=3, free=2, unknown=1, invalid=2)


def test_zero_is_obstacle_when_configured() -> None:
    scan = scan_from_obstacle_distance(obstacle_distance([0, 10] * 4, increment=45), t_s=0.0, zero_is_obstacle=True)
    assert scan.ranges_m[0] == 0.0
    assert math.isnan(scan.ranges_m[1])  # 10 cm < min 20 cm is still invalid
    assert scan.counts == SectorCounts(valid=4, invalid=4)


def test_unused_tail_is_not_counted() -> None:
    scan = scan_from_obstacle_distance(obstacle_distance([100] * 8, increment=45), t_s=0.0)
    assert scan.counts.total == 8


@pytest.mark.parametrize(
    ("kwargs", "match"),
    [
        ({"increment": 0, "increment_f": 0.0}, "both 0"),
        ({"increment_f": math.nan}, "increment_f"),
        ({"increment_f": math.inf}, "increment_f"),
        ({"increment_f": 361.0}, "full turn"),
        ({"increment": 5, "angle_offset": math.nan}, "angle_offset"),
        ({"increment": 5, "min_cm": 500, "max_cm": 100}, "min_distance"),
        ({"increment": 5, "max_cm": 0, "min_cm": 0}, "max_distance"),
        ({"increment": 5, "frame": mavlink.MAV_FRAME_BODY_NED}, "frame"),
    ],
)
def test_malformed_obstacle_distance_raises(kwargs: dict[str, Any], match: str) -> None:
    with pytest.raises(ProtocolError, match=match):
        scan_from_obstacle_distance(obstacle_distance([100] * 72, **kwargs), t_s=0.0)


def test_unix_time_usec_gives_no_boot_time() -> None:
    msg = obstacle_distance([100] * 72, increment=5, time_usec=1_700_000_000_000_000)
    assert scan_from_obstacle_distance(msg, t_s=0.0).time_boot_ms is None


def distance_sensor(
    current_cm: int,
    orientation: int,
    *,
    min_cm: int = 10,
    max_cm: int = 800,
    quaternion: tuple[float, float, float, float] = (0.0, 0.0, 0.0, 0.0),
) -> Any:
    m = mavlink.MAVLink_distance_sensor_message(
        4321,
        min_cm,
        max_cm,
        current_cm,
        mavlink.MAV_DISTANCE_SENSOR_LASER,
        0,
        orientation,
        0,
        0.1,
        0.1,
        list(quaternion),
        100,
    )
    return _wire(m)


@pytest.mark.parametrize("orientation", range(8))
def test_distance_sensor_yaw_orientations(orientation: int) -> None:
    scan = scan_from_distance_sensor(distance_sensor(250, orientation), t_s=1.0)
    assert scan.frame is ScanFrame.BODY_FRD
    assert len(scan) == 1
    expected = math.remainder(math.radians(45.0 * orientation), 2 * math.pi)
    assert math.isclose(math.remainder(scan.bearings_rad[0] - expected, 2 * math.pi), 0.0, abs_tol=1e-12)
    assert scan.ranges_m[0] == pytest.approx(2.5)
    assert scan.time_boot_ms == 4321
    assert scan.counts == SectorCounts(valid=1)


def test_distance_sensor_special_values() -> None:
    assert scan_from_distance_sensor(distance_sensor(801, 0), t_s=0).ranges_m[0] == math.inf
    # Exactly max_distance (800 cm) is free too: ArduPilot's emptied proximity face (GCS_Common.cpp send_proximity).
    at_max = scan_from_distance_sensor(distance_sensor(800, 0), t_s=0)
    assert (at_max.ranges_m[0], at_max.counts) == (math.inf, SectorCounts(free=1))
    assert scan_from_distance_sensor(distance_sensor(799, 0), t_s=0).ranges_m[0] == pytest.approx(7.99)
    assert scan_from_distance_sensor(distance_sensor(U16, 0), t_s=0).counts == SectorCounts(unknown=1)
    assert scan_from_distance_sensor(distance_sensor(5, 0), t_s=0).counts == SectorCounts(invalid=1)
    assert scan_from_distance_sensor(distance_sensor(0, 0), t_s=0).counts == SectorCounts(invalid=1)


@pytest.mark.parametrize(
    "orientation",
    [
        mavlink.MAV_SENSOR_ROTATION_PITCH_90,
        mavlink.MAV_SENSOR_ROTATION_PITCH_270,
        mavlink.MAV_SENSOR_ROTATION_ROLL_180,
        mavlink.MAV_SENSOR_ROTATION_ROLL_90_YAW_45,
    ],
)
def test_distance_sensor_non_horizontal_gives_empty_scan(orientation: int) -> None:
    scan = scan_from_distance_sensor(distance_sensor(250, orientation), t_s=0.0)
    assert len(scan) == 0
    assert scan.counts.total == 0


def test_distance_sensor_custom_quaternion() -> None:
    # Yaw 60 deg about body z (down): x axis turns towards the right (clockwise seen from above).
    half = math.radians(60.0) / 2
    q = (math.cos(half), 0.0, 0.0, math.sin(half))
    scan = scan_from_distance_sensor(distance_sensor(300, 100, quaternion=q), t_s=0.0)
    assert scan.bearings_rad[0] == pytest.approx(math.radians(60.0), abs=1e-6)
    # Pitch up 90 deg: not horizontal.
    half = math.radians(90.0) / 2
    q_up = (math.cos(half), 0.0, math.sin(half), 0.0)
    assert len(scan_from_distance_sensor(distance_sensor(300, 100, quaternion=q_up), t_s=0.0)) == 0
    with pytest.raises(ProtocolError, match="quaternion"):
        scan_from_distance_sensor(distance_sensor(300, 100), t_s=0.0)


def test_distance_sensor_undefined_orientation_raises() -> None:
    with pytest.raises(ProtocolError, match="orientation"):
        scan_from_distance_sensor(distance_sensor(250, 77), t_s=0.0)


def obstacle_3d(x: float, y: float, z: float, frame: int, *, min_m: float = 0.1, max_m: float = 20.0) -> Any:
    m = mavlink.MAVLink_obstacle_distance_3d_message(
        99, mavlink.MAV_DISTANCE_SENSOR_LASER, frame, U16, x, y, z, min_m, max_m
    )
    return _wire(m)


def test_obstacle_distance_3d_body_frd_rotated_by_yaw() -> None:
    pose = Pose(t_s=0.0, pos_ned_m=np.array([10.0, 20.0, -5.0]), yaw_rad=math.pi / 2)  # facing east
    pts = points_from_obstacle_distance_3d(obstacle_3d(2.0, 1.0, 0.5, mavlink.MAV_FRAME_BODY_FRD), pose)
    # Forward 2 m -> east; right 1 m -> south; down 0.5 m stays down.
    np.testing.assert_allclose(pts, [[9.0, 22.0, -4.5]], atol=1e-6)


def test_obstacle_distance_3d_local_ned_as_is_and_offset() -> None:
    pose = Pose(t_s=0.0, pos_ned_m=np.array([1.0, 1.0, -2.0]), yaw_rad=1.0)
    pts = points_from_obstacle_distance_3d(obstacle_3d(4.0, 5.0, -2.0, mavlink.MAV_FRAME_LOCAL_NED), pose)
    np.testing.assert_allclose(pts, [[4.0, 5.0, -2.0]], atol=1e-6)
    pts = points_from_obstacle_distance_3d(obstacle_3d(3.0, 0.0, 0.0, mavlink.MAV_FRAME_LOCAL_OFFSET_NED), pose)
    np.testing.assert_allclose(pts, [[4.0, 1.0, -2.0]], atol=1e-6)


def test_obstacle_distance_3d_out_of_range_and_malformed() -> None:
    pose = Pose(t_s=0.0, pos_ned_m=np.zeros(3), yaw_rad=0.0)
    far = obstacle_3d(30.0, 0.0, 0.0, mavlink.MAV_FRAME_BODY_FRD)
    assert points_from_obstacle_distance_3d(far, pose).shape == (0, 3)
    near = obstacle_3d(0.05, 0.0, 0.0, mavlink.MAV_FRAME_BODY_FRD)
    assert points_from_obstacle_distance_3d(near, pose).shape == (0, 3)
    with pytest.raises(ProtocolError, match="finite"):
        points_from_obstacle_distance_3d(obstacle_3d(math.nan, 0, 0, mavlink.MAV_FRAME_BODY_FRD), pose)
    with pytest.raises(ProtocolError, match="min_distance"):
        points_from_obstacle_distance_3d(obstacle_3d(1, 0, 0, mavlink.MAV_FRAME_BODY_FRD, min_m=5, max_m=1), pose)
    with pytest.raises(ProtocolError, match="frame"):
        points_from_obstacle_distance_3d(obstacle_3d(1, 0, 0, mavlink.MAV_FRAME_GLOBAL), pose)
