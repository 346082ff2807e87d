"""Serial transport: a flight controller's UART (``/dev/ttyACM0:57600``), opened with pyserial.

pyserial sets the line up (baud, raw mode); the reading and writing go through asyncio's own pipe transports
on the port's file descriptor (both accept character devices), so reads are event-driven and writes never
block: a write the UART cannot take at once is buffered by asyncio instead of being cut mid-frame. A port that
stops draining (cable pulled, autopilot halted) is skipped past ``MAX_WRITE_BUFFER_B`` buffered bytes.
"""

from __future__ import annotations

import asyncio
import contextlib
import io
import logging
from typing import Any

from apf_companion.errors import LinkError
from apf_companion.links.endpoint import Endpoint
from apf_companion.links.receiver import Receiver
from apf_companion.links.transports.base import MAX_WRITE_BUFFER_B

__all__ = ["SerialPort"]

log = logging.getLogger(__name__)

PEER = "serial"


class _SerialReader(asyncio.Protocol):
    def __init__(self, receiver: Receiver, lost: asyncio.Event) -> None:
        self._receiver = receiver
        self._lost = lost

    def data_received(self, data: bytes) -> None:
        self._receiver.feed(data, PEER, datagram=False)

    def connection_lost(self, exc: Exception | None) -> None:
        if exc is not None:
            log.warning("mavlink.serial_lost", extra={"error": str(exc)})
        self._lost.set()


class SerialPort:
    """``serial:/dev/...:BAUD``: one peer (the autopilot), connected from the moment the port opens."""

    local_address = None

    def __init__(self, endpoint: Endpoint, receiver: Receiver) -> None:
        self.endpoint = endpoint
        self.receiver = receiver
        self._port: Any = None  # serial.Serial (pyserial is untyped)
        self._reader: asyncio.ReadTransport | None = None
        self._writer: asyncio.WriteTransport | None = None
        self._lost = asyncio.Event()

    @property
    def is_connected(self) -> bool:
        return self._writer is not None and not self._writer.is_closing() and not self._lost.is_set()

    async def open(self) -> None:
        self._port = _open_port(self.endpoint)
        loop = asyncio.get_running_loop()
        fd = self._port.fileno()
        # Two views of one descriptor; closefd=False: the port itself is closed by pyserial in ``aclose``.
        self._reader, _ = await loop.connect_read_pipe(
            lambda: _SerialReader(self.receiver, self._lost), io.FileIO(fd, "rb", closefd=False)
        )
        self._writer, _ = await loop.connect_write_pipe(asyncio.Protocol, io.FileIO(fd, "wb", closefd=False))
        self.receiver.connected.set()

    async def run(self, tasks: asyncio.TaskGroup) -> None:
        await self._lost.wait()

    def send(self, data: bytes) -> bool:
        if self._writer is None or not self.is_connected:
            return False
        if self._writer.get_write_buffer_size() >= MAX_WRITE_BUFFER_B:
            return False
        self._writer.write(data)
        return True

    async def aclose(self) -> None:
        if self._reader is not None:
            self._reader.close()
        if self._writer is not None:
            self._writer.abort()  # drop unsent bytes: the link is going away
        if self._port is not None:
            with contextlib.suppress(Exception):
                self._port.close()


def _open_port(endpoint: Endpoint) -> Any:
    try:
        import serial  # pyserial: only needed for serial endpoints
    except ImportError as err:
        msg = "serial endpoints need pyserial (pip install pyserial)"
        raise LinkError(msg) from err
    try:
        return serial.Serial(endpoint.device, endpoint.baud, timeout=0, write_timeout=0)
    except (serial.SerialException, OSError, ValueError) as err:
        raise OSError(str(err)) from err
