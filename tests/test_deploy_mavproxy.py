"""deploy/apf-mavproxy.service's MAVProxy, started with the unit's own ExecStart flags against a fake flight
controller on loopback: it routes both ways, and it sends the autopilot nothing of its own, above all no
ground-station HEARTBEAT. ArduPilot counts any HEARTBEAT from its GCS sysid as the ground station seen
(``GCS_Common.cpp`` handle_heartbeat -> sysid_mygcs_seen), PX4 any MAV_TYPE_GCS HEARTBEAT (``mavlink_receiver.cpp``
handle_message_heartbeat, ``Commander.cpp`` dataLinkCheck): a router that sends one hides a lost radio link from
the GCS failsafe (FS_GCS_ENABLE, NAV_DLL_ACT).

The flight controller here is a TCP server (MAVProxy's ``--master=tcp:``, a point-to-point link like the UART) that
sends its HEARTBEAT at 1 Hz, as ArduPilot does; the service's and the ground station's ``--out`` ports are UDP
sockets of the test. The test waits on conditions only: MAVProxy forwarding the autopilot's messages to the
service, the service's own HEARTBEAT forwarded to the autopilot, then a window of several more autopilot
heartbeats forwarded (MAVProxy's loop demonstrably running, whatever the load) before it looks at what the
autopilot received.
"""

from __future__ import annotations

import asyncio
import os
import re
import shlex
import signal
import sys
from dataclasses import dataclass, field
from pathlib import Path
from typing import cast

import pytest
from pymavlink.dialects.v20 import ardupilotmega as mavlink

from tests.conftest import HANG_S, counter_advances, free_port, reap, until
from tests.service.mavproxy import mavproxy_path

DEPLOY = Path(__file__).resolve().parent.parent / "deploy"
UNIT = DEPLOY / "apf-mavproxy.service"
ENV_FILE = DEPLOY / "mavproxy.env"
SERVICE_OUT = "127.0.0.1:14540"  # the unit's --out for apf-companion
FC_HEARTBEAT_S = 1.0  # ArduPilot's HEARTBEAT period
WINDOW_HEARTBEATS = 4  # autopilot heartbeats forwarded during the window: 4 of MAVProxy's 1 Hz heartbeat periods
FC_IDS = (1, 1)
SERVICE_IDS = (1, 191)


def exec_start(unit_text: str) -> list[str]:
    """The unit's ExecStart= command line (continuation lines joined), split as systemd does for plain words."""
    joined = re.sub(r"\\\n\s*", " ", unit_text)
    lines = [line for line in joined.splitlines() if line.startswith("ExecStart=")]
    assert len(lines) == 1, lines
    return shlex.split(lines[0].removeprefix("ExecStart="))


def env_file(text: str) -> dict[str, str]:
    return dict(line.split("=", 1) for line in text.splitlines() if line and not line.startswith("#"))


def local_argv(
    argv: list[str], env: dict[str, str], fc_port: int, service_port: int, gcs_port: int, state: Path
) -> list[str]:
    """The unit's command line with only its endpoints, its state directory and the interpreter made local; every
    other flag exactly as in the unit. Fails if the unit no longer has the shape this relies on."""
    assert argv[0].endswith("/mavproxy.py"), argv[0]
    env = env | {"APF_MAVPROXY_MASTER": f"tcp:127.0.0.1:{fc_port}", "APF_MAVPROXY_GCS": f"udp:127.0.0.1:{gcs_port}"}
    out: list[str] = []
    replaced = {"service": 0, "state": 0}
    for arg in argv[1:]:
        arg = re.sub(r"\$\{(\w+)\}", lambda m: env[m.group(1)], arg)
        if SERVICE_OUT in arg:
            arg = arg.replace(SERVICE_OUT, f"127.0.0.1:{service_port}")
            replaced["service"] += 1
        if arg.startswith("--state-basedir="):
            arg = f"--state-basedir={state}"
            replaced["state"] += 1
        out.append(arg)
    assert replaced == {"service": 1, "state": 1}, (replaced, argv)
    mavproxy = mavproxy_path()
    assert mavproxy is not None
    return [sys.executable, "-u", mavproxy, *out]


@dataclass
class Seen:
    """Messages one endpoint received: (type, sysid, compid, HEARTBEAT's MAV_TYPE or None)."""

    messages: list[tuple[str, int, int, int | None]] = field(default_factory=list)

    def add(self, msg: mavlink.MAVLink_message) -> None:
        mav_type = msg.type if msg.get_type() == "HEARTBEAT" else None
        self.messages.append((msg.get_type(), msg.get_srcSystem(), msg.get_srcComponent(), mav_type))

    def heartbeats_from(self, ids: tuple[int, int]) -> int:
        return sum(1 for kind, *src, _ in self.messages if kind == "HEARTBEAT" and tuple(src) == ids)


def _parser() -> mavlink.MAVLink:
    parser = mavlink.MAVLink(None)
    parser.robust_parsing = True
    return parser


