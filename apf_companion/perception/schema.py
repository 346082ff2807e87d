"""The project's zenoh JSON schemas: range scans (``apf.range_scan/1``) and goals (``apf.goal/1``).

Range scan, key ``apf/sensors/<id>/ranges`` (default ``apf/sensors/range0/ranges``), encoding
``application/json``, UTF-8, one object::

    {
      "schema": "apf.range_scan/1",
      "time_boot_ms": 123456,            # int >= 0 or null: sensor time, if the publisher has one
      "frame": "body_frd",               # or "local_ned": bearing 0 = forward, or 0 = north
      "angle_min_deg": -90.0,            # bearing of ranges_m[0]
      "angle_increment_deg": 5.0,        # bearing step between elements; CLOCKWISE positive (seen from above)
      "range_min_m": 0.2,
      "range_max_m": 12.0,
      "ranges_m": [3.5, null, 13.0, 0.1] # null = unknown; > range_max_m = free; < range_min_m = invalid
    }

Element ``i`` lies at bearing ``angle_min_deg + i * angle_increment_deg``. Numbers must be finite JSON
numbers (no NaN/Infinity tokens); ``|angle_increment_deg|`` must be at least 1e-6 when there are two or more
ranges; at most 4096 ranges. Unknown keys are ignored, so later minor versions can add fields. The
encoder writes free elements as ``range_max_m + 1`` and every NaN (unknown or invalid) as ``null``.

Goal, key ``apf/cmd/goal``, encoding ``application/json``::

    {"schema": "apf.goal/1", "north_m": 20.0, "east_m": 5.0, "down_m": -10.0, "frame": "local_ned"}

``frame`` is optional and may only be ``"local_ned"`` (local NED from the EKF origin, metres; ``down_m``
is negative above the origin).

Any bad input raises ``ProtocolError`` naming the field.
"""

from __future__ import annotations

import json
import math
from typing import Any

import numpy as np

from apf_companion.errors import ConfigError, ProtocolError
from apf_companion.perception.types import FloatArray, GoalCommand, RangeScan, ScanFrame, SectorCounts

__all__ = [
    "GOAL_SCHEMA",
    "MAX_JSON_RANGES",
    "SCAN_SCHEMA",
    "decode_goal_json",
    "decode_scan_json",
    "encode_goal_json",
    "encode_scan_json",
    "uniform_bearings_deg",
]

SCAN_SCHEMA = "apf.range_scan/1"
GOAL_SCHEMA = "apf.goal/1"
MAX_JSON_RANGES = 4096
_MAX_JSON_BYTES = 256 * 1024
_MIN_INCREMENT_DEG = 1e-6

_FRAMES = {"body_frd": ScanFrame.BODY_FRD, "local_ned": ScanFrame.LOCAL_NED}


def _reject_constant(token: str) -> float:
    msg = f"JSON number {token} is not allowed (use null for unknown)"
    raise ProtocolError(msg)


def _load_object(data: bytes | str, what: str) -> dict[str, Any]:
    if len(data) > _MAX_JSON_BYTES:
        msg = f"{what}: payload of {len(data)} bytes exceeds {_MAX_JSON_BYTES}"
        raise ProtocolError(msg)
    try:
        obj = json.loads(data, parse_constant=_reject_constant)
    except ProtocolError:
        raise
    except (ValueError, RecursionError) as err:  # JSONDecodeError and UnicodeDecodeError are ValueErrors
        msg = f"{what}: not valid UTF-8 JSON ({err})"
        raise ProtocolError(msg) from err
    if not isinstance(obj, dict):
        msg = f"{what}: expected a JSON object, got {type(obj).__name__}"
        raise ProtocolError(msg)
    return obj


def _number(obj: dict[str, Any], key: str, what: str) -> float:
    value = obj.get(key)
    # bool is an int subclass; true/false are not numbers here.
    if isinstance(value, bool) or not isinstance(value, int | float):
        msg = f"{what}: field {key!r} must be a number, got {value!r}"
        raise ProtocolError(msg)
    try:
        out = float(value)
    except OverflowError:  # a JSON integer beyond float range
        out = math.inf
    if not math.isfinite(out):
        msg = f"{what}: field {key!r} must be finite, got {value!r}"
        raise ProtocolError(msg)
    return out


