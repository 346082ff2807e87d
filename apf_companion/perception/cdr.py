"""ROS 2 ``sensor_msgs/msg/LaserScan`` in CDR, as zenoh-bridge-ros2dds publishes it.

Wire format (OMG CDR, XCDR1, what ROS 2 DDS middlewares put on the wire): a 4-byte encapsulation header
``00 01 00 00`` (CDR little-endian; ``00 00`` = big-endian is read too; the last two "options" bytes are
ignored), then the body, each primitive aligned to its size counted from the start of the body::

    int32   header.stamp.sec
    uint32  header.stamp.nanosec
    string  header.frame_id          # uint32 length including the NUL, bytes, NUL
    float32 angle_min, angle_max, angle_increment   [rad, counter-clockwise about z up]
    float32 time_increment, scan_time               [s]
    float32 range_min, range_max                    [m]
    float32[] ranges                 # uint32 count, values [m]
    float32[] intensities            # uint32 count, values

Angles: ROS (REP 103) measures LaserScan angles in a FLU frame (x forward, y left, z up), counter-clockwise
positive. This project's body frame is FRD with clockwise-positive bearings, so ``bearing_frd = -angle``
(plus ``mount_yaw_rad`` for a sensor not facing forward). A sensor mounted upside down is not supported.

Ranges (REP 117 and the message's comments): +inf = nothing within range_max (free); NaN = erroneous
(invalid); -inf = too close to measure (invalid); finite values outside [range_min, range_max] "should be
discarded" (invalid). The ROS stamp is wall time, not the autopilot's boot time: ``time_boot_ms`` is None
and the caller stamps the scan on receipt.
"""

from __future__ import annotations

import math
import struct
from dataclasses import dataclass

import numpy as np

from apf_companion.errors import ConfigError, ProtocolError
from apf_companion.perception.schema import uniform_bearings_deg
from apf_companion.perception.types import FloatArray, RangeScan, ScanFrame, SectorCounts

__all__ = [
    "CDR_BE",
    "CDR_LE",
    "MAX_CDR_RANGES",
    "LaserScanMsg",
    "decode_laserscan_cdr",
    "encode_laserscan_cdr",
    "laserscan_to_scan",
    "parse_laserscan_cdr",
]

CDR_BE = b"\x00\x00"
CDR_LE = b"\x00\x01"
MAX_CDR_RANGES = 65536
_MAX_FRAME_ID_BYTES = 1024
_FLOAT32 = {"<": np.dtype("<f4"), ">": np.dtype(">f4")}


@dataclass(frozen=True, slots=True, kw_only=True, eq=False)
class LaserScanMsg:
    """The fields of a decoded ``sensor_msgs/msg/LaserScan``, in ROS units and conventions (CCW, FLU)."""

    stamp_sec: int
    stamp_nanosec: int
    frame_id: str
    angle_min: float
    angle_max: float
    angle_increment: float
    time_increment: float
    scan_time: float
    range_min: float
    range_max: float
    ranges: FloatArray
    intensities: FloatArray


