"""JSON (apf.range_scan/1, apf.goal/1) and CDR LaserScan codecs: round trips, a hand-built vector, bad input."""

from __future__ import annotations

import json
import math
import struct

import numpy as np
import pytest

from apf_companion.errors import ConfigError, ProtocolError
from apf_companion.perception import (
    GoalCommand,
    RangeScan,
    ScanFrame,
    SectorCounts,
    decode_goal_json,
    decode_laserscan_cdr,
    decode_scan_json,
    decode_scan_payload,
    encode_goal_json,
    encode_laserscan_cdr,
    encode_scan_json,
    parse_laserscan_cdr,
)


def _scan(**kw: object) -> RangeScan:
    base: dict[str, object] = {
        "t_s": 3.0,
        "frame": ScanFrame.BODY_FRD,
        "bearings_rad": np.deg2rad([-10.0, 0.0, 10.0, 20.0]),
        "ranges_m": np.array([1.5, math.nan, math.inf, 7.25]),
        "range_min_m": 0.2,
        "range_max_m": 12.0,
        "time_boot_ms": 1234,
    }
    base.update(kw)
    return RangeScan(**base)  # type: ignore[arg-type]


def test_json_round_trip() -> None:
    scan = _scan()
    data = encode_scan_json(scan)
    obj = json.loads(data)
    assert obj == {
        "schema": "apf.range_scan/1",
        "time_boot_ms": 1234,
        "frame": "body_frd",
        "angle_min_deg": pytest.approx(-10.0),
        "angle_increment_deg": pytest.approx(10.0),
        "range_min_m": 0.2,
        "range_max_m": 12.0,
        "ranges_m": [1.5, None, 13.0, 7.25],
    }
    back = decode_scan_json(data, t_s=3.0, source="")
    np.testing.assert_allclose(back.bearings_rad, scan.bearings_rad, atol=1e-12)
    np.testing.assert_array_equal(back.ranges_m, scan.ranges_m)
    assert back.counts == SectorCounts(valid=2, free=1, unknown=1)
    assert back.frame is ScanFrame.BODY_FRD
    assert back.time_boot_ms == 1234


def test_json_classification_and_local_ned() -> None:
    data = json.dumps(
        {
            "schema": "apf.range_scan/1",
            "time_boot_ms": None,
            "frame": "local_ned",
            "angle_min_deg": 170.0,
            "angle_increment_deg": -5.0,
            "range_min_m": 0.5,
            "range_max_m": 10.0,
            "ranges_m": [0.4, 0.5, 10.0, 10.01, None, 3],
            "extra_field": "ignored",
        }
    )
    scan = decode_scan_json(data, t_s=0.0)
    assert scan.frame is ScanFrame.LOCAL_NED
    assert scan.time_boot_ms is None
    assert scan.counts == SectorCounts(valid=3, free=1, unknown=1, invalid=1)
    assert math.isnan(scan.ranges_m[0]) and scan.ranges_m[3] == math.inf
    np.testing.assert_allclose(np.rad2deg(scan.bearings_rad), [170, 165, 160, 155, 150, 145])


def _good() -> dict[str, object]:
    return json.loads(encode_scan_json(_scan()))  # type: ignore[no-any-return]


@pytest.mark.parametrize(
    ("change", "field"),
    [
        ({"schema": "apf.range_scan/2"}, "schema"),
        ({"frame": "body_flu"}, "frame"),
        ({"time_boot_ms": -1}, "time_boot_ms"),
        ({"time_boot_ms": 1.5}, "time_boot_ms"),
        ({"angle_min_deg": "0"}, "angle_min_deg"),
        ({"angle_increment_deg": True}, "angle_increment_deg"),
        ({"angle_increment_deg": 0.0}, "angle_increment_deg"),
        ({"range_min_m": 20.0}, "range_min_m"),
        ({"range_max_m": None}, "range_max_m"),
        ({"ranges_m": {"a": 1}}, "ranges_m"),
        ({"ranges_m": [1.0, "x"]}, "ranges_m"),
        ({"ranges_m": [1.0] * 5000}, "ranges_m"),
        ({"angle_min_deg": 10**400}, "angle_min_deg"),
    ],
)
def test_json_bad_fields_are_named(change: dict[str, object], field: str) -> None:
    obj = _good()
    obj.update(change)
    with pytest.raises(ProtocolError, match=field):
        decode_scan_json(json.dumps(obj), t_s=0.0)


@pytest.mark.parametrize("data", [b"", b"not json", b"[1, 2]", b'{"schema": NaN}', b"\xff\xfe\x00", b"[" * 100000])
def test_json_garbage(data: bytes) -> None:
    with pytest.raises(ProtocolError):
        decode_scan_json(data, t_s=0.0)


def test_json_missing_field_named() -> None:
    obj = _good()
    del obj["range_max_m"]
    with pytest.raises(ProtocolError, match="range_max_m"):
        decode_scan_json(json.dumps(obj), t_s=0.0)