def _check_schema(obj: dict[str, Any], expected: str, what: str) -> None:
    schema = obj.get("schema")
    if schema != expected:
        msg = f"{what}: field 'schema' must be {expected!r}, got {schema!r}"
        raise ProtocolError(msg)


def uniform_bearings_deg(scan: RangeScan) -> tuple[float, float]:
    """``(angle_min_deg, angle_increment_deg)`` of a scan with evenly spaced bearings.

    Raises ConfigError when the bearings are not evenly spaced (within 1e-6 deg, modulo 360).
    """
    b_deg = np.rad2deg(scan.bearings_rad)
    if b_deg.size == 0:
        return 0.0, 0.0
    if b_deg.size == 1:
        return float(b_deg[0]), 0.0
    steps = np.remainder(np.diff(b_deg) + 180.0, 360.0) - 180.0
    inc = float(np.mean(steps))
    if not np.allclose(steps, inc, rtol=0.0, atol=1e-6):
        msg = "scan bearings must be evenly spaced to be encoded as angle_min + i * angle_increment"
        raise ConfigError(msg)
    return float(b_deg[0]), inc


def encode_scan_json(scan: RangeScan) -> bytes:
    """Encode ``scan`` as an ``apf.range_scan/1`` JSON object (UTF-8 bytes).

    The bearings must be evenly spaced (else ConfigError). Free elements are written as
    ``range_max_m + 1``, NaN as ``null``. ``t_s`` is not sent: it is the receiver's clock.
    """
    angle_min_deg, inc_deg = uniform_bearings_deg(scan)
    free_value = scan.range_max_m + 1.0
    ranges: list[float | None] = [
        None if math.isnan(r) else (free_value if math.isinf(r) else r) for r in scan.ranges_m.tolist()
    ]
    obj = {
        "schema": SCAN_SCHEMA,
        "time_boot_ms": scan.time_boot_ms,
        "frame": scan.frame.value,
        "angle_min_deg": angle_min_deg,
        "angle_increment_deg": inc_deg,
        "range_min_m": scan.range_min_m,
        "range_max_m": scan.range_max_m,
        "ranges_m": ranges,
    }
    return json.dumps(obj, separators=(",", ":"), allow_nan=False).encode()


def _scan_values(raw: object, inc_deg: float, what: str) -> FloatArray:
    """The ``ranges_m`` list as float64 (null -> NaN); ProtocolError for anything else."""
    if not isinstance(raw, list):
        msg = f"{what}: field 'ranges_m' must be a list, got {type(raw).__name__}"
        raise ProtocolError(msg)
    if len(raw) > MAX_JSON_RANGES:
        msg = f"{what}: field 'ranges_m' has {len(raw)} elements, at most {MAX_JSON_RANGES} allowed"
        raise ProtocolError(msg)
    if len(raw) > 1 and abs(inc_deg) < _MIN_INCREMENT_DEG:
        msg = f"{what}: field 'angle_increment_deg' must be at least {_MIN_INCREMENT_DEG} in size for {len(raw)} ranges"
        raise ProtocolError(msg)
    if any(v is not None and (isinstance(v, bool) or not isinstance(v, int | float)) for v in raw):
        msg = f"{what}: field 'ranges_m' may hold only numbers and null"
        raise ProtocolError(msg)
    try:
        values = np.array([np.nan if v is None else float(v) for v in raw], dtype=np.float64)
    except OverflowError as err:
        msg = f"{what}: field 'ranges_m' holds a number too large to be finite"
        raise ProtocolError(msg) from err
    if not np.all(np.isfinite(values[~np.isnan(values)])):
        msg = f"{what}: field 'ranges_m' holds a number too large to be finite"
        raise ProtocolError(msg)
    return values


