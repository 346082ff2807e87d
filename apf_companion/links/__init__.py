"""Links at the edges: MAVLink over UDP/TCP/serial (asyncio), zenoh, and .tlog recording."""

from __future__ import annotations

from apf_companion.links.endpoint import Endpoint, EndpointKind, parse_endpoint
from apf_companion.links.mavlink import LinkStats, MavlinkLink, load_dialect
from apf_companion.links.tlog import TlogWriter

__all__ = [
    "Endpoint",
    "EndpointKind",
    "LinkStats",
    "MavlinkLink",
    "TlogWriter",
    "load_dialect",
    "parse_endpoint",
]
