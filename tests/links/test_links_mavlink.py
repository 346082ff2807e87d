"""MavlinkLink over real loopback sockets (UDP, TCP) and a real pseudo-terminal (serial): one test per transport
kind and per behaviour the service relies on (replies to peers heard from, per-peer parsing, reconnects, tlog).

Every wait is on a condition or a message with a deadline that only bounds a hang; nothing depends on timing.
"""

from __future__ import annotations

import asyncio
import contextlib
import os
import socket
from collections.abc import AsyncIterator, Iterator
from pathlib import Path
from typing import Any

import pytest
from pymavlink import mavutil
from pymavlink.dialects.v20 import ardupilotmega as mavlink

from apf_companion.errors import LinkError, LinkTimeout
from apf_companion.links import EndpointKind, MavlinkLink
from apf_companion.links.transports import MAX_UDP_PEERS, TRANSPORTS
from tests.conftest import HANG_S, free_port, until


def heartbeat(link: MavlinkLink) -> Any:
    return link.mav.heartbeat_encode(
        mavlink.MAV_TYPE_QUADROTOR, mavlink.MAV_AUTOPILOT_ARDUPILOTMEGA, 0, 0, mavlink.MAV_STATE_ACTIVE
    )


def frame(source_system: int) -> bytes:
    """One HEARTBEAT frame from ``source_system`` (component 1), sequence 0."""
    mav = mavlink.MAVLink(None, srcSystem=source_system, srcComponent=1)
    return bytes(
        mav.heartbeat_encode(mavlink.MAV_TYPE_GCS, mavlink.MAV_AUTOPILOT_INVALID, 0, 0, mavlink.MAV_STATE_ACTIVE).pack(
            mav
        )
    )


@contextlib.asynccontextmanager
async def udp_pair(**client_kw: Any) -> AsyncIterator[tuple[MavlinkLink, MavlinkLink]]:
    """A udpin server on a free port and a udpout client sending to it."""
    async with await MavlinkLink.open("udpin:127.0.0.1:0", source_system=1, source_component=1) as server:
        assert server.local_address is not None
        port = server.local_address[1]
        async with await MavlinkLink.open(
            f"udpout:127.0.0.1:{port}", source_system=2, source_component=191, **client_kw
        ) as client:
            yield server, client


def test_every_endpoint_kind_has_a_transport() -> None:
    assert set(TRANSPORTS) == set(EndpointKind)


async def test_udp_in_out_round_trip_and_reply_to_peer() -> None:
    async with await MavlinkLink.open("udpin:127.0.0.1:0", source_system=1, source_component=1) as server:
        assert server.local_address is not None
        assert not server.is_connected  # udpin: connected once a peer was heard
        server.send(heartbeat(server))
        assert server.stats.send_dropped == 1  # nobody to reply to yet
        port = server.local_address[1]
        async with await MavlinkLink.open(f"udpout:127.0.0.1:{port}", source_system=42, source_component=191) as client:
            assert client.is_connected
            client.send(heartbeat(client))
            msg = await server.recv_match(type="HEARTBEAT", timeout=HANG_S)
            assert (msg.get_srcSystem(), msg.get_srcComponent()) == (42, 191)
            assert msg.autopilot == mavlink.MAV_AUTOPILOT_ARDUPILOTMEGA
            assert server.is_connected
            await server.wait_connected(timeout=HANG_S)
            server.send(heartbeat(server))  # udpin replies to the peer it heard from
            reply = await client.recv_match(type="HEARTBEAT", timeout=HANG_S)
            assert reply.get_srcSystem() == 1
            assert client.stats.packets_sent == 1
            assert server.stats.packets_received == 1


async def test_udpin_replies_to_every_peer_heard_from() -> None:
    async with await MavlinkLink.open("udpin:127.0.0.1:0", source_system=1, source_component=1) as server:
        assert server.local_address is not None
        ep = f"udpout:127.0.0.1:{server.local_address[1]}"
        async with (
            await MavlinkLink.open(ep, source_system=2, source_component=1) as a,
            await MavlinkLink.open(ep, source_system=3, source_component=1) as b,
        ):
            a.send(heartbeat(a))
            b.send(heartbeat(b))
            senders = {(await server.recv(timeout=HANG_S)).get_srcSystem() for _ in range(2)}
            assert senders == {2, 3}
            server.send(heartbeat(server))
            for client in (a, b):
                assert (await client.recv_match(type="HEARTBEAT", timeout=HANG_S)).get_srcSystem() == 1
            assert server.stats.bytes_sent == len(frame(1))  # counted once per send, not per peer
    assert MAX_UDP_PEERS >= 2


