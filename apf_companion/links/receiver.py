"""Bytes in, good MAVLink messages out: one robust pymavlink parser per peer and a bounded queue.

A transport hands every chunk it reads to ``Receiver.feed`` with a key naming the peer it came from (a UDP
address, one key per TCP connection, ``"serial"``), so interleaved peers never corrupt each other's frames.
Junk becomes counted bad frames, never exceptions. With signing on, every good frame is checked (``LinkSigning``)
and the ones it refuses are counted there and dropped. When the queue is full the OLDEST message is dropped and
counted: telemetry is latest-wins.
"""

from __future__ import annotations

import asyncio
import logging
from collections.abc import Hashable
from dataclasses import dataclass
from types import ModuleType
from typing import Any

from apf_companion.links.signing import LinkSigning
from apf_companion.links.tlog import TlogWriter

__all__ = ["LinkStats", "PeerKey", "Receiver"]

log = logging.getLogger(__name__)

PeerKey = Hashable  # which peer a chunk came from: each key gets its own parser


@dataclass(slots=True)
class LinkStats:
    """Link health counters (monotonically increasing)."""

    packets_received: int = 0
    packets_sent: int = 0
    bad_frames: int = 0
    bytes_received: int = 0
    bytes_sent: int = 0
    send_dropped: int = 0  # no peer connected, or the peer is stalled
    rx_dropped: int = 0  # receive queue overflow (oldest dropped)
    reconnects: int = 0


class Receiver:
    """What a transport reports to its link: bytes per peer, and whether a peer is connected."""

    def __init__(
        self,
        dialect: ModuleType,
        stats: LinkStats,
        *,
        queue_size: int,
        tlog: TlogWriter | None,
        signing: LinkSigning | None = None,
    ) -> None:
        self.stats = stats
        self.signing = signing
        self.queue: asyncio.Queue[Any] = asyncio.Queue(maxsize=queue_size)
        self.connected = asyncio.Event()  # set while ``wait_connected`` may return
        self._dialect = dialect
        self._tlog = tlog
        self._parsers: dict[PeerKey, Any] = {}

    def feed(self, data: bytes, peer: PeerKey, *, datagram: bool) -> None:
        """Parse ``data`` from ``peer``; queue the good messages. ``datagram``: ``data`` ends on a frame boundary."""
        self.stats.bytes_received += len(data)
        parser = self._parser(peer)
        try:
            msgs = parser.parse_buffer(data) or []
        except Exception:  # pymavlink can still raise on pathological input; never let it reach the loop
            log.debug("mavlink.parse_error", exc_info=True)
            msgs = []
            self.stats.bad_frames += 1
            self.forget(peer)
        for msg in msgs:
            self._accept(msg)
        if datagram and parser.buf_len() > 0:
            # A datagram ends on a frame boundary: leftover bytes are a truncated frame, not a prefix of the next.
            self.stats.bad_frames += 1
            self.forget(peer)

    def forget(self, peer: PeerKey) -> None:
        """Drop ``peer``'s parser (it disconnected, or its stream is out of step)."""
        self._parsers.pop(peer, None)

    def _parser(self, peer: PeerKey) -> Any:
        parser = self._parsers.get(peer)
        if parser is None:
            parser = self._dialect.MAVLink(None)
            parser.robust_parsing = True
            self._parsers[peer] = parser
        return parser

    def _accept(self, msg: Any) -> None:
        if msg.get_type() == "BAD_DATA":
            self.stats.bad_frames += 1
            return
        if self.signing is not None and not self.signing.accept(msg):
            return  # counted by the signing check
        self.stats.packets_received += 1
        if self._tlog is not None:
            self._tlog.write(bytes(msg.get_msgbuf()))
        if self.queue.full():
            self.queue.get_nowait()
            self.stats.rx_dropped += 1
        self.queue.put_nowait(msg)
