"""Interop with programs nobody here wrote: MAVSDK-Python 4.x (asyncio API over libcmavsdk) and MAVProxy
(headless). Each test stays well under 15 s."""

from __future__ import annotations

import asyncio
import math
import shutil
import socket
import sys
from pathlib import Path

import numpy as np
import pytest
from pymavlink.dialects.v20 import ardupilotmega as m

from apf_companion.autopilot import CopterMode
from apf_companion.links import MavlinkLink
from sim.vehicle import SimConfig, Simulator, SpawnConfig
from sim.vehicle.testing import command_long
from tests.conftest import HANG_S, free_port, reap, wait_for

pytestmark = pytest.mark.interop


@pytest.mark.parametrize("profile", ["px4", "ardupilot"])
async def test_mavsdk_discovers_and_reads_position_velocity(profile: str) -> None:
    mavsdk_asyncio = pytest.importorskip("mavsdk.asyncio")
    telemetry = pytest.importorskip("mavsdk.asyncio.plugins.telemetry")
    action = pytest.importorskip("mavsdk.asyncio.plugins.action")
    port = free_port(socket.SOCK_DGRAM)
    spawn = SpawnConfig(pos_ne_m=(2.0, 3.0), airborne=True, alt_m=5.0)
    # MAVSDK asks for no streams here: the vehicle streams unasked (a real ArduCopter waits to be asked)
    sim = await Simulator.start(
        SimConfig(links=[f"udpout:127.0.0.1:{port}"], profile=profile, spawn=spawn, unasked_streams=True)
    )
    try:
        config = mavsdk_asyncio.Configuration.create_with_component_type(mavsdk_asyncio.ComponentType.GROUND_STATION)
        async with mavsdk_asyncio.Mavsdk(config) as sdk:
            await sdk.add_any_connection(f"udpin://127.0.0.1:{port}")
            system = await sdk.first_autopilot(timeout_s=HANG_S)
            assert system is not None, "MAVSDK did not discover the simulator as an autopilot"
            assert await system.autopilot_type() == (1 if profile == "px4" else 2)
            tel = telemetry.TelemetryAsync(system)
            async with asyncio.timeout(HANG_S):
                async for pv in tel.subscribe_position_velocity_ned():
                    if not math.isnan(pv.position.north_m):
                        break
            assert (pv.position.north_m, pv.position.east_m) == pytest.approx((2.0, 3.0), abs=1e-4)
            assert pv.position.down_m == pytest.approx(-5.0, abs=1e-3)
            assert pv.velocity.north_m_s == pytest.approx(0.0, abs=1e-3)
            # requests that need our COMMAND_ACKs: a message rate, then a mode change (RTL) that moves it
            async with asyncio.timeout(HANG_S):
                await tel.set_rate_position_velocity_ned(20.0)
                await action.ActionAsync(system).return_to_launch()
            await wait_for(sim, lambda s: s.vehicle.mode in ("RTL", "AUTO.RTL"))
            async with asyncio.timeout(HANG_S):
                async for pv in tel.subscribe_position_velocity_ned():
                    if pv.velocity.north_m_s < -0.2:  # flying home (south-west) or climbing first
                        break
                    if pv.velocity.down_m_s < -0.2:
                        break
    finally:
        await sim.aclose()


def _mavproxy() -> str | None:
    """mavproxy.py beside this interpreter (a venv used without activation), else on PATH."""
    beside = Path(sys.executable).parent / "mavproxy.py"
    return str(beside) if beside.is_file() else shutil.which("mavproxy.py")