async def test_udpin_forgets_the_parser_of_an_evicted_peer() -> None:
    """A vehicle restarting on a new source port each time (as the soak does) must not grow the parsers forever."""
    async with await MavlinkLink.open("udpin:127.0.0.1:0", source_system=1, source_component=1) as server:
        assert server.local_address is not None
        n = MAX_UDP_PEERS + 8
        for i in range(n):
            with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:  # a new source port each time
                s.bind(("127.0.0.1", 0))
                s.sendto(frame(10 + i), server.local_address)
                assert (await server.recv(timeout=HANG_S)).get_srcSystem() == 10 + i
        assert server.stats.packets_received == n
        assert len(server._receiver._parsers) == MAX_UDP_PEERS  # one per peer still replied to


async def test_sequence_numbers_increase() -> None:
    async with udp_pair() as (server, client):
        for _ in range(3):
            client.send(heartbeat(client))
        seqs = [(await server.recv(timeout=HANG_S)).get_seq() for _ in range(3)]
        assert seqs == [0, 1, 2]


async def test_garbage_is_counted_never_raised() -> None:
    async with udp_pair() as (server, client):
        client.send_bytes(b"\x00\x01garbage\xff" * 10)
        client.send_bytes(b"\xfd\x09\x00\x00")  # a truncated MAVLink 2 header
        bad_crc = bytearray(frame(2))
        bad_crc[-1] ^= 0xFF
        client.send_bytes(bytes(bad_crc))
        client.send(heartbeat(client))
        msg = await server.recv(timeout=HANG_S)
        assert msg.get_type() == "HEARTBEAT"
        assert server.stats.bad_frames >= 3
        assert server.stats.packets_received == 1


async def test_recv_timeout_raises_link_timeout() -> None:
    async with await MavlinkLink.open("udpin:127.0.0.1:0", source_system=1, source_component=1) as server:
        with pytest.raises(LinkTimeout):
            await server.recv(timeout=0.05)
        with pytest.raises(LinkTimeout):
            await server.recv_match(type="HEARTBEAT", timeout=0.05)
        with pytest.raises(LinkTimeout, match="no peer"):
            await server.wait_connected(timeout=0.05)


async def test_recv_match_skips_what_does_not_match() -> None:
    async with udp_pair() as (server, client):
        for _ in range(3):
            client.send(heartbeat(client))
        client.send(client.mav.system_time_encode(0, 1234))
        msg = await server.recv_match(type=("SYSTEM_TIME",), condition=lambda m: m.time_boot_ms == 1234, timeout=HANG_S)
        assert msg.get_type() == "SYSTEM_TIME"
        assert server.recv_nowait() is None  # the heartbeats before it were discarded


async def test_rx_queue_overflow_drops_the_oldest() -> None:
    async with await MavlinkLink.open(
        "udpin:127.0.0.1:0", source_system=1, source_component=1, rx_queue_size=2
    ) as server:
        assert server.local_address is not None
        async with await MavlinkLink.open(
            f"udpout:127.0.0.1:{server.local_address[1]}", source_system=2, source_component=1
        ) as client:
            for _ in range(5):
                client.send(heartbeat(client))
            await until(lambda: server.stats.packets_received == 5, HANG_S, "five frames parsed")
            assert server.stats.rx_dropped == 3
            assert [(await server.recv(timeout=HANG_S)).get_seq() for _ in range(2)] == [3, 4]


async def test_address_in_use_is_a_link_error() -> None:
    async with await MavlinkLink.open("tcpin:127.0.0.1:0", source_system=1, source_component=1) as a:
        assert a.local_address is not None
        with pytest.raises(LinkError, match="cannot open"):
            await MavlinkLink.open(f"tcpin:127.0.0.1:{a.local_address[1]}", source_system=1, source_component=1)