class FakeFlightController:
    """A TCP server on 127.0.0.1 as the autopilot 1/1: sends HEARTBEAT every ``FC_HEARTBEAT_S`` to whoever
    connects (MAVProxy), records what arrives."""

    def __init__(self) -> None:
        self.seen = Seen()
        self.connections = 0
        self._tasks: set[asyncio.Task[None]] = set()

    async def handle(self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        self.connections += 1
        sender = asyncio.create_task(self._heartbeats(writer))
        self._tasks.add(sender)
        parser = _parser()
        try:
            while data := await reader.read(4096):
                for msg in parser.parse_buffer(data) or []:
                    self.seen.add(msg)
        except ConnectionResetError:  # MAVProxy stopped
            pass
        finally:
            sender.cancel()
            writer.close()

    async def _heartbeats(self, writer: asyncio.StreamWriter) -> None:
        mav = mavlink.MAVLink(None, *FC_IDS)
        while True:  # the autopilot's own clock: it paces what it sends, nothing waits on it
            hb = mav.heartbeat_encode(mavlink.MAV_TYPE_QUADROTOR, mavlink.MAV_AUTOPILOT_ARDUPILOTMEGA, 0, 0, 4)
            writer.write(hb.pack(mav))
            await writer.drain()
            await asyncio.sleep(FC_HEARTBEAT_S)


class UdpEnd(asyncio.DatagramProtocol):
    """An ``--out`` endpoint; as the service it answers each autopilot HEARTBEAT with its own (1/191, onboard
    controller), as apf-companion does at 1 Hz."""

    def __init__(self, answer_as: tuple[int, int] | None) -> None:
        self.seen = Seen()
        self._parser = _parser()
        self._mav = mavlink.MAVLink(None, *answer_as) if answer_as else None
        self._transport: asyncio.DatagramTransport | None = None

    def connection_made(self, transport: asyncio.BaseTransport) -> None:
        self._transport = cast(asyncio.DatagramTransport, transport)  # 3.11's selector transport is not a subclass

    def datagram_received(self, data: bytes, addr: tuple[str | int, int]) -> None:
        for msg in self._parser.parse_buffer(data) or []:
            self.seen.add(msg)
            fc_heartbeat = msg.get_type() == "HEARTBEAT" and (msg.get_srcSystem(), msg.get_srcComponent()) == FC_IDS
            if fc_heartbeat and self._mav is not None and self._transport is not None:
                hb = self._mav.heartbeat_encode(
                    mavlink.MAV_TYPE_ONBOARD_CONTROLLER, mavlink.MAV_AUTOPILOT_INVALID, 0, 0, 4
                )
                self._transport.sendto(hb.pack(self._mav), addr)


def test_the_unit_turns_off_what_mavproxy_originates() -> None:
    """The heartbeat (periodic and at start) and the stream requests: the latter come every 15 s, outside the
    window of the test below, so the flag is checked here."""
    argv = exec_start(UNIT.read_text())
    assert argv[0] == "/opt/apf-companion/venv/bin/mavproxy.py"
    assert {"--heartbeat-rate=0", "--nowait", "--streamrate=-1"} <= set(argv)
    assert env_file(ENV_FILE.read_text())["APF_MAVPROXY_BAUD"] == "921600"


@pytest.mark.interop
@pytest.mark.skipif(mavproxy_path() is None, reason="MAVProxy not installed (pip install --no-deps MAVProxy)")
async def test_the_router_sends_the_autopilot_no_gcs_heartbeat(tmp_path: Path) -> None:
    fc = FakeFlightController()
    fc_port, service_port, gcs_port = free_port(), free_port(), free_port()
    server = await asyncio.start_server(fc.handle, "127.0.0.1", fc_port)
    loop = asyncio.get_running_loop()
    service_t, service = await loop.create_datagram_endpoint(
        lambda: UdpEnd(SERVICE_IDS), local_addr=("127.0.0.1", service_port)
    )
    gcs_t, _ = await loop.create_datagram_endpoint(lambda: UdpEnd(None), local_addr=("127.0.0.1", gcs_port))
    argv = local_argv(
        exec_start(UNIT.read_text()),
        env_file(ENV_FILE.read_text()),
        fc_port,
        service_port,
        gcs_port,
        tmp_path / "state",
    )
    log_path = tmp_path / "mavproxy.out"
    with log_path.open("wb") as log:
        proc = await asyncio.create_subprocess_exec(
            *argv, stdout=log, stderr=asyncio.subprocess.STDOUT, cwd=tmp_path, env=os.environ | {"HOME": str(tmp_path)}
        )
    try:

        def where() -> str:
            return f"{argv}\nMAVProxy said: {log_path.read_text(errors='replace')}"

        # It routes: the autopilot's heartbeat reaches the service, the service's reaches the autopilot (so the
        # path a GCS heartbeat would take is open). MAVProxy starts slowly on a loaded machine.
        await until(lambda: service.seen.heartbeats_from(FC_IDS) > 0, HANG_S * 2, f"autopilot -> service: {where()}")
        await until(lambda: fc.seen.heartbeats_from(SERVICE_IDS) > 0, HANG_S, f"service -> autopilot: {where()}")
        # The window: several of the autopilot's heartbeat periods, measured by its heartbeats forwarded meanwhile.
        await counter_advances(lambda: service.seen.heartbeats_from(FC_IDS), WINDOW_HEARTBEATS, "window")
        assert proc.returncode is None, where()

        gcs_heartbeats = [
            m for m in fc.seen.messages if m[0] == "HEARTBEAT" and (m[1] == 255 or m[3] == mavlink.MAV_TYPE_GCS)
        ]
        assert gcs_heartbeats == [], f"GCS heartbeats reached the autopilot: {gcs_heartbeats}"
        own = sorted({m[:3] for m in fc.seen.messages if (m[1], m[2]) != SERVICE_IDS})
        assert own == [], f"the router sent the autopilot messages of its own: {own}"
        assert fc.connections == 1
    finally:
        if proc.returncode is None:
            proc.send_signal(signal.SIGINT)  # the unit's KillSignal
        await reap(proc)
        server.close()
        await server.wait_closed()
        service_t.close()
        gcs_t.close()
