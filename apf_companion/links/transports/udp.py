"""UDP transports: ``udpin`` listens and replies to every peer heard from, ``udpout`` sends to one address.

Both read through an asyncio datagram endpoint, so receiving is driven by the event loop's callbacks;
``run`` only waits until the socket is closed. A datagram ends on a frame boundary, which the receiver uses
to drop truncated frames at once.
"""

from __future__ import annotations

import asyncio
from collections import OrderedDict

from apf_companion.links.endpoint import Endpoint
from apf_companion.links.receiver import Receiver

__all__ = ["MAX_UDP_PEERS", "UdpIn", "UdpOut"]

MAX_UDP_PEERS = 16  # udpin replies to at most this many recent peers

Address = tuple[str, int]


class _Datagrams(asyncio.DatagramProtocol):
    def __init__(self, owner: _UdpTransport) -> None:
        self._owner = owner

    def datagram_received(self, data: bytes, addr: Address) -> None:
        self._owner.heard(data, addr)

    def error_received(self, exc: Exception) -> None:
        # ICMP port-unreachable from a peer that is not up yet: normal while the other end starts.
        self._owner.receiver.stats.send_dropped += 1

    def connection_lost(self, exc: Exception | None) -> None:
        self._owner.lost.set()


class _UdpTransport:
    """What both directions share: the socket, its lifetime and the receive path."""

    def __init__(self, endpoint: Endpoint, receiver: Receiver) -> None:
        self.endpoint = endpoint
        self.receiver = receiver
        self.lost = asyncio.Event()
        self._udp: asyncio.DatagramTransport | None = None

    @property
    def local_address(self) -> Address | None:
        if self._udp is None:
            return None
        host, port = self._udp.get_extra_info("sockname")[:2]
        return str(host), int(port)

    async def _bind(self, *, local: Address | None = None, remote: Address | None = None) -> None:
        loop = asyncio.get_running_loop()
        self._udp, _ = await loop.create_datagram_endpoint(
            lambda: _Datagrams(self), local_addr=local, remote_addr=remote
        )

    def heard(self, data: bytes, addr: Address) -> None:
        self.receiver.feed(data, addr, datagram=True)

    async def run(self, tasks: asyncio.TaskGroup) -> None:
        await self.lost.wait()

    async def aclose(self) -> None:
        if self._udp is not None:
            self._udp.close()


class UdpIn(_UdpTransport):
    """``udpin:HOST:PORT``: bind, and reply to the most recent ``MAX_UDP_PEERS`` peers (like pymavlink's udpin)."""

    def __init__(self, endpoint: Endpoint, receiver: Receiver) -> None:
        super().__init__(endpoint, receiver)
        self._peers: OrderedDict[Address, None] = OrderedDict()

    @property
    def is_connected(self) -> bool:
        return bool(self._peers)

    async def open(self) -> None:
        await self._bind(local=(self.endpoint.host, self.endpoint.port))

    def heard(self, data: bytes, addr: Address) -> None:
        self._peers[addr] = None
        self._peers.move_to_end(addr)
        while len(self._peers) > MAX_UDP_PEERS:
            old, _ = self._peers.popitem(last=False)
            self.receiver.forget(old)  # its parser too, or a new source port per reconnect grows them forever
        self.receiver.connected.set()
        super().heard(data, addr)

    def send(self, data: bytes) -> bool:
        if self._udp is None or not self._peers:
            return False
        for addr in self._peers:
            self._udp.sendto(data, addr)
        return True


class UdpOut(_UdpTransport):
    """``udpout:HOST:PORT``: send to one address (and read its replies); connected from the start."""

    @property
    def is_connected(self) -> bool:
        return self._udp is not None

    async def open(self) -> None:
        await self._bind(remote=(self.endpoint.host, self.endpoint.port))
        self.receiver.connected.set()

    def send(self, data: bytes) -> bool:
        if self._udp is None:
            return False
        self._udp.sendto(data)
        return True