async def test_tcp_client_and_server_round_trip() -> None:
    async with await MavlinkLink.open("tcpin:127.0.0.1:0", source_system=1, source_component=1) as server:
        assert server.local_address is not None
        port = server.local_address[1]
        async with await MavlinkLink.open(f"tcp:127.0.0.1:{port}", source_system=2, source_component=191) as client:
            assert client.local_address is None
            await client.wait_connected(timeout=HANG_S)
            await server.wait_connected(timeout=HANG_S)
            client.send(heartbeat(client))
            assert (await server.recv_match(type="HEARTBEAT", timeout=HANG_S)).get_srcSystem() == 2
            server.send(heartbeat(server))
            assert (await client.recv_match(type="HEARTBEAT", timeout=HANG_S)).get_srcSystem() == 1
            # Each tcpin client runs as a named task in the link's task group.
            names = {t.get_name() for t in asyncio.all_tasks()}
            assert "mavlink[tcpin:127.0.0.1:0].client0" in names  # named after the endpoint as configured
            assert f"mavlink[tcp:127.0.0.1:{port}].receive" in names
        await until(lambda: not server.is_connected, HANG_S, "server sees the client gone")
    assert not any(t.get_name().startswith("mavlink[") for t in asyncio.all_tasks())


async def test_tcpin_parses_each_client_on_its_own() -> None:
    """Half a frame from one client, then half from another: each stream keeps its own parser."""
    async with await MavlinkLink.open("tcpin:127.0.0.1:0", source_system=1, source_component=1) as server:
        assert server.local_address is not None
        a, b = frame(2), frame(3)
        conns = [await asyncio.open_connection(*server.local_address) for _ in range(2)]
        try:
            sent = 0
            for (_, writer), chunk in zip(conns * 2, (a[:7], b[:7], a[7:], b[7:]), strict=True):
                writer.write(chunk)
                sent += len(chunk)
                await until(lambda: server.stats.bytes_received == sent, HANG_S, f"{sent} bytes at the server")  # noqa: B023
            senders = {(await server.recv(timeout=HANG_S)).get_srcSystem() for _ in range(2)}
            assert senders == {2, 3}
            assert server.stats.bad_frames == 0
        finally:
            for _, writer in conns:
                writer.close()


async def test_tcp_client_reconnects_after_server_restart() -> None:
    port = free_port()
    client = await MavlinkLink.open(f"tcp:127.0.0.1:{port}", source_system=2, source_component=191)
    try:
        client.send(heartbeat(client))  # nobody there yet: dropped and counted
        assert client.stats.send_dropped == 1
        server = await MavlinkLink.open(f"tcpin:127.0.0.1:{port}", source_system=1, source_component=1)
        await client.wait_connected(timeout=HANG_S)
        client.send(heartbeat(client))
        assert (await server.recv_match(type="HEARTBEAT", timeout=HANG_S)).get_srcSystem() == 2
        assert client.stats.reconnects == 0
        await server.aclose()
        await until(lambda: not client.is_connected, HANG_S, "client sees the server gone")
        server = await MavlinkLink.open(f"tcpin:127.0.0.1:{port}", source_system=1, source_component=1)
        await client.wait_connected(timeout=HANG_S)
        await server.wait_connected(timeout=HANG_S)
        client.send(heartbeat(client))
        assert (await server.recv_match(type="HEARTBEAT", timeout=HANG_S)).get_srcSystem() == 2
        assert client.stats.reconnects == 1
        server.send(heartbeat(server))
        assert (await client.recv_match(type="HEARTBEAT", timeout=HANG_S)).get_srcSystem() == 1
        await server.aclose()
    finally:
        await client.aclose()


async def test_tlog_is_readable_by_pymavlink(tmp_path: Path) -> None:
    tlog = tmp_path / "link.tlog"
    async with udp_pair(tlog_path=tlog) as (server, client):
        client.send(heartbeat(client))
        await server.recv(timeout=HANG_S)
        server.send(server.mav.local_position_ned_encode(10, 1.0, 2.0, -3.0, 0, 0, 0))
        await client.recv_match(type="LOCAL_POSITION_NED", timeout=HANG_S)
    log = mavutil.mavlink_connection(str(tlog), dialect="ardupilotmega")
    types = []
    while (m := log.recv_match()) is not None:
        types.append((m.get_type(), m.get_srcSystem()))
    assert types == [("HEARTBEAT", 2), ("LOCAL_POSITION_NED", 1)]


