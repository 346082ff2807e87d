"""Links at the edges: MAVLink over UDP/TCP/serial (asyncio, MAVLink 2 signing), zenoh, and .tlog recording."""

from __future__ import annotations

from apf_companion.links.endpoint import Endpoint, EndpointKind, parse_endpoint
from apf_companion.links.mavlink import LinkStats, MavlinkLink, load_dialect
from apf_companion.links.signing import (
    LinkSigning,
    SigningParams,
    SigningStats,
    TimestampFile,
    TimestampKeeper,
    Verdict,
    accept_unsigned_only,
    accept_unsigned_telemetry,
    load_signing_key,
    signing_timestamp,
    start_timestamp,
)
from apf_companion.links.tlog import TlogWriter

__all__ = [
    "Endpoint",
    "EndpointKind",
    "LinkSigning",
    "LinkStats",
    "MavlinkLink",
    "SigningParams",
    "SigningStats",
    "TimestampFile",
    "TimestampKeeper",
    "TlogWriter",
    "Verdict",
    "accept_unsigned_only",
    "accept_unsigned_telemetry",
    "load_dialect",
    "load_signing_key",
    "parse_endpoint",
    "signing_timestamp",
    "start_timestamp",
]
