"""CDR LaserScan against an independent implementation (rosbags' CDR serializer), when it is installed."""

from __future__ import annotations

import numpy as np
import pytest

from apf_companion.perception import (
    SectorCounts,
    decode_laserscan_cdr,
    encode_laserscan_cdr,
    parse_laserscan_cdr,
)

typesys = pytest.importorskip("rosbags.typesys")
pytestmark = pytest.mark.interop


def _rosbags_laserscan(ranges: np.ndarray, frame_id: str, little_endian: bool) -> bytes:
    ts = typesys.get_typestore(typesys.Stores.ROS2_HUMBLE)
    laser_scan = ts.types["sensor_msgs/msg/LaserScan"]
    header = ts.types["std_msgs/msg/Header"]
    stamp = ts.types["builtin_interfaces/msg/Time"]
    msg = laser_scan(
        header=header(stamp=stamp(sec=17, nanosec=5), frame_id=frame_id),
        angle_min=-1.5,
        angle_max=1.5,
        angle_increment=0.5,
        time_increment=0.0,
        scan_time=0.1,
        range_min=0.2,
        range_max=8.0,
        ranges=ranges,
        intensities=np.array([], dtype=np.float32),
    )
    return bytes(ts.serialize_cdr(msg, "sensor_msgs/msg/LaserScan", little_endian=little_endian))


@pytest.mark.parametrize("little_endian", [True, False])
@pytest.mark.parametrize("frame_id", ["", "laser", "laser_frame", "base_scan_01"])
def test_rosbags_bytes_decode(little_endian: bool, frame_id: str) -> None:
    ranges = np.array([1.0, 2.0, np.inf, np.nan, 3.0, 0.1, 9.0], dtype=np.float32)
    data = _rosbags_laserscan(ranges, frame_id, little_endian)
    parsed = parse_laserscan_cdr(data)
    assert (parsed.stamp_sec, parsed.stamp_nanosec, parsed.frame_id) == (17, 5, frame_id)
    np.testing.assert_array_equal(parsed.ranges, ranges.astype(np.float64))

    scan = decode_laserscan_cdr(data, t_s=0.0)
    # ROS -1.5 rad (to the right) is FRD +1.5 rad.
    assert scan.bearings_rad[0] == pytest.approx(1.5)
    assert scan.counts == SectorCounts(valid=3, free=1, invalid=3)  # nan, 0.1 < min, 9.0 > max


@pytest.mark.parametrize("little_endian", [True, False])
@pytest.mark.parametrize("frame_id", ["", "laser", "laser_frame", "base_scan_01"])
def test_our_encoder_writes_rosbags_bytes(little_endian: bool, frame_id: str) -> None:
    # No readings outside the limits, so nothing is lost by the decode: the bytes must match exactly.
    ranges = np.array([1.0, 2.0, np.inf, np.nan, 3.0, 0.25, 7.5], dtype=np.float32)
    data = _rosbags_laserscan(ranges, frame_id, little_endian)
    scan = decode_laserscan_cdr(data, t_s=0.0)
    ours = encode_laserscan_cdr(
        scan, stamp_sec=17, stamp_nanosec=5, frame_id=frame_id, scan_time_s=0.1, big_endian=not little_endian
    )
    assert ours == data