class _Reader:
    """Bounds-checked CDR reader over the body (offsets are relative to the body for alignment)."""

    __slots__ = ("_body", "_order", "pos")

    def __init__(self, body: bytes, order: str) -> None:
        self._body = body
        self._order = order
        self.pos = 0

    def _need(self, n: int, what: str) -> None:
        if n > len(self._body) - self.pos:
            msg = f"LaserScan CDR truncated in {what}: need {n} bytes at offset {self.pos}"
            raise ProtocolError(msg)

    def align(self, size: int) -> None:
        self.pos += -self.pos % size

    def unpack(self, fmt: str, what: str) -> tuple[float | int, ...]:
        s = struct.Struct(self._order + fmt)
        self.align(4)
        self._need(s.size, what)
        out = s.unpack_from(self._body, self.pos)
        self.pos += s.size
        return out

    def string(self, what: str) -> str:
        (length,) = self.unpack("I", what)
        n = int(length)
        if n == 0 or n > _MAX_FRAME_ID_BYTES:
            msg = f"LaserScan CDR: {what} length {n} out of range 1..{_MAX_FRAME_ID_BYTES}"
            raise ProtocolError(msg)
        self._need(n, what)
        raw = self._body[self.pos : self.pos + n]
        self.pos += n
        if raw[-1] != 0:
            msg = f"LaserScan CDR: {what} is not NUL-terminated"
            raise ProtocolError(msg)
        try:
            return raw[:-1].decode("utf-8")
        except UnicodeDecodeError as err:
            msg = f"LaserScan CDR: {what} is not UTF-8"
            raise ProtocolError(msg) from err

    def float32_seq(self, what: str) -> FloatArray:
        (count,) = self.unpack("I", what)
        n = int(count)
        if n > MAX_CDR_RANGES:
            msg = f"LaserScan CDR: {what} has {n} elements, at most {MAX_CDR_RANGES} allowed"
            raise ProtocolError(msg)
        self._need(4 * n, what)
        raw = np.frombuffer(self._body, dtype=_FLOAT32[self._order], count=n, offset=self.pos)
        with np.errstate(invalid="ignore"):  # signalling NaNs in the payload stay NaN
            values = raw.astype(np.float64)
        self.pos += 4 * n
        return values

    @property
    def remaining(self) -> int:
        return len(self._body) - self.pos


def parse_laserscan_cdr(data: bytes) -> LaserScanMsg:
    """Parse CDR bytes into a ``LaserScanMsg`` (no unit or convention changes).

    Raises ProtocolError on an unknown encapsulation, truncation, an over-long or unterminated frame_id,
    more than 3 trailing bytes (alignment padding), or ``intensities`` neither empty nor as long as
    ``ranges``.
    """
    data = bytes(data)
    if len(data) < 4:
        msg = f"LaserScan CDR: {len(data)} bytes, too short for the encapsulation header"
        raise ProtocolError(msg)
    kind = data[:2]
    if kind == CDR_LE:
        order = "<"
    elif kind == CDR_BE:
        order = ">"
    else:
        msg = f"LaserScan CDR: encapsulation {kind.hex()} is not plain CDR (0000 or 0001)"
        raise ProtocolError(msg)
    r = _Reader(data[4:], order)
    sec, nanosec = r.unpack("iI", "header.stamp")
    frame_id = r.string("header.frame_id")
    fields = r.unpack("7f", "angles and limits")
    ranges = r.float32_seq("ranges")
    intensities = r.float32_seq("intensities")
    if r.remaining > 3:
        msg = f"LaserScan CDR: {r.remaining} unexpected trailing bytes"
        raise ProtocolError(msg)
    if intensities.size not in (0, ranges.size):
        msg = f"LaserScan CDR: {intensities.size} intensities for {ranges.size} ranges"
        raise ProtocolError(msg)
    angle_min, angle_max, angle_increment, time_increment, scan_time, range_min, range_max = (float(v) for v in fields)
    return LaserScanMsg(
        stamp_sec=int(sec),
        stamp_nanosec=int(nanosec),
        frame_id=frame_id,
        angle_min=angle_min,
        angle_max=angle_max,
        angle_increment=angle_increment,
        time_increment=time_increment,
        scan_time=scan_time,
        range_min=range_min,
        range_max=range_max,
        ranges=ranges,
        intensities=intensities,
    )