async def test_send_after_close_is_dropped_and_close_is_idempotent() -> None:
    async with udp_pair() as (server, client):
        await client.aclose()
        assert not client.is_connected
        client.send(heartbeat(client))
        assert client.stats.send_dropped == 1 and client.stats.bytes_sent == 0
        await client.aclose()
        await server.aclose()


# ------------------------------------------------------------------------------------------------- serial
# A pseudo-terminal is a real tty device: pyserial opens and configures it exactly like /dev/ttyACM0 and the
# link reads and writes its file descriptor, so only the autopilot at the far end is played by the test (on
# the master side). pyserial's loop:// would be in-process too, but it has no file descriptor to wait on.


@pytest.fixture
def pty() -> Iterator[tuple[int, str]]:
    """(master fd, slave device path) of a fresh pseudo-terminal."""
    pytest.importorskip("serial")
    master_fd, slave_fd = os.openpty()
    try:
        yield master_fd, os.ttyname(slave_fd)
    finally:
        os.close(slave_fd)
        os.close(master_fd)


class _Collect(asyncio.Protocol):
    def __init__(self) -> None:
        self.data = bytearray()
        self.changed = asyncio.Event()

    def data_received(self, data: bytes) -> None:
        self.data += data
        self.changed.set()


async def _read_master(master_fd: int) -> tuple[asyncio.ReadTransport, _Collect]:
    loop = asyncio.get_running_loop()
    pipe = open(master_fd, "rb", buffering=0, closefd=False)  # noqa: SIM115 - the transport owns it
    transport, proto = await loop.connect_read_pipe(_Collect, pipe)
    return transport, proto


async def _until_bytes(proto: _Collect, n: int) -> None:
    async with asyncio.timeout(HANG_S):
        while len(proto.data) < n:
            proto.changed.clear()
            await proto.changed.wait()


async def test_serial_over_a_pseudo_terminal(pty: tuple[int, str]) -> None:
    master_fd, device = pty
    async with await MavlinkLink.open(f"{device}:115200", source_system=1, source_component=191) as link:
        assert link.is_connected and link.local_address is None
        await link.wait_connected(timeout=HANG_S)
        transport, got = await _read_master(master_fd)
        try:
            link.send(heartbeat(link))
            await _until_bytes(got, len(frame(1)))
            assert got.data[0] == mavlink.PROTOCOL_MARKER_V2
        finally:
            transport.close()
        os.write(master_fd, frame(7))
        msg = await link.recv_match(type="HEARTBEAT", timeout=HANG_S)
        assert msg.get_srcSystem() == 7


async def test_serial_burst_larger_than_the_tty_buffer_arrives_whole(pty: tuple[int, str]) -> None:
    """Writes the UART cannot take at once are buffered, never cut mid-frame."""
    master_fd, device = pty
    async with await MavlinkLink.open(f"{device}:115200", source_system=1, source_component=191) as link:
        n = 3000  # ~63 kB: several times what a pty holds before the writer would block
        for _ in range(n):
            link.send(heartbeat(link))
        assert link.stats.send_dropped == 0
        transport, got = await _read_master(master_fd)
        try:
            await _until_bytes(got, n * len(frame(1)))
        finally:
            transport.close()
    parser = mavlink.MAVLink(None)
    msgs = parser.parse_buffer(bytes(got.data)) or []
    assert [m.get_type() for m in msgs] == ["HEARTBEAT"] * n
    assert [m.get_seq() for m in msgs[:300]] == [i % 256 for i in range(300)]


async def test_serial_port_gone_is_not_connected() -> None:
    pytest.importorskip("serial")
    master_fd, slave_fd = os.openpty()  # not the fixture: this test closes the master itself
    try:
        async with await MavlinkLink.open(
            f"{os.ttyname(slave_fd)}:57600", source_system=1, source_component=191
        ) as link:
            os.close(master_fd)  # the far end hangs up: reads of the tty now fail
            await until(lambda: not link.is_connected, HANG_S, "link notices the port is gone")
            link.send(heartbeat(link))
            assert link.stats.send_dropped == 1
    finally:
        os.close(slave_fd)


async def test_missing_serial_device_is_a_link_error() -> None:
    with pytest.raises(LinkError, match="cannot open"):
        await MavlinkLink.open("/dev/does-not-exist-apf:57600", source_system=1, source_component=191)
