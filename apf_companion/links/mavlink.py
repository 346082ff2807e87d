"""An asyncio MAVLink 2 link: pymavlink's parser and encoder fed from asyncio transports, no blocking calls.

One ``MavlinkLink`` owns one endpoint (UDP in/out, TCP client/server, serial). Incoming bytes go through a
pymavlink ``MAVLink`` parser per peer with robust parsing on, so junk becomes counted bad frames instead of
exceptions; good messages land in a bounded queue (oldest dropped and counted on overflow). Outgoing messages are
packed with this link's system/component ids and a running sequence number and written to every connected peer
(a ``udpin``/``tcpin`` link replies to all peers it has heard from, like pymavlink's ``udpin``). A ``tcp:`` client
reconnects with exponential backoff. Every frame in and out can be recorded to a ``.tlog``.
"""

from __future__ import annotations

import asyncio
import contextlib
import importlib
import logging
import os
import time
from collections import OrderedDict
from collections.abc import AsyncIterator, Callable
from dataclasses import dataclass
from pathlib import Path
from types import ModuleType, TracebackType
from typing import Any

from apf_companion.errors import LinkError, LinkTimeout
from apf_companion.links.endpoint import Endpoint, EndpointKind, parse_endpoint
from apf_companion.links.tlog import TlogWriter

log = logging.getLogger(__name__)

MAX_UDP_PEERS = 16  # udpin replies to at most this many recent peers
TCP_BACKOFF_MIN_S = 0.2
TCP_BACKOFF_MAX_S = 5.0
MAX_WRITE_BUFFER_B = 1 << 20  # stop queueing to a stalled TCP peer beyond this


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


def load_dialect(name: str) -> ModuleType:
    """The MAVLink 2 dialect module (``pymavlink.dialects.v20.<name>``), without touching process globals."""
    try:
        return importlib.import_module(f"pymavlink.dialects.v20.{name}")
    except ImportError as err:
        msg = f"unknown MAVLink dialect {name!r}"
        raise LinkError(msg) from err