def test_json_nan_token_rejected() -> None:
    text = encode_scan_json(_scan()).decode().replace("1.5", "NaN")
    with pytest.raises(ProtocolError, match="NaN"):
        decode_scan_json(text, t_s=0.0)


def test_encode_needs_even_bearings() -> None:
    scan = _scan(bearings_rad=np.deg2rad([0.0, 10.0, 25.0, 30.0]))
    with pytest.raises(ConfigError, match="evenly"):
        encode_scan_json(scan)


def test_goal_round_trip_and_errors() -> None:
    goal = GoalCommand(pos_ned_m=np.array([20.0, 5.0, -10.0]))
    data = encode_goal_json(goal)
    assert json.loads(data) == {
        "schema": "apf.goal/1",
        "north_m": 20.0,
        "east_m": 5.0,
        "down_m": -10.0,
        "frame": "local_ned",
    }
    assert decode_goal_json(data) == goal
    assert decode_goal_json(b'{"schema":"apf.goal/1","north_m":1,"east_m":2,"down_m":3}') == GoalCommand(
        pos_ned_m=np.array([1.0, 2.0, 3.0])
    )
    with pytest.raises(ProtocolError, match="east_m"):
        decode_goal_json(b'{"schema":"apf.goal/1","north_m":1,"down_m":3}')
    with pytest.raises(ProtocolError, match="frame"):
        decode_goal_json(b'{"schema":"apf.goal/1","north_m":1,"east_m":2,"down_m":3,"frame":"global"}')
    with pytest.raises(ProtocolError, match="schema"):
        decode_goal_json(b'{"north_m":1,"east_m":2,"down_m":3}')


def _hand_built_laserscan() -> bytes:
    """sensor_msgs/LaserScan, CDR LE, built field by field with explicit offsets (body-relative)."""
    body = b""
    body += struct.pack("<i", 17)  # 0: stamp.sec
    body += struct.pack("<I", 500_000_000)  # 4: stamp.nanosec
    body += struct.pack("<I", 6) + b"laser\x00"  # 8: frame_id length 6 incl. NUL, bytes 12..17
    body += b"\x00\x00"  # 18: pad to 20
    body += struct.pack(
        "<7f",
        -math.pi / 2,  # angle_min: 90 deg to the LEFT (CCW) in ROS
        math.pi / 2,  # angle_max
        math.pi / 2,  # angle_increment
        0.0,  # time_increment
        0.1,  # scan_time
        0.25,  # range_min
        8.0,  # range_max
    )  # 20..47
    body += struct.pack("<I", 3) + struct.pack("<3f", 2.0, math.inf, math.nan)  # 48: ranges
    body += struct.pack("<I", 3) + struct.pack("<3f", 1.0, 0.0, 0.0)  # 64: intensities
    return b"\x00\x01\x00\x00" + body


def test_cdr_hand_built_vector() -> None:
    data = _hand_built_laserscan()
    msg = parse_laserscan_cdr(data)
    assert (msg.stamp_sec, msg.stamp_nanosec, msg.frame_id) == (17, 500_000_000, "laser")
    assert msg.range_max == 8.0
    scan = decode_laserscan_cdr(data, t_s=9.0)
    assert scan.frame is ScanFrame.BODY_FRD
    # ROS -90 deg (CCW, i.e. to the right) is FRD +90 deg; ROS 0 is forward; ROS +90 (left) is FRD -90.
    np.testing.assert_allclose(np.rad2deg(scan.bearings_rad), [90.0, 0.0, -90.0], atol=1e-5)
    assert scan.ranges_m[0] == 2.0 and scan.ranges_m[1] == math.inf and math.isnan(scan.ranges_m[2])
    assert scan.counts == SectorCounts(valid=1, free=1, invalid=1)
    assert scan.time_boot_ms is None
    assert scan.source == "zenoh:laserscan:laser"


def test_cdr_encoder_matches_hand_built_layout() -> None:
    scan = RangeScan(
        t_s=0.0,
        frame=ScanFrame.BODY_FRD,
        bearings_rad=np.deg2rad([90.0, 0.0, -90.0]),
        ranges_m=np.array([2.0, math.inf, math.nan]),
        range_min_m=0.25,
        range_max_m=8.0,
    )
    data = encode_laserscan_cdr(scan, stamp_sec=17, stamp_nanosec=500_000_000, frame_id="laser", scan_time_s=0.1)
    ref = _hand_built_laserscan()
    # Same bytes up to the intensities (ours are empty): header, angles, limits, ranges.
    assert data[: 4 + 64] == ref[: 4 + 64]
    assert data[4 + 64 :] == struct.pack("<I", 0)


