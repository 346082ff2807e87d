"""TCP transports: ``tcp:`` connects to a server and reconnects with backoff; ``tcpin:`` accepts clients.

Both run each connection through ``TcpPeers``: register the writer, read until the peer ends, forget it.
Sends go to every connected peer; a peer whose write buffer passed ``MAX_WRITE_BUFFER_B`` (stalled) is
skipped rather than buffered without bound.
"""

from __future__ import annotations

import asyncio
import contextlib
import itertools
import logging

from apf_companion.links.endpoint import Endpoint, connection_hint
from apf_companion.links.receiver import Receiver
from apf_companion.links.transports.base import MAX_WRITE_BUFFER_B

__all__ = ["TCP_BACKOFF_MAX_S", "TCP_BACKOFF_MIN_S", "TcpClient", "TcpPeers", "TcpServer"]

log = logging.getLogger(__name__)

TCP_BACKOFF_MIN_S = 0.2
TCP_BACKOFF_MAX_S = 5.0
READ_CHUNK_B = 65536


class TcpPeers:
    """The connected TCP peers of one link (the server's clients, or the client's one connection)."""

    def __init__(self, receiver: Receiver) -> None:
        self.receiver = receiver
        self._writers: dict[int, asyncio.StreamWriter] = {}
        self._ids = itertools.count()

    def __bool__(self) -> bool:
        return bool(self._writers)

    async def serve(self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        """One connection: register it, feed what it sends to the receiver until it ends, forget it."""
        key = next(self._ids)
        self._writers[key] = writer
        self.receiver.connected.set()
        try:
            while data := await reader.read(READ_CHUNK_B):
                self.receiver.feed(data, ("tcp", key), datagram=False)
        except (ConnectionError, OSError):
            pass
        finally:
            self._writers.pop(key, None)
            self.receiver.forget(("tcp", key))
            if not self._writers:
                self.receiver.connected.clear()
            writer.close()

    def send(self, data: bytes) -> bool:
        sent = False
        for writer in self._writers.values():
            if writer.transport.get_write_buffer_size() < MAX_WRITE_BUFFER_B:
                writer.write(data)
                sent = True
        return sent

    def close(self) -> None:
        for writer in self._writers.values():
            writer.close()
        self._writers.clear()


class TcpClient:
    """``tcp:HOST:PORT``: connect in the background; after a failure or a disconnect, retry with backoff."""

    local_address = None

    def __init__(self, endpoint: Endpoint, receiver: Receiver) -> None:
        self.endpoint = endpoint
        self.receiver = receiver
        self._peers = TcpPeers(receiver)

    @property
    def is_connected(self) -> bool:
        return bool(self._peers)

    async def open(self) -> None:
        """Nothing to do before ``run``: a server that is not up yet is normal (it is retried)."""

    async def run(self, tasks: asyncio.TaskGroup) -> None:
        ep = self.endpoint
        backoff_s = TCP_BACKOFF_MIN_S
        connected_before = False
        while True:
            try:
                reader, writer = await asyncio.open_connection(ep.host, ep.port)
            except OSError as err:
                # The first failure of a streak is a WARNING saying what to check; the retries stay at DEBUG.
                first = backoff_s == TCP_BACKOFF_MIN_S
                log.log(
                    logging.WARNING if first else logging.DEBUG,
                    "mavlink.tcp_connect_failed",
                    extra={"endpoint": str(ep), "error": str(err), "hint": connection_hint(ep), "retry_s": backoff_s},
                )
                await asyncio.sleep(backoff_s)
                backoff_s = min(backoff_s * 2, TCP_BACKOFF_MAX_S)
                continue
            if connected_before:
                self.receiver.stats.reconnects += 1
            connected_before = True
            backoff_s = TCP_BACKOFF_MIN_S
            log.info("mavlink.tcp_connected", extra={"endpoint": str(ep)})
            await self._peers.serve(reader, writer)
            log.warning("mavlink.tcp_disconnected", extra={"endpoint": str(ep)})
            await asyncio.sleep(backoff_s)

    def send(self, data: bytes) -> bool:
        return self._peers.send(data)

    async def aclose(self) -> None:
        self._peers.close()


class TcpServer:
    """``tcpin:HOST:PORT``: listen; each client runs as a named task in the link's task group."""

    def __init__(self, endpoint: Endpoint, receiver: Receiver) -> None:
        self.endpoint = endpoint
        self.receiver = receiver
        self._peers = TcpPeers(receiver)
        self._server: asyncio.Server | None = None
        self._tasks: asyncio.TaskGroup | None = None
        self._early: list[tuple[asyncio.StreamReader, asyncio.StreamWriter]] = []  # accepted before ``run``
        self._accepted = itertools.count()

    @property
    def local_address(self) -> tuple[str, int] | None:
        if self._server is None:
            return None
        host, port = self._server.sockets[0].getsockname()[:2]
        return str(host), int(port)

    @property
    def is_connected(self) -> bool:
        return bool(self._peers)

    async def open(self) -> None:
        self._server = await asyncio.start_server(self._on_client, self.endpoint.host, self.endpoint.port)

    async def run(self, tasks: asyncio.TaskGroup) -> None:
        assert self._server is not None, "open() first"
        self._tasks = tasks
        for reader, writer in self._early:
            self._on_client(reader, writer)
        self._early.clear()
        await self._server.serve_forever()

    def _on_client(self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        if self._tasks is None:
            self._early.append((reader, writer))
            return
        name = f"mavlink[{self.endpoint}].client{next(self._accepted)}"
        try:
            self._tasks.create_task(self._peers.serve(reader, writer), name=name)
        except RuntimeError:  # the link is closing: its task group takes no new tasks
            writer.close()

    def send(self, data: bytes) -> bool:
        return self._peers.send(data)

    async def aclose(self) -> None:
        self._peers.close()
        for _, writer in self._early:
            writer.close()
        if self._server is not None:
            self._server.close()
            with contextlib.suppress(Exception):
                await asyncio.wait_for(self._server.wait_closed(), 1.0)
