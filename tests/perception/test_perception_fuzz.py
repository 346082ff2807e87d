"""Property tests: decoders only ever raise ProtocolError; adapters never crash on any field values."""

from __future__ import annotations

import json
import math
import struct

import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st
from pymavlink.dialects.v20 import ardupilotmega as mavlink

from apf_companion.errors import ProtocolError
from apf_companion.perception import (
    ObstacleMemory,
    Pose,
    RangeScan,
    ScanFrame,
    decode_goal_json,
    decode_laserscan_cdr,
    decode_scan_json,
    decode_scan_payload,
    encode_laserscan_cdr,
    encode_scan_json,
    scan_from_distance_sensor,
    scan_from_obstacle_distance,
    scan_to_points_ned,
)

_SETTINGS = settings(max_examples=300, deadline=None)


def _only_protocol_error(fn: object, *args: object, **kwargs: object) -> object:
    try:
        return fn(*args, **kwargs)  # type: ignore[operator]
    except ProtocolError:
        return None


@_SETTINGS
@given(st.binary(max_size=512))
def test_random_bytes_to_decoders(data: bytes) -> None:
    _only_protocol_error(decode_scan_json, data, t_s=0.0)
    _only_protocol_error(decode_goal_json, data)
    _only_protocol_error(decode_laserscan_cdr, data, t_s=0.0)
    _only_protocol_error(decode_laserscan_cdr, b"\x00\x01\x00\x00" + data, t_s=0.0)
    _only_protocol_error(decode_scan_payload, data, None, t_s=0.0)


def _valid_cdr() -> bytes:
    scan = RangeScan(
        t_s=0.0,
        frame=ScanFrame.BODY_FRD,
        bearings_rad=np.deg2rad([0.0, 5.0, 10.0, 15.0]),
        ranges_m=np.array([1.0, 2.0, math.inf, math.nan]),
        range_min_m=0.1,
        range_max_m=5.0,
    )
    return encode_laserscan_cdr(scan, frame_id="lidar")


@_SETTINGS
@given(st.lists(st.tuples(st.integers(0, 200), st.integers(0, 255)), min_size=1, max_size=8))
def test_mutated_cdr(mutations: list[tuple[int, int]]) -> None:
    data = bytearray(_valid_cdr())
    for pos, value in mutations:
        data[pos % len(data)] = value
    out = _only_protocol_error(decode_laserscan_cdr, bytes(data), t_s=0.0)
    if isinstance(out, RangeScan):
        assert np.all(np.isfinite(out.bearings_rad))


_json_leaf = st.none() | st.booleans() | st.integers() | st.floats() | st.text(max_size=5)
_json = st.recursive(
    _json_leaf,
    lambda inner: st.lists(inner, max_size=4) | st.dictionaries(st.text(max_size=5), inner, max_size=4),
    max_leaves=20,
)
_scan_keys = [
    "schema",
    "time_boot_ms",
    "frame",
    "angle_min_deg",
    "angle_increment_deg",
    "range_min_m",
    "range_max_m",
    "ranges_m",
]


@_SETTINGS
@given(st.dictionaries(st.sampled_from(_scan_keys), _json, max_size=8))
def test_random_json_objects(obj: dict[str, object]) -> None:
    try:
        text = json.dumps(obj)
    except ValueError:
        return
    _only_protocol_error(decode_scan_json, text, t_s=0.0)