@pytest.mark.parametrize("big_endian", [False, True])
def test_cdr_round_trip(big_endian: bool) -> None:
    rng = np.random.default_rng(7)
    ranges = rng.uniform(0.3, 11.0, 360).astype(np.float32).astype(np.float64)
    ranges[::17] = math.inf
    bearings = np.deg2rad(np.arange(360) - 180.0)
    scan = RangeScan(
        t_s=1.0,
        frame=ScanFrame.BODY_FRD,
        bearings_rad=bearings,
        ranges_m=ranges,
        range_min_m=0.25,
        range_max_m=12.0,
    )
    back = decode_laserscan_cdr(encode_laserscan_cdr(scan, big_endian=big_endian), t_s=1.0)
    np.testing.assert_array_equal(back.ranges_m, ranges)
    diff = np.remainder(back.bearings_rad - bearings + math.pi, 2 * math.pi) - math.pi
    np.testing.assert_allclose(diff, 0.0, atol=2e-6)  # float32 angles


def test_cdr_mount_yaw() -> None:
    scan = decode_laserscan_cdr(_hand_built_laserscan(), t_s=0.0, mount_yaw_rad=math.pi)
    np.testing.assert_allclose(np.rad2deg(scan.bearings_rad), [-90.0, -180.0, 90.0], atol=1e-5)


def test_cdr_out_of_limits_are_invalid() -> None:
    # REP 117 / the message comment: values < range_min or > range_max are discarded; 0 is below range_min.
    scan = RangeScan(
        t_s=0.0,
        frame=ScanFrame.BODY_FRD,
        bearings_rad=np.deg2rad([0.0, 1.0, 2.0, 3.0]),
        ranges_m=np.array([0.1, 9.0, 0.0, 4.0]),
        range_min_m=0.2,
        range_max_m=8.0,
    )
    out = decode_laserscan_cdr(encode_laserscan_cdr(scan, frame_id="x"), t_s=0.0)
    assert out.counts == SectorCounts(valid=1, invalid=3)
    assert out.ranges_m[3] == 4.0


@pytest.mark.parametrize("cut", [0, 3, 4, 10, 20, 40, 50, 60, 70])
def test_cdr_truncated(cut: int) -> None:
    with pytest.raises(ProtocolError):
        decode_laserscan_cdr(_hand_built_laserscan()[:cut], t_s=0.0)


def test_cdr_garbled() -> None:
    data = bytearray(_hand_built_laserscan())
    bad_kind = b"\x00\x07" + bytes(data[2:])
    with pytest.raises(ProtocolError, match="encapsulation"):
        decode_laserscan_cdr(bad_kind, t_s=0.0)
    huge_count = bytearray(data)
    huge_count[4 + 48 : 4 + 52] = struct.pack("<I", 0xFFFFFFF0)
    with pytest.raises(ProtocolError, match="ranges"):
        decode_laserscan_cdr(bytes(huge_count), t_s=0.0)
    no_nul = bytearray(data)
    no_nul[4 + 17] = ord("!")
    with pytest.raises(ProtocolError, match="NUL"):
        decode_laserscan_cdr(bytes(no_nul), t_s=0.0)
    mismatch = bytearray(data)
    mismatch[4 + 64 : 4 + 68] = struct.pack("<I", 2)
    with pytest.raises(ProtocolError):
        decode_laserscan_cdr(bytes(mismatch), t_s=0.0)
    nan_limits = bytearray(data)
    nan_limits[4 + 44 : 4 + 48] = struct.pack("<f", math.nan)
    with pytest.raises(ProtocolError, match="range_max"):
        decode_laserscan_cdr(bytes(nan_limits), t_s=0.0)
    with pytest.raises(ProtocolError, match="trailing"):
        decode_laserscan_cdr(bytes(data) + b"\x00" * 8, t_s=0.0)


def test_payload_dispatch() -> None:
    scan = _scan()
    js = encode_scan_json(scan)
    cdr = encode_laserscan_cdr(scan)
    assert decode_scan_payload(js, "application/json", t_s=0.0).source == "zenoh:json"
    assert decode_scan_payload(cdr, "application/cdr", t_s=0.0).source.startswith("zenoh:laserscan")
    assert decode_scan_payload(js, "zenoh/bytes", t_s=0.0).source == "zenoh:json"
    assert decode_scan_payload(cdr, None, t_s=0.0).source.startswith("zenoh:laserscan")
    # No format in the encoding: the content decides (zenoh-bridge-ros2dds and rmw_zenoh set none).
    for encoding in ("zenoh/bytes", "application/octet-stream", "text/json"):
        assert decode_scan_payload(cdr, encoding, t_s=0.0).source.startswith("zenoh:laserscan")
        assert decode_scan_payload(b" \n" + js, encoding, t_s=0.0).source == "zenoh:json"
    with pytest.raises(ProtocolError, match="neither"):
        decode_scan_payload(b"\x12\x34garbage", "zenoh/bytes", t_s=0.0)
    with pytest.raises(ProtocolError, match="encapsulation 0007"):  # XCDR2: named by the CDR decoder
        decode_scan_payload(b"\x00\x07" + cdr[2:], "zenoh/bytes", t_s=0.0)
    with pytest.raises(ProtocolError):
        decode_scan_payload(cdr, "application/json", t_s=0.0)
