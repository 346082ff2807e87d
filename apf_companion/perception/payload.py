"""Pick the decoder for a zenoh sensor payload from its encoding."""

from __future__ import annotations

from apf_companion.errors import ProtocolError
from apf_companion.perception.cdr import CDR_BE, CDR_LE, decode_laserscan_cdr
from apf_companion.perception.schema import decode_scan_json
from apf_companion.perception.types import RangeScan

__all__ = ["ENCODING_CDR", "ENCODING_JSON", "decode_scan_payload"]

ENCODING_JSON = "application/json"
ENCODING_CDR = "application/cdr"


def decode_scan_payload(payload: bytes, encoding: str | None, *, t_s: float, mount_yaw_rad: float = 0.0) -> RangeScan:
    """Decode a sensor payload: ``apf.range_scan/1`` JSON or CDR ``sensor_msgs/msg/LaserScan``.

    The zenoh encoding decides (``application/json`` or ``application/cdr``, with or without a
    ``;schema`` suffix). Publishers that leave the encoding at its default (zenoh-bridge-ros2dds may) are
    sniffed: a payload starting with ``{`` is JSON, one starting with a CDR encapsulation header is CDR.
    ``mount_yaw_rad`` applies to LaserScans only (JSON scans state their own frame). Anything else raises
    ProtocolError.
    """
    base = (encoding or "").split(";", 1)[0].strip().lower()
    if base == ENCODING_JSON:
        return decode_scan_json(payload, t_s=t_s)
    if base == ENCODING_CDR:
        return decode_laserscan_cdr(payload, t_s=t_s, mount_yaw_rad=mount_yaw_rad)
    head = payload.lstrip()[:1]
    if head == b"{":
        return decode_scan_json(payload, t_s=t_s)
    if payload[:2] in (CDR_LE, CDR_BE):
        return decode_laserscan_cdr(payload, t_s=t_s, mount_yaw_rad=mount_yaw_rad)
    msg = f"sensor payload with encoding {encoding!r} is neither apf.range_scan/1 JSON nor LaserScan CDR"
    raise ProtocolError(msg)