@pytest.mark.skipif(_mavproxy() is None, reason="MAVProxy not installed (pip install --no-deps MAVProxy)")
async def test_mavproxy_headless_sees_heartbeat_and_mode(tmp_path: Path) -> None:
    port = free_port(socket.SOCK_DGRAM)
    mavproxy = _mavproxy()
    assert mavproxy is not None
    proc = await asyncio.create_subprocess_exec(
        sys.executable, "-u", mavproxy, f"--master=udpin:127.0.0.1:{port}", "--daemon", "--non-interactive",
        f"--state-basedir={tmp_path}",
        stdout=asyncio.subprocess.PIPE, stderr=asyncio.subprocess.STDOUT, cwd=tmp_path,
    )  # fmt: skip
    ctl = await MavlinkLink.open("udpin:127.0.0.1:0", source_system=250, source_component=190)
    assert ctl.local_address is not None
    sim = await Simulator.start(
        SimConfig(
            links=[f"udpout:127.0.0.1:{port}", f"udpout:127.0.0.1:{ctl.local_address[1]}"],
            profile="ardupilot",
            spawn=SpawnConfig(airborne=True),
            unasked_streams=True,
        )
    )
    lines: list[str] = []

    async def read_until(needle: str) -> None:
        assert proc.stdout is not None
        while True:
            line = (await proc.stdout.readline()).decode(errors="replace")
            if not line:
                raise AssertionError(f"MAVProxy exited; output: {lines}")
            lines.append(line.rstrip())
            if needle in line:
                return

    try:
        async with asyncio.timeout(HANG_S):  # MAVProxy starts slowly on a loaded machine
            await read_until("Detected vehicle 1:1")
            await read_until("Mode GUIDED")
            await ctl.recv_match(type="HEARTBEAT", timeout=HANG_S)
            ack = await command_long(ctl, m.MAV_CMD_DO_SET_MODE, 1, CopterMode.LOITER, timeout=HANG_S)
            assert ack.result == m.MAV_RESULT_ACCEPTED
            await read_until("Mode LOITER")
        assert "online system 1" in lines
        assert "ARMED" in lines
    finally:
        if proc.returncode is None:
            proc.terminate()
            await reap(proc)
        await sim.aclose()
        await ctl.aclose()
    assert (tmp_path / "mav.tlog").stat().st_size > 0  # MAVProxy logged our traffic


@pytest.mark.parametrize("profile", ["px4", "ardupilot"])
async def test_mavsdk_standard_flows(profile: str) -> None:
    """MAVSDK's usual sequence: wait for health, arm (param2 = NaN), take off, goto while still climbing (the goto
    wins: ArduCopter mode_guided.cpp / PX4 reposition), then offboard with a single setpoint before start (PX4
    offboardCheck.cpp: the last setpoint must be newer than COM_OF_LOSS_T, no pre-stream)."""
    mavsdk_asyncio = pytest.importorskip("mavsdk.asyncio")
    telemetry = pytest.importorskip("mavsdk.asyncio.plugins.telemetry")
    action = pytest.importorskip("mavsdk.asyncio.plugins.action")
    offboard = pytest.importorskip("mavsdk.asyncio.plugins.offboard")
    port = free_port(socket.SOCK_DGRAM)
    sim = await Simulator.start(
        SimConfig(
            links=[f"udpout:127.0.0.1:{port}"], profile=profile, speedup=4.0, fast_start=True, unasked_streams=True
        )
    )
    try:
        config = mavsdk_asyncio.Configuration.create_with_component_type(mavsdk_asyncio.ComponentType.GROUND_STATION)
        async with mavsdk_asyncio.Mavsdk(config) as sdk:
            await sdk.add_any_connection(f"udpin://127.0.0.1:{port}")
            system = await sdk.first_autopilot(timeout_s=5.0)
            assert system is not None
            tel, act = telemetry.TelemetryAsync(system), action.ActionAsync(system)
            async with asyncio.timeout(8.0):
                async for health in tel.subscribe_health():
                    if health.is_global_position_ok and health.is_home_position_ok:
                        break
            assert health.is_armable == (profile == "ardupilot")  # PX4's SYS_STATUS has no PREARM_CHECK here
            async with asyncio.timeout(5.0):
                await act.arm()
                await act.set_takeoff_altitude(10.0)
                await act.takeoff()
            await wait_for(sim, lambda s: s.vehicle.pos_ned_m[2] < -1.5)
            home = await tel.home()
            north_deg = math.degrees(6.0 / 6378137.0)
            async with asyncio.timeout(5.0):
                await act.goto_location(
                    home.latitude_deg + north_deg, home.longitude_deg, home.absolute_altitude_m + 4, 0
                )
            await wait_for(
                sim, lambda s: abs(s.vehicle.pos_ned_m[0] - 6.0) < 0.2 and abs(s.vehicle.pos_ned_m[2] + 4) < 0.2
            )
            assert sim.vehicle.pos_ned_m[2] > -4.5  # the climb to 10 m was abandoned
            off = offboard.OffboardAsync(system)
            async with asyncio.timeout(5.0):
                await off.set_position_ned(offboard.PositionNedYaw(0.0, 0.0, -5.0, 0.0))
                await off.start()
            await wait_for(sim, lambda s: s.vehicle.mode in ("OFFBOARD", "GUIDED"))
            await wait_for(sim, lambda s: float(np.linalg.norm(s.vehicle.pos_ned_m - [0.0, 0.0, -5.0])) < 0.1)
            async with asyncio.timeout(5.0):
                await off.stop()
        assert sim.error is None
    finally:
        await sim.aclose()
