"""An asyncio MAVLink 2 link: pymavlink's parser and encoder fed from asyncio transports, no blocking calls.

One ``MavlinkLink`` owns one endpoint. The bytes travel through the ``Transport`` for its kind (UDP in/out,
TCP client/server, serial: ``apf_companion.links.transports.TRANSPORTS``); incoming bytes go through a
pymavlink ``MAVLink`` parser per peer with robust parsing on (``Receiver``), so junk becomes counted bad
frames instead of exceptions, and good messages land in a bounded queue (oldest dropped and counted on
overflow). Outgoing messages are packed with this link's system/component ids and a running sequence number
and written to every connected peer (a ``udpin``/``tcpin`` link replies to all peers it has heard from, like
pymavlink's ``udpin``). A ``tcp:`` client reconnects with exponential backoff. Every frame in and out can be
recorded to a ``.tlog``. The link's background tasks (the transport's receive loop, one task per TCP client)
run in one ``asyncio.TaskGroup``, owned by one supervisor task and ended by ``aclose``. With ``signing``
(``SigningParams``) every frame out is signed and every frame in is checked (apf_companion.links.signing).
"""

from __future__ import annotations

import asyncio
import contextlib
import importlib
import logging
from collections.abc import AsyncIterator, Callable
from pathlib import Path
from types import ModuleType, TracebackType
from typing import Any

from apf_companion.errors import LinkError, LinkTimeout
from apf_companion.links.endpoint import Endpoint, parse_endpoint
from apf_companion.links.receiver import LinkStats, Receiver
from apf_companion.links.signing import LinkSigning, SigningParams
from apf_companion.links.tlog import TlogWriter
from apf_companion.links.transports import TRANSPORTS

__all__ = ["LinkStats", "MavlinkLink", "load_dialect"]

log = logging.getLogger(__name__)


def load_dialect(name: str) -> ModuleType:
    """The MAVLink 2 dialect module (``pymavlink.dialects.v20.<name>``), without touching process globals."""
    try:
        return importlib.import_module(f"pymavlink.dialects.v20.{name}")
    except ImportError as err:
        msg = f"unknown MAVLink dialect {name!r}"
        raise LinkError(msg) from err


class MavlinkLink:
    """An open MAVLink link. Create with ``await MavlinkLink.open(...)``; close with ``aclose`` or ``async with``.

    The facade over the link's parts, each owning its state: the transport (sockets, peers), the ``Receiver``
    (parsers, the message queue, the connected event), the ``TlogWriter`` and ``LinkSigning``. The link itself owns
    only the supervisor task, whether it is closed and the encoder (``mav``: our ids and the sequence number).
    """

    def __init__(
        self,
        endpoint: Endpoint,
        *,
        source_system: int,
        source_component: int,
        dialect: str,
        tlog_path: Path | str | None,
        rx_queue_size: int,
        signing: SigningParams | None = None,
    ) -> None:
        self.endpoint = endpoint
        self.dialect = load_dialect(dialect)
        self.mav: Any = self.dialect.MAVLink(None, srcSystem=source_system, srcComponent=source_component)
        self.stats = LinkStats()
        self.signing = LinkSigning(signing, self.mav) if signing is not None else None
        self._tlog = TlogWriter(tlog_path) if tlog_path is not None else None
        self._receiver = Receiver(
            self.dialect, self.stats, queue_size=rx_queue_size, tlog=self._tlog, signing=self.signing
        )
        self._transport = TRANSPORTS[endpoint.kind](endpoint, self._receiver)
        self._supervisor: asyncio.Task[None] | None = None
        self._closed = False

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
        signing: SigningParams | None = None,
    ) -> MavlinkLink:
        """Open a link. Listening kinds are bound when this returns; a ``tcp:`` client connects in the background.

        With ``signing``, every frame sent is signed and every frame received is checked
        (apf_companion.links.signing); ``link.signing`` holds the timestamp and the verdict counts.

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
            signing=signing,
        )
        try:
            await link._transport.open()
        except BaseException as err:
            await link.aclose()
            if not isinstance(err, OSError):
                raise
            msg = f"cannot open MAVLink endpoint {ep}: {err}"
            raise LinkError(msg) from err
        link._supervisor = asyncio.get_running_loop().create_task(link._supervise(), name=f"mavlink[{ep}]")
        return link

    async def _supervise(self) -> None:
        """Own the link's background tasks: the transport's receive loop and whatever it starts."""
        try:
            async with asyncio.TaskGroup() as tasks:
                tasks.create_task(self._transport.run(tasks), name=f"mavlink[{self.endpoint}].receive")
        except Exception:  # a bug in a transport: say so loudly; the link then sends and receives nothing
            log.exception("mavlink.link_failed", extra={"endpoint": str(self.endpoint)})

    async def aclose(self) -> None:
        """Close every socket, stop background tasks and flush the tlog. Safe to call twice."""
        if self._closed:
            return
        self._closed = True
        if self._supervisor is not None:
            self._supervisor.cancel()
            with contextlib.suppress(asyncio.CancelledError):
                await self._supervisor
        await self._transport.aclose()
        if self._tlog is not None:
            self._tlog.close()

    async def __aenter__(self) -> MavlinkLink:
        return self

    async def __aexit__(
        self, exc_type: type[BaseException] | None, exc: BaseException | None, tb: TracebackType | None
    ) -> None:
        await self.aclose()

    @property
    def local_address(self) -> tuple[str, int] | None:
        """The bound (host, port) of a UDP or ``tcpin`` link (port 0 in the endpoint = the port picked)."""
        return self._transport.local_address

    @property
    def is_connected(self) -> bool:
        """tcp: connected now; udpin/tcpin: at least one peer; udpout/serial: open."""
        return not self._closed and self._transport.is_connected

    async def wait_connected(self, timeout: float) -> None:
        """Wait until a peer is connected. Raises LinkTimeout after ``timeout`` seconds."""
        try:
            async with asyncio.timeout(timeout):
                await self._receiver.connected.wait()
        except TimeoutError as err:
            msg = f"{self.endpoint}: no peer connected within {timeout:.1f} s"
            raise LinkTimeout(msg) from err

    async def recv(self, timeout: float | None = None) -> Any:
        """The next good message. Raises LinkTimeout if none arrives within ``timeout`` seconds."""
        try:
            async with asyncio.timeout(timeout):
                return await self._receiver.queue.get()
        except TimeoutError as err:
            msg = f"{self.endpoint}: no message within {timeout} s"
            raise LinkTimeout(msg) from err

    def recv_nowait(self) -> Any | None:
        """The next queued message, or None."""
        try:
            return self._receiver.queue.get_nowait()
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
        try:
            async with asyncio.timeout(timeout):
                while True:
                    msg = await self._receiver.queue.get()
                    if (types is None or msg.get_type() in types) and (condition is None or condition(msg)):
                        return msg
        except TimeoutError as err:
            text = f"{self.endpoint}: no {types or 'message'} within {timeout} s"
            raise LinkTimeout(text) from err

    async def messages(self) -> AsyncIterator[Any]:
        """Every good message as it arrives (an endless async generator; break or cancel to stop)."""
        while True:
            yield await self._receiver.queue.get()

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
        if not self._closed and self._transport.send(data):
            self.stats.bytes_sent += len(data)
        else:
            self.stats.send_dropped += 1