def _classify_m(values: FloatArray, range_min_m: float, range_max_m: float) -> tuple[FloatArray, SectorCounts]:
    """Ranges (NaN unknown/invalid, +inf free) and the counts, as in ``decode_scan_json``."""
    unknown = np.isnan(values)
    free = ~unknown & (values > range_max_m)
    invalid = ~unknown & (values < range_min_m)
    ranges_m = np.where(unknown | invalid, np.nan, values)
    ranges_m[free] = np.inf
    counts = SectorCounts(
        valid=int(values.size - np.count_nonzero(unknown | free | invalid)),
        free=int(np.count_nonzero(free)),
        unknown=int(np.count_nonzero(unknown)),
        invalid=int(np.count_nonzero(invalid)),
    )
    return ranges_m, counts


def decode_scan_json(data: bytes | str, *, t_s: float, source: str = "zenoh:json") -> RangeScan:
    """Decode an ``apf.range_scan/1`` JSON payload into a ``RangeScan`` stamped ``t_s``.

    Classification: null -> NaN (unknown); above ``range_max_m`` -> +inf (free); below ``range_min_m``
    -> NaN (invalid); otherwise an obstacle. Raises ProtocolError naming the offending field.
    """
    what = SCAN_SCHEMA
    obj = _load_object(data, what)
    _check_schema(obj, SCAN_SCHEMA, what)
    frame_name = obj.get("frame")
    if not isinstance(frame_name, str) or frame_name not in _FRAMES:
        msg = f"{what}: field 'frame' must be 'body_frd' or 'local_ned', got {frame_name!r}"
        raise ProtocolError(msg)
    time_boot_ms = obj.get("time_boot_ms")
    if time_boot_ms is not None and (
        isinstance(time_boot_ms, bool) or not isinstance(time_boot_ms, int) or time_boot_ms < 0
    ):
        msg = f"{what}: field 'time_boot_ms' must be an int >= 0 or null, got {time_boot_ms!r}"
        raise ProtocolError(msg)
    angle_min_deg = _number(obj, "angle_min_deg", what)
    inc_deg = _number(obj, "angle_increment_deg", what)
    range_min_m = _number(obj, "range_min_m", what)
    range_max_m = _number(obj, "range_max_m", what)
    if not 0.0 <= range_min_m <= range_max_m:
        msg = f"{what}: fields 'range_min_m'/'range_max_m' need 0 <= min <= max, got {range_min_m}, {range_max_m}"
        raise ProtocolError(msg)
    values = _scan_values(obj.get("ranges_m"), inc_deg, what)
    bearings_deg = angle_min_deg + inc_deg * np.arange(values.size, dtype=np.float64)
    if not np.all(np.isfinite(bearings_deg)):
        msg = f"{what}: fields 'angle_min_deg'/'angle_increment_deg' give non-finite bearings"
        raise ProtocolError(msg)
    ranges_m, counts = _classify_m(values, range_min_m, range_max_m)
    return RangeScan(
        t_s=t_s,
        frame=_FRAMES[frame_name],
        bearings_rad=np.deg2rad(np.remainder(bearings_deg + 180.0, 360.0) - 180.0),
        ranges_m=ranges_m,
        range_min_m=range_min_m,
        range_max_m=range_max_m,
        time_boot_ms=time_boot_ms,
        counts=counts,
        source=source,
    )


def encode_goal_json(goal: GoalCommand) -> bytes:
    """Encode ``goal`` as an ``apf.goal/1`` JSON object (UTF-8 bytes)."""
    north_m, east_m, down_m = (float(v) for v in goal.pos_ned_m)
    obj = {"schema": GOAL_SCHEMA, "north_m": north_m, "east_m": east_m, "down_m": down_m, "frame": goal.frame}
    return json.dumps(obj, separators=(",", ":"), allow_nan=False).encode()


def decode_goal_json(data: bytes | str) -> GoalCommand:
    """Decode an ``apf.goal/1`` JSON payload. Raises ProtocolError naming the offending field."""
    what = GOAL_SCHEMA
    obj = _load_object(data, what)
    _check_schema(obj, GOAL_SCHEMA, what)
    frame = obj.get("frame", "local_ned")
    if frame != "local_ned":
        msg = f"{what}: field 'frame' must be 'local_ned' (or absent), got {frame!r}"
        raise ProtocolError(msg)
    pos = [_number(obj, key, what) for key in ("north_m", "east_m", "down_m")]
    return GoalCommand(pos_ned_m=np.array(pos, dtype=np.float64), frame="local_ned")
