"""MavlinkLink over real loopback sockets (UDP, TCP) and a real pseudo-terminal (serial)."""

from __future__ import annotations

import asyncio
import os
from pathlib import Path

import pytest
from pymavlink import mavutil

from apf_companion.errors import LinkError, LinkTimeout
from apf_companion.links import MavlinkLink

from .conftest import free_port


def heartbeat(link: MavlinkLink) -> object:
    return link.mav.heartbeat_encode(2, 3, 0, 0, 4)


async def test_udp_in_out_round_trip_and_reply_to_peer() -> None:
    async with await MavlinkLink.open("udpin:127.0.0.1:0", source_system=1, source_component=1) as server:
        assert server.local_address is not None
        port = server.local_address[1]
        async with await MavlinkLink.open(f"udpout:127.0.0.1:{port}", source_system=42, source_component=191) as client:
            client.send(heartbeat(client))
            msg = await server.recv_match(type="HEARTBEAT", timeout=2.0)
            assert (msg.get_srcSystem(), msg.get_srcComponent()) == (42, 191)
            assert msg.autopilot == 3
            assert server.is_connected
            # udpin replies to the peer it heard from
            server.send(server.mav.heartbeat_encode(2, 3, 0, 0, 4))
            reply = await client.recv_match(type="HEARTBEAT", timeout=2.0)
            assert reply.get_srcSystem() == 1
            assert client.stats.packets_sent == 1
            assert server.stats.packets_received == 1


async def test_sequence_numbers_increase() -> None:
    async with await MavlinkLink.open("udpin:127.0.0.1:0", source_system=1, source_component=1) as server:
        assert server.local_address is not None
        async with await MavlinkLink.open(
            f"udpout:127.0.0.1:{server.local_address[1]}", source_system=2, source_component=1
        ) as client:
            for _ in range(3):
                client.send(heartbeat(client))
            seqs = [(await server.recv(timeout=2.0)).get_seq() for _ in range(3)]
            assert seqs == [0, 1, 2]


async def test_garbage_is_counted_never_raised() -> None:
    async with await MavlinkLink.open("udpin:127.0.0.1:0", source_system=1, source_component=1) as server:
        assert server.local_address is not None
        async with await MavlinkLink.open(
            f"udpout:127.0.0.1:{server.local_address[1]}", source_system=2, source_component=1
        ) as client:
            client.send_bytes(b"\x00\x01garbage\xff" * 10)
            client.send_bytes(b"\xfd\x09\x00\x00")  # a truncated MAVLink 2 header
            frame = bytearray(heartbeat(client).pack(client.mav))  # type: ignore[attr-defined]
            frame[-1] ^= 0xFF  # bad CRC
            client.send_bytes(bytes(frame))
            client.send(heartbeat(client))
            msg = await server.recv(timeout=2.0)
            assert msg.get_type() == "HEARTBEAT"
            assert server.stats.bad_frames >= 3
            assert server.stats.packets_received == 1


async def test_recv_timeout_raises_link_timeout() -> None:
    async with await MavlinkLink.open("udpin:127.0.0.1:0", source_system=1, source_component=1) as server:
        with pytest.raises(LinkTimeout):
            await server.recv(timeout=0.05)
        with pytest.raises(LinkTimeout):
            await server.recv_match(type="HEARTBEAT", timeout=0.05)


async def test_address_in_use_is_a_link_error() -> None:
    async with await MavlinkLink.open("tcpin:127.0.0.1:0", source_system=1, source_component=1) as a:
        assert a.local_address is not None
        with pytest.raises(LinkError, match="cannot open"):
            await MavlinkLink.open(f"tcpin:127.0.0.1:{a.local_address[1]}", source_system=1, source_component=1)


async def test_tcp_client_reconnects_after_server_restart() -> None:
    port = free_port()
    client = await MavlinkLink.open(f"tcp:127.0.0.1:{port}", source_system=2, source_component=191)
    try:
        client.send(heartbeat(client))  # nobody there yet: dropped and counted
        assert client.stats.send_dropped == 1
        server = await MavlinkLink.open(f"tcpin:127.0.0.1:{port}", source_system=1, source_component=1)
        await client.wait_connected(timeout=5.0)
        client.send(heartbeat(client))
        assert (await server.recv_match(type="HEARTBEAT", timeout=2.0)).get_srcSystem() == 2
        await server.aclose()
        await asyncio.sleep(0.3)
        server = await MavlinkLink.open(f"tcpin:127.0.0.1:{port}", source_system=1, source_component=1)
        await client.wait_connected(timeout=8.0)
        await server.wait_connected(timeout=8.0)
        client.send(heartbeat(client))
        assert (await server.recv_match(type="HEARTBEAT", timeout=2.0)).get_srcSystem() == 2
        assert client.stats.reconnects == 1
        server.send(server.mav.heartbeat_encode(2, 3, 0, 0, 4))
        assert (await client.recv_match(type="HEARTBEAT", timeout=2.0)).get_srcSystem() == 1
        await server.aclose()
    finally:
        await client.aclose()


async def test_tlog_is_readable_by_pymavlink(tmp_path: Path) -> None:
    tlog = tmp_path / "link.tlog"
    async with await MavlinkLink.open("udpin:127.0.0.1:0", source_system=1, source_component=1) as server:
        assert server.local_address is not None
        async with await MavlinkLink.open(
            f"udpout:127.0.0.1:{server.local_address[1]}", source_system=2, source_component=191, tlog_path=tlog
        ) as client:
            client.send(heartbeat(client))
            await server.recv(timeout=2.0)
            server.send(server.mav.local_position_ned_encode(10, 1.0, 2.0, -3.0, 0, 0, 0))
            await client.recv_match(type="LOCAL_POSITION_NED", timeout=2.0)
    log = mavutil.mavlink_connection(str(tlog), dialect="ardupilotmega")
    types = []
    while (m := log.recv_match()) is not None:
        types.append((m.get_type(), m.get_srcSystem()))
    assert types == [("HEARTBEAT", 2), ("LOCAL_POSITION_NED", 1)]


async def test_serial_over_a_pseudo_terminal() -> None:
    pytest.importorskip("serial")
    master_fd, slave_fd = os.openpty()
    try:
        link = await MavlinkLink.open(f"{os.ttyname(slave_fd)}:115200", source_system=1, source_component=191)
        try:
            link.send(heartbeat(link))
            data = os.read(master_fd, 1024)
            assert data[0] == 0xFD  # MAVLink 2
            peer = link.dialect.MAVLink(None, srcSystem=1, srcComponent=1)
            os.write(master_fd, bytes(peer.heartbeat_encode(2, 3, 0, 0, 4).pack(peer)))
            msg = await link.recv_match(type="HEARTBEAT", timeout=2.0)
            assert msg.get_srcComponent() == 1
        finally:
            await link.aclose()
    finally:
        os.close(master_fd)
        os.close(slave_fd)


async def test_missing_serial_device_is_a_link_error() -> None:
    with pytest.raises(LinkError):
        await MavlinkLink.open("/dev/does-not-exist-apf:57600", source_system=1, source_component=191)