def laserscan_to_scan(
    msg: LaserScanMsg, *, t_s: float, mount_yaw_rad: float = 0.0, source: str | None = None
) -> RangeScan:
    """Turn a ROS LaserScan into a BODY_FRD ``RangeScan`` (angles negated, REP 117 ranges).

    ``mount_yaw_rad`` is the sensor's forward axis in body FRD (clockwise from the vehicle's forward).
    Raises ProtocolError for non-finite angles or limits, ``range_min > range_max``, or a zero
    ``angle_increment`` with two or more ranges.
    """
    for name in ("angle_min", "angle_increment", "range_min", "range_max"):
        if not math.isfinite(getattr(msg, name)):
            text = f"LaserScan: {name}={getattr(msg, name)} is not finite"
            raise ProtocolError(text)
    if not 0.0 <= msg.range_min <= msg.range_max:
        text = f"LaserScan: need 0 <= range_min <= range_max, got {msg.range_min}, {msg.range_max}"
        raise ProtocolError(text)
    n = msg.ranges.size
    if n > 1 and msg.angle_increment == 0.0:
        text = f"LaserScan: angle_increment is 0 for {n} ranges"
        raise ProtocolError(text)
    angles_flu = msg.angle_min + msg.angle_increment * np.arange(n, dtype=np.float64)
    if not np.all(np.isfinite(angles_flu)):
        text = "LaserScan: angle_min/angle_increment give non-finite angles"
        raise ProtocolError(text)
    bearings_frd = np.remainder(mount_yaw_rad - angles_flu + math.pi, 2.0 * math.pi) - math.pi
    r = msg.ranges
    free = np.isposinf(r)
    with np.errstate(invalid="ignore"):
        valid = np.isfinite(r) & (r >= msg.range_min) & (r <= msg.range_max)
    invalid = ~(free | valid)
    ranges_m = np.where(valid, r, np.nan)
    ranges_m[free] = np.inf
    counts = SectorCounts(
        valid=int(np.count_nonzero(valid)),
        free=int(np.count_nonzero(free)),
        invalid=int(np.count_nonzero(invalid)),
    )
    return RangeScan(
        t_s=t_s,
        frame=ScanFrame.BODY_FRD,
        bearings_rad=bearings_frd,
        ranges_m=ranges_m,
        range_min_m=msg.range_min,
        range_max_m=msg.range_max,
        time_boot_ms=None,
        counts=counts,
        source=source if source is not None else f"zenoh:laserscan:{msg.frame_id}",
    )


def decode_laserscan_cdr(data: bytes, *, t_s: float, mount_yaw_rad: float = 0.0) -> RangeScan:
    """CDR ``sensor_msgs/msg/LaserScan`` bytes to a BODY_FRD ``RangeScan`` stamped ``t_s``.

    ``parse_laserscan_cdr`` then ``laserscan_to_scan``; any malformed input raises ProtocolError.
    """
    return laserscan_to_scan(parse_laserscan_cdr(data), t_s=t_s, mount_yaw_rad=mount_yaw_rad)


def encode_laserscan_cdr(
    scan: RangeScan,
    *,
    stamp_sec: int = 0,
    stamp_nanosec: int = 0,
    frame_id: str = "base_link",
    time_increment_s: float = 0.0,
    scan_time_s: float = 0.0,
    big_endian: bool = False,
) -> bytes:
    """Encode a BODY_FRD ``scan`` as CDR ``sensor_msgs/msg/LaserScan`` (the inverse of the decoder).

    Bearings are negated into ROS's counter-clockwise angles and must be evenly spaced (else ConfigError);
    a LOCAL_NED scan raises ConfigError (a LaserScan is in a sensor frame). Ranges keep NaN and +inf, in
    float32. ``intensities`` is empty.
    """
    if scan.frame is not ScanFrame.BODY_FRD:
        msg = "encode_laserscan_cdr needs a BODY_FRD scan (a LaserScan lives in the sensor frame)"
        raise ConfigError(msg)
    angle_min_deg, inc_deg = uniform_bearings_deg(scan)
    angle_min = -math.radians(angle_min_deg)
    angle_increment = -math.radians(inc_deg)
    angle_max = angle_min + angle_increment * max(len(scan) - 1, 0)
    order = ">" if big_endian else "<"
    frame_bytes = frame_id.encode("utf-8") + b"\x00"
    body = bytearray(struct.pack(order + "iII", stamp_sec, stamp_nanosec, len(frame_bytes)))
    body += frame_bytes
    body += b"\x00" * (-len(body) % 4)
    body += struct.pack(
        order + "7f",
        angle_min,
        angle_max,
        angle_increment,
        time_increment_s,
        scan_time_s,
        scan.range_min_m,
        scan.range_max_m,
    )
    body += struct.pack(order + "I", len(scan))
    body += scan.ranges_m.astype(_FLOAT32[order]).tobytes()
    body += struct.pack(order + "I", 0)
    return (CDR_BE if big_endian else CDR_LE) + b"\x00\x00" + bytes(body)