class MavlinkLink:
    """An open MAVLink link. Create with ``await MavlinkLink.open(...)``; close with ``aclose`` or ``async with``."""

    def __init__(
        self,
        endpoint: Endpoint,
        *,
        source_system: int,
        source_component: int,
        dialect: str,
        tlog_path: Path | str | None,
        rx_queue_size: int,
    ) -> None:
        self.endpoint = endpoint
        self.dialect = load_dialect(dialect)
        self.mav: Any = self.dialect.MAVLink(None, srcSystem=source_system, srcComponent=source_component)
        self.stats = LinkStats()
        self._queue: asyncio.Queue[Any] = asyncio.Queue(maxsize=rx_queue_size)
        self._parsers: dict[object, Any] = {}
        self._tlog = TlogWriter(tlog_path) if tlog_path is not None else None
        self._udp: asyncio.DatagramTransport | None = None
        self._udp_peers: OrderedDict[tuple[str, int], None] = OrderedDict()
        self._tcp_writers: dict[object, asyncio.StreamWriter] = {}
        self._server: asyncio.Server | None = None
        self._serial: Any = None
        self._serial_fd: int | None = None
        self._tasks: set[asyncio.Task[None]] = set()
        self._connected = asyncio.Event()
        self._closed = False
        self.local_address: tuple[str, int] | None = None

    # ----------------------------------------------------------------------------------------- lifecycle
    @classmethod
    async def open(
        cls,
        endpoint: Endpoint | str,
        *,
        source_system: int,
        source_component: int,
        tlog_path: Path | str | None = None,
        dialect: str = "ardupilotmega",
        rx_queue_size: int = 4096,
    ) -> MavlinkLink:
        """Open a link. Listening kinds are bound when this returns; a ``tcp:`` client connects in the background.

        Raises:
            LinkError: the socket or serial port cannot be opened (address in use, no such device, ...).
        """
        ep = parse_endpoint(endpoint) if isinstance(endpoint, str) else endpoint
        link = cls(
            ep,
            source_system=source_system,
            source_component=source_component,
            dialect=dialect,
            tlog_path=tlog_path,
            rx_queue_size=rx_queue_size,
        )
        try:
            await link._start()
        except OSError as err:
            await link.aclose()
            msg = f"cannot open MAVLink endpoint {ep}: {err}"
            raise LinkError(msg) from err
        return link

    async def _start(self) -> None:
        loop = asyncio.get_running_loop()
        ep = self.endpoint
        if ep.kind is EndpointKind.UDPIN:
            self._udp, _ = await loop.create_datagram_endpoint(
                lambda: _UdpProtocol(self), local_addr=(ep.host, ep.port)
            )
            self.local_address = self._udp.get_extra_info("sockname")[:2]
        elif ep.kind is EndpointKind.UDPOUT:
            self._udp, _ = await loop.create_datagram_endpoint(
                lambda: _UdpProtocol(self), remote_addr=(ep.host, ep.port)
            )
            self.local_address = self._udp.get_extra_info("sockname")[:2]
            self._connected.set()
        elif ep.kind is EndpointKind.TCPIN:
            self._server = await asyncio.start_server(self._serve_tcp_client, ep.host, ep.port)
            self.local_address = self._server.sockets[0].getsockname()[:2]
        elif ep.kind is EndpointKind.TCP:
            self._spawn(self._tcp_client_loop())
        else:
            self._open_serial()

    def _spawn(self, coro: Any) -> None:
        task: asyncio.Task[None] = asyncio.get_running_loop().create_task(coro)
        self._tasks.add(task)
        task.add_done_callback(self._tasks.discard)

    async def aclose(self) -> None:
        """Close every socket, stop background tasks and flush the tlog. Safe to call twice."""
        if self._closed:
            return
        self._closed = True
        for task in list(self._tasks):
            task.cancel()
        for task in list(self._tasks):
            with contextlib.suppress(asyncio.CancelledError, Exception):
                await task
        for writer in list(self._tcp_writers.values()):
            writer.close()
        self._tcp_writers.clear()
        if self._server is not None:
            self._server.close()
            with contextlib.suppress(Exception):
                await asyncio.wait_for(self._server.wait_closed(), 1.0)
        if self._udp is not None:
            self._udp.close()
        if self._serial is not None:
            if self._serial_fd is not None:
                asyncio.get_running_loop().remove_reader(self._serial_fd)
            self._serial.close()
        if self._tlog is not None:
            self._tlog.close()

    async def __aenter__(self) -> MavlinkLink:
        return self

    async def __aexit__(
        self, exc_type: type[BaseException] | None, exc: BaseException | None, tb: TracebackType | None
    ) -> None:
        await self.aclose()

    @property
    def is_connected(self) -> bool:
        """tcp: connected now; udpin/tcpin: at least one peer; udpout/serial: always."""
        if self.endpoint.kind is EndpointKind.UDPIN:
            return bool(self._udp_peers)
        if self.endpoint.kind in (EndpointKind.TCP, EndpointKind.TCPIN):
            return bool(self._tcp_writers)
        return not self._closed

    async def wait_connected(self, timeout: float) -> None:
        """Wait until ``is_connected``. Raises LinkTimeout after ``timeout`` seconds."""
        try:
            async with asyncio.timeout(timeout):
                await self._connected.wait()
        except TimeoutError as err:
            msg = f"{self.endpoint}: no peer connected within {timeout:.1f} s"
            raise LinkTimeout(msg) from err

    # ----------------------------------------------------------------------------------------- receive
    def _on_bytes(self, data: bytes, peer: object, *, datagram: bool) -> None:
        self.stats.bytes_received += len(data)
        parser = self._parsers.get(peer)
        if parser is None:
            parser = self.dialect.MAVLink(None)
            parser.robust_parsing = True
            self._parsers[peer] = parser
        try:
            msgs = parser.parse_buffer(data) or []
        except Exception:  # pymavlink can still raise on pathological input; never let it reach the loop
            log.debug("mavlink.parse_error", exc_info=True)
            msgs = []
            self.stats.bad_frames += 1
            self._parsers.pop(peer, None)
        for msg in msgs:
            if msg.get_type() == "BAD_DATA":
                self.stats.bad_frames += 1
                continue
            self.stats.packets_received += 1
            if self._tlog is not None:
                self._tlog.write(bytes(msg.get_msgbuf()))
            if self._queue.full():
                self._queue.get_nowait()
                self.stats.rx_dropped += 1
            self._queue.put_nowait(msg)
        if datagram and parser.buf_len() > 0:
            # A datagram ends on a frame boundary: leftover bytes are a truncated frame, not a prefix of the next.
            self.stats.bad_frames += 1
            self._parsers.pop(peer, None)

    async def recv(self, timeout: float | None = None) -> Any:
        """The next good message. Raises LinkTimeout if none arrives within ``timeout`` seconds."""
        try:
            async with asyncio.timeout(timeout):
                return await self._queue.get()
        except TimeoutError as err:
            msg = f"{self.endpoint}: no message within {timeout} s"
            raise LinkTimeout(msg) from err

    def recv_nowait(self) -> Any | None:
        """The next queued message, or None."""
        try:
            return self._queue.get_nowait()
        except asyncio.QueueEmpty:
            return None

    async def recv_match(
        self,
        *,
        type: str | tuple[str, ...] | None = None,
        condition: Callable[[Any], bool] | None = None,
        timeout: float,
    ) -> Any:
        """Like pymavlink's ``recv_match``: the next message of ``type`` passing ``condition``; others are discarded.

        Raises:
            LinkTimeout: nothing matched within ``timeout`` seconds.
        """
        types = (type,) if isinstance(type, str) else type
        deadline = time.monotonic() + timeout
        while True:
            remaining = deadline - time.monotonic()
            if remaining <= 0:
                msg = f"{self.endpoint}: no {types or 'message'} within {timeout} s"
                raise LinkTimeout(msg)
            msg_ = await self.recv(timeout=remaining)
            if types is not None and msg_.get_type() not in types:
                continue
            if condition is not None and not condition(msg_):
                continue
            return msg_

    async def messages(self) -> AsyncIterator[Any]:
        """Every good message as it arrives (an endless async generator; break or cancel to stop)."""
        while True:
            yield await self._queue.get()

    # ----------------------------------------------------------------------------------------- send
    def send(self, msg: Any) -> None:
        """Pack ``msg`` (from ``link.mav.<name>_encode(...)``) with our ids and the next sequence number; send it."""
        buf = bytes(msg.pack(self.mav))
        self.mav.seq = (self.mav.seq + 1) % 256
        self.send_bytes(buf)
        self.stats.packets_sent += 1
        if self._tlog is not None:
            self._tlog.write(buf)

    def send_bytes(self, data: bytes) -> None:
        """Write raw bytes to every connected peer (counted as dropped when there is none)."""
        if self._closed:
            self.stats.send_dropped += 1
            return
        kind = self.endpoint.kind
        sent = False
        if kind is EndpointKind.UDPIN and self._udp is not None:
            for addr in self._udp_peers:
                self._udp.sendto(data, addr)
                sent = True
        elif kind is EndpointKind.UDPOUT and self._udp is not None:
            self._udp.sendto(data)
            sent = True
        elif kind in (EndpointKind.TCP, EndpointKind.TCPIN):
            for writer in self._tcp_writers.values():
                if writer.transport.get_write_buffer_size() < MAX_WRITE_BUFFER_B:
                    writer.write(data)
                    sent = True
        elif kind is EndpointKind.SERIAL and self._serial_fd is not None:
            try:
                os.write(self._serial_fd, data)
                sent = True
            except (BlockingIOError, OSError):
                sent = False
        if sent:
            self.stats.bytes_sent += len(data)
        else:
            self.stats.send_dropped += 1

    # ----------------------------------------------------------------------------------------- UDP
    def _udp_peer_heard(self, addr: tuple[str, int]) -> None:
        self._udp_peers[addr] = None
        self._udp_peers.move_to_end(addr)
        while len(self._udp_peers) > MAX_UDP_PEERS:
            self._udp_peers.popitem(last=False)
        self._connected.set()

    # ----------------------------------------------------------------------------------------- TCP
    async def _pump_stream(self, reader: asyncio.StreamReader, key: object) -> None:
        while True:
            data = await reader.read(65536)
            if not data:
                return
            self._on_bytes(data, key, datagram=False)

    async def _run_tcp_connection(self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        """One TCP peer (a tcpin client or our tcp: connection): register it, read until it ends, forget it."""
        key = object()
        self._tcp_writers[key] = writer
        self._connected.set()
        try:
            await self._pump_stream(reader, key)
        except (ConnectionError, OSError):
            pass
        finally:
            self._tcp_writers.pop(key, None)
            self._parsers.pop(key, None)
            if not self._tcp_writers:
                self._connected.clear()
            writer.close()

    async def _serve_tcp_client(self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        task = asyncio.current_task()
        if task is not None:
            self._tasks.add(task)  # so aclose cancels it
        try:
            await self._run_tcp_connection(reader, writer)
        finally:
            if task is not None:
                self._tasks.discard(task)

    async def _tcp_client_loop(self) -> None:
        ep = self.endpoint
        backoff = TCP_BACKOFF_MIN_S
        first = True
        while True:
            try:
                reader, writer = await asyncio.open_connection(ep.host, ep.port)
            except OSError as err:
                log.debug("mavlink.tcp_connect_failed", extra={"endpoint": str(ep), "error": str(err)})
                await asyncio.sleep(backoff)
                backoff = min(backoff * 2, TCP_BACKOFF_MAX_S)
                continue
            if not first:
                self.stats.reconnects += 1
            first = False
            backoff = TCP_BACKOFF_MIN_S
            log.info("mavlink.tcp_connected", extra={"endpoint": str(ep)})
            await self._run_tcp_connection(reader, writer)
            log.warning("mavlink.tcp_disconnected", extra={"endpoint": str(ep)})
            await asyncio.sleep(backoff)

    # ----------------------------------------------------------------------------------------- serial
    def _open_serial(self) -> None:
        try:
            import serial  # pyserial: only needed for serial endpoints
        except ImportError as err:
            msg = "serial endpoints need pyserial (pip install pyserial)"
            raise LinkError(msg) from err
        try:
            port = serial.Serial(self.endpoint.device, self.endpoint.baud, timeout=0, write_timeout=0)
        except (serial.SerialException, OSError) as err:
            raise OSError(str(err)) from err
        self._serial = port
        self._serial_fd = port.fileno()
        os.set_blocking(self._serial_fd, False)
        asyncio.get_running_loop().add_reader(self._serial_fd, self._on_serial_readable)
        self._connected.set()

    def _on_serial_readable(self) -> None:
        assert self._serial_fd is not None
        try:
            data = os.read(self._serial_fd, 4096)
        except (BlockingIOError, InterruptedError):
            return
        except OSError:
            log.warning("mavlink.serial_read_failed", exc_info=True)
            return
        if data:
            self._on_bytes(data, "serial", datagram=False)


class _UdpProtocol(asyncio.DatagramProtocol):
    def __init__(self, link: MavlinkLink) -> None:
        self.link = link

    def datagram_received(self, data: bytes, addr: tuple[str, int]) -> None:
        if self.link.endpoint.kind is EndpointKind.UDPIN:
            self.link._udp_peer_heard(addr)
        self.link._on_bytes(data, addr, datagram=True)

    def error_received(self, exc: Exception) -> None:
        # ICMP port-unreachable from a udpout peer that is not up yet: normal while the other end starts.
        self.link.stats.send_dropped += 1