@_SETTINGS
@given(
    ranges=st.lists(st.none() | st.floats(-1e6, 1e6), min_size=1, max_size=80),
    angle_min=st.floats(-720, 720),
    inc=st.floats(-10, 10).filter(lambda v: abs(v) >= 1e-3),
    lo=st.floats(0, 5),
    span=st.floats(0, 50),
)
def test_valid_json_decodes_and_reencodes(
    ranges: list[float | None], angle_min: float, inc: float, lo: float, span: float
) -> None:
    obj = {
        "schema": "apf.range_scan/1",
        "time_boot_ms": 5,
        "frame": "body_frd",
        "angle_min_deg": angle_min,
        "angle_increment_deg": inc,
        "range_min_m": lo,
        "range_max_m": lo + span,
        "ranges_m": ranges,
    }
    scan = decode_scan_json(json.dumps(obj), t_s=0.0)
    assert scan.counts.total == len(ranges)
    again = decode_scan_json(encode_scan_json(scan), t_s=0.0)
    np.testing.assert_array_equal(again.ranges_m, scan.ranges_m)
    pose = Pose(t_s=0.0, pos_ned_m=np.zeros(3), yaw_rad=0.3)
    pts = scan_to_points_ned(scan, pose)
    assert pts.shape == (scan.counts.valid, 3)
    assert np.all(np.isfinite(pts))


@_SETTINGS
@given(
    distances=st.lists(st.integers(0, 65535), min_size=72, max_size=72),
    increment=st.integers(0, 255),
    increment_f=st.floats(width=32),
    angle_offset=st.floats(width=32),
    min_cm=st.integers(0, 65535),
    max_cm=st.integers(0, 65535),
    frame=st.integers(0, 25),
)
def test_obstacle_distance_any_fields(
    distances: list[int],
    increment: int,
    increment_f: float,
    angle_offset: float,
    min_cm: int,
    max_cm: int,
    frame: int,
) -> None:
    msg = mavlink.MAVLink_obstacle_distance_message(
        0, 0, distances, increment, min_cm, max_cm, increment_f, angle_offset, frame
    )
    scan = _only_protocol_error(scan_from_obstacle_distance, msg, t_s=0.0)
    if isinstance(scan, RangeScan):
        assert 1 <= len(scan) <= 72
        assert scan.counts.total == len(scan)
        finite = scan.ranges_m[np.isfinite(scan.ranges_m)]
        assert np.all((finite >= scan.range_min_m) & (finite <= scan.range_max_m))


@_SETTINGS
@given(
    current=st.integers(0, 65535),
    orientation=st.integers(0, 255),
    min_cm=st.integers(0, 65535),
    max_cm=st.integers(0, 65535),
    q=st.lists(st.floats(width=32), min_size=4, max_size=4),
)
def test_distance_sensor_any_fields(current: int, orientation: int, min_cm: int, max_cm: int, q: list[float]) -> None:
    msg = mavlink.MAVLink_distance_sensor_message(0, min_cm, max_cm, current, 0, 0, orientation, 0, 0.0, 0.0, q, 0)
    scan = _only_protocol_error(scan_from_distance_sensor, msg, t_s=0.0)
    if isinstance(scan, RangeScan):
        assert len(scan) in (0, 1)


@_SETTINGS
@given(
    batches=st.lists(st.lists(st.tuples(*[st.floats(-20, 20)] * 3), min_size=0, max_size=30), min_size=1, max_size=6),
    radius=st.floats(0.01, 3.0),
)
def test_memory_points_are_separated_within_a_batch(
    batches: list[list[tuple[float, float, float]]], radius: float
) -> None:
    mem = ObstacleMemory(expiry_s=100.0, merge_radius_m=radius, max_points=50)
    for i, batch in enumerate(batches):
        mem.add(np.array(batch, dtype=np.float64).reshape(-1, 3), t_s=float(i))
        assert len(mem) <= 50
    pts = mem.points(float(len(batches)))
    # Every point of the last batch is remembered or merged into a point within the radius.
    last = np.array(batches[-1], dtype=np.float64).reshape(-1, 3)
    if last.size and pts.size:
        d = np.linalg.norm(last[:, None, :] - pts[None, :, :], axis=-1)
        assert np.all(d.min(axis=1) < radius + 1e-9) or len(pts) == 50


def test_struct_sanity() -> None:
    # The fuzzers above rely on the encapsulation header being what the decoder checks.
    assert _valid_cdr()[:4] == struct.pack("BBBB", 0, 1, 0, 0)
