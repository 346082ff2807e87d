"""Pick the decoder for a zenoh sensor payload: by its encoding when that names JSON or CDR, else by its content."""

from __future__ import annotations

from apf_companion.errors import ProtocolError
from apf_companion.perception.cdr import decode_laserscan_cdr
from apf_companion.perception.schema import decode_scan_json
from apf_companion.perception.types import RangeScan

__all__ = ["ENCODING_CDR", "ENCODING_JSON", "decode_scan_payload"]

ENCODING_JSON = "application/json"
ENCODING_CDR = "application/cdr"


def decode_scan_payload(payload: bytes, encoding: str | None, *, t_s: float, mount_yaw_rad: float = 0.0) -> RangeScan:
    """Decode a sensor payload: ``apf.range_scan/1`` JSON or CDR ``sensor_msgs/msg/LaserScan``.

    An encoding of ``application/json`` or ``application/cdr`` (with or without a ``;schema`` suffix) decides.
    Any other encoding says nothing about the format, and the payload's first byte decides: ``{`` (after
    whitespace) is JSON, a NUL byte is the first byte of a CDR encapsulation header (``00 01`` little-endian,
    ``00 00`` big-endian; any other header is refused by the CDR decoder, naming it). That is how ROS 2 sources
    arrive: zenoh-bridge-ros2dds (``route_publisher.rs``, ``publisher.put(sample)``) and rmw_zenoh
    (``rmw_publisher_data.cpp``, ``z_publisher_put`` with default options) set no encoding, so their samples
    carry zenoh's default ``zenoh/bytes``; other publishers use ``application/octet-stream``.
    ``mount_yaw_rad`` applies to LaserScans only (JSON scans state their own frame). Anything else raises
    ProtocolError.
    """
    base = (encoding or "").split(";", 1)[0].strip().lower()
    if base == ENCODING_JSON:
        return decode_scan_json(payload, t_s=t_s)
    if base == ENCODING_CDR:
        return decode_laserscan_cdr(payload, t_s=t_s, mount_yaw_rad=mount_yaw_rad)
    if payload.lstrip()[:1] == b"{":
        return decode_scan_json(payload, t_s=t_s)
    if payload[:1] == b"\x00":  # JSON text never starts with NUL; every CDR encapsulation header does
        return decode_laserscan_cdr(payload, t_s=t_s, mount_yaw_rad=mount_yaw_rad)
    msg = f"sensor payload with encoding {encoding!r} is neither apf.range_scan/1 JSON nor LaserScan CDR"
    raise ProtocolError(msg)
