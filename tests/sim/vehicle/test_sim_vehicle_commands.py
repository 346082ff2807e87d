"""The simulated autopilot over real loopback UDP with a pymavlink-based client: identity, commands and their
ACKs, parameters, message intervals, requests, tlog recording."""

from __future__ import annotations

import asyncio
import itertools
from collections.abc import Callable
from pathlib import Path
from typing import Any

import pytest
from pymavlink import mavutil
from pymavlink.dialects.v20 import ardupilotmega as m

from apf_companion.autopilot import PX4_HOLD, PX4_OFFBOARD, PX4_TAKEOFF, CopterMode, Px4Mode
from apf_companion.errors import LinkTimeout
from apf_companion.links import MavlinkLink
from sim.vehicle import SimConfig, Simulator, SpawnConfig
from sim.vehicle.testing import command_int, command_long, simulator_with_client
from tests.conftest import HANG_S, wait_for

ACCEPTED = m.MAV_RESULT_ACCEPTED
FAILED = m.MAV_RESULT_FAILED
TEMP_REJECTED = m.MAV_RESULT_TEMPORARILY_REJECTED
UNSUPPORTED = m.MAV_RESULT_UNSUPPORTED


async def heartbeat(link: MavlinkLink, condition: Callable[[Any], bool] | None = None) -> Any:
    return await link.recv_match(type="HEARTBEAT", condition=condition, timeout=HANG_S)


@pytest.mark.parametrize(
    ("profile", "autopilot", "custom_mode"),
    [
        ("ardupilot", m.MAV_AUTOPILOT_ARDUPILOTMEGA, CopterMode.STABILIZE),
        ("px4", m.MAV_AUTOPILOT_PX4, PX4_HOLD.to_custom_mode()),
    ],
)
async def test_heartbeat_identity(profile: str, autopilot: int, custom_mode: int) -> None:
    async with simulator_with_client(profile=profile) as (_sim, gcs):
        hb = await heartbeat(gcs)
        assert (hb.get_srcSystem(), hb.get_srcComponent()) == (1, 1)
        assert hb.type == m.MAV_TYPE_QUADROTOR
        assert hb.autopilot == autopilot
        assert hb.custom_mode == custom_mode
        assert hb.base_mode & m.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED
        assert not hb.base_mode & m.MAV_MODE_FLAG_SAFETY_ARMED
        assert hb.system_status == m.MAV_STATE_STANDBY
        assert hb.get_header().mlen > 0 and hb.get_msgbuf()[0] == 0xFD  # MAVLink 2 frames


async def test_default_rates_in_sim_time() -> None:
    async with simulator_with_client(speedup=20.0) as (_sim, gcs):
        stamps: dict[str, list[int]] = {"LOCAL_POSITION_NED": [], "ATTITUDE": [], "GLOBAL_POSITION_INT": []}
        while min(len(v) for v in stamps.values()) < 6:
            msg = await gcs.recv_match(type=tuple(stamps), timeout=HANG_S)
            stamps[msg.get_type()].append(msg.time_boot_ms)
        assert {
            b - a for a, b in zip(stamps["LOCAL_POSITION_NED"][1:], stamps["LOCAL_POSITION_NED"][2:], strict=False)
        } == {100}
        assert {b - a for a, b in zip(stamps["ATTITUDE"][1:], stamps["ATTITUDE"][2:], strict=False)} == {100}
        assert {
            b - a for a, b in zip(stamps["GLOBAL_POSITION_INT"][1:], stamps["GLOBAL_POSITION_INT"][2:], strict=False)
        } == {200}


async def test_arm_disarm_acks_ardupilot() -> None:
    async with simulator_with_client(profile="ardupilot") as (sim, gcs):
        ack = await command_long(gcs, m.MAV_CMD_COMPONENT_ARM_DISARM, 1)
        assert ack.result == ACCEPTED
        assert (ack.target_system, ack.target_component) == (255, 190)
        hb = await heartbeat(gcs, lambda h: h.base_mode & m.MAV_MODE_FLAG_SAFETY_ARMED)
        assert hb.system_status == m.MAV_STATE_ACTIVE
        assert (await command_long(gcs, m.MAV_CMD_COMPONENT_ARM_DISARM, 1)).result == ACCEPTED  # already armed
        assert (await command_long(gcs, m.MAV_CMD_COMPONENT_ARM_DISARM, 0)).result == ACCEPTED  # landed: ok
        assert not sim.vehicle.armed
        # LAND is not an armable mode on ArduCopter
        assert (await command_long(gcs, m.MAV_CMD_DO_SET_MODE, 1, CopterMode.LAND)).result == ACCEPTED
        texts: list[str] = []
        assert (await command_long(gcs, m.MAV_CMD_COMPONENT_ARM_DISARM, 1, texts=texts)).result == FAILED
        assert any("not armable" in t for t in texts)


async def test_disarm_in_flight_needs_force() -> None:
    async with simulator_with_client(profile="ardupilot", spawn=SpawnConfig(airborne=True)) as (sim, gcs):
        assert (await command_long(gcs, m.MAV_CMD_COMPONENT_ARM_DISARM, 0)).result == FAILED
        assert sim.vehicle.armed
        assert (await command_long(gcs, m.MAV_CMD_COMPONENT_ARM_DISARM, 0, 21196)).result == ACCEPTED
        # motors off in the air: it falls and crashes on the ground from 5 m
        await wait_for(sim, lambda s: s.vehicle.on_ground or s.vehicle.crashed)
        assert sim.vehicle.crashed and sim.result()["crashed_at"]["obstacle_id"] == -1


async def test_px4_rejections_are_temporarily_rejected() -> None:
    async with simulator_with_client(profile="px4") as (_sim, gcs):
        ack = await command_long(gcs, m.MAV_CMD_DO_SET_MODE, 1, 1)  # MANUAL needs RC
        assert ack.result == TEMP_REJECTED
        texts: list[str] = []
        ack = await command_long(gcs, m.MAV_CMD_DO_SET_MODE, 1, 6, texts=texts)  # OFFBOARD without a stream
        assert ack.result == TEMP_REJECTED
        assert "Switching to Offboard is currently not available" in texts
        ack = await command_long(gcs, m.MAV_CMD_DO_SET_MODE, 0, 4, 3)  # no custom-mode flag
        assert ack.result == m.MAV_RESULT_DENIED
        ack = await command_long(gcs, m.MAV_CMD_DO_SET_MODE, 1, 4, 3)  # AUTO.LOITER
        assert ack.result == ACCEPTED
        ack = await command_long(gcs, m.MAV_CMD_COMPONENT_ARM_DISARM, 0)  # disarmed already: fine
        assert ack.result == ACCEPTED


async def test_set_mode_command_and_message_ardupilot() -> None:
    async with simulator_with_client(profile="ardupilot") as (sim, gcs):
        assert (await command_long(gcs, m.MAV_CMD_DO_SET_MODE, 1, CopterMode.GUIDED)).result == ACCEPTED
        hb = await heartbeat(gcs, lambda h: h.custom_mode == CopterMode.GUIDED)
        assert hb.base_mode & m.MAV_MODE_FLAG_GUIDED_ENABLED
        assert (await command_long(gcs, m.MAV_CMD_DO_SET_MODE, 1, CopterMode.AUTO)).result == FAILED
        assert (await command_long(gcs, m.MAV_CMD_DO_SET_MODE, 0, CopterMode.LOITER)).result == UNSUPPORTED
        gcs.send(gcs.mav.set_mode_encode(1, m.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED, CopterMode.LOITER))
        ack = await gcs.recv_match(type="COMMAND_ACK", timeout=HANG_S)
        assert (ack.command, ack.result) == (m.MAVLINK_MSG_ID_SET_MODE, ACCEPTED)
        await heartbeat(gcs, lambda h: h.custom_mode == CopterMode.LOITER)
        ack = await command_int(gcs, m.MAV_CMD_DO_SET_MODE, params=(1, CopterMode.BRAKE, 0, 0))
        assert ack.result == ACCEPTED
        assert sim.vehicle.mode == "BRAKE"


async def test_commands_for_other_components_are_not_answered() -> None:
    async with simulator_with_client() as (sim, gcs):
        with pytest.raises(LinkTimeout):
            await command_long(gcs, m.MAV_CMD_COMPONENT_ARM_DISARM, 1, target=(1, 191), timeout=0.3)
        with pytest.raises(LinkTimeout):
            await command_long(gcs, m.MAV_CMD_COMPONENT_ARM_DISARM, 1, target=(2, 1), timeout=0.3)
        assert not sim.vehicle.armed
        assert (await command_long(gcs, m.MAV_CMD_COMPONENT_ARM_DISARM, 1, target=(0, 0))).result == ACCEPTED


async def test_unsupported_command() -> None:
    async with simulator_with_client() as (_sim, gcs):
        ack = await command_long(gcs, m.MAV_CMD_DO_MOTOR_TEST, 1)
        assert ack.result == UNSUPPORTED
        assert (await command_long(gcs, m.MAV_CMD_DO_REPOSITION, -1)).result == UNSUPPORTED  # COMMAND_INT only


async def test_takeoff_and_land_ardupilot() -> None:
    async with simulator_with_client(profile="ardupilot", speedup=20.0) as (sim, gcs):
        # not armed / not GUIDED -> FAILED
        assert (await command_long(gcs, m.MAV_CMD_NAV_TAKEOFF, 0, 0, 0, 0, 0, 0, 4)).result == FAILED
        assert (await command_long(gcs, m.MAV_CMD_DO_SET_MODE, 1, CopterMode.GUIDED)).result == ACCEPTED
        assert (await command_long(gcs, m.MAV_CMD_COMPONENT_ARM_DISARM, 1)).result == ACCEPTED
        assert (await command_long(gcs, m.MAV_CMD_NAV_TAKEOFF, 0, 0, 0, 0, 0, 0, 4)).result == ACCEPTED
        state = await gcs.recv_match(type="EXTENDED_SYS_STATE", timeout=HANG_S)
        assert state.landed_state in (m.MAV_LANDED_STATE_TAKEOFF, m.MAV_LANDED_STATE_ON_GROUND)
        await wait_for(sim, lambda s: s.vehicle.pos_ned_m[2] < -3.95)
        await gcs.recv_match(
            type="EXTENDED_SYS_STATE", condition=lambda x: x.landed_state == m.MAV_LANDED_STATE_IN_AIR, timeout=2.0
        )
        assert sim.vehicle.pos_ned_m[2] == pytest.approx(-4.0, abs=0.1)
        assert (await command_long(gcs, m.MAV_CMD_NAV_TAKEOFF, 0, 0, 0, 0, 0, 0, 4)).result == FAILED  # flying
        assert (await command_long(gcs, m.MAV_CMD_NAV_LAND)).result == ACCEPTED
        assert sim.vehicle.mode == "LAND"
        await wait_for(sim, lambda s: not s.vehicle.armed)
        assert sim.vehicle.on_ground and sim.vehicle.pos_ned_m[2] == 0.0
        assert any("Land complete" in s.text for s in sim.engine.statustexts)


async def test_takeoff_px4_goes_to_hold() -> None:
    async with simulator_with_client(profile="px4", speedup=20.0) as (sim, gcs):
        assert (await command_long(gcs, m.MAV_CMD_COMPONENT_ARM_DISARM, 1)).result == ACCEPTED
        ack = await command_long(gcs, m.MAV_CMD_NAV_TAKEOFF, 0, 0, 0, 0, 0, 0, float("nan"))
        assert ack.result == ACCEPTED
        await heartbeat(gcs, lambda h: h.custom_mode == PX4_TAKEOFF.to_custom_mode())
        await heartbeat(gcs, lambda h: h.custom_mode == PX4_HOLD.to_custom_mode())
        assert sim.vehicle.pos_ned_m[2] == pytest.approx(-2.5, abs=0.15)  # MIS_TAKEOFF_ALT
        # param7 is AMSL on PX4: home (584 m) + 6 m climbs 6 m; a relative "5" is below home: the minimum
        assert (await command_long(gcs, m.MAV_CMD_NAV_LAND)).result == ACCEPTED
        await wait_for(sim, lambda s: s.vehicle.on_ground and not s.vehicle.armed)
        assert (await command_long(gcs, m.MAV_CMD_COMPONENT_ARM_DISARM, 1)).result == ACCEPTED
        texts: list[str] = []
        ack = await command_long(gcs, m.MAV_CMD_NAV_TAKEOFF, 0, 0, 0, 0, 0, 0, 5.0, texts=texts)
        assert ack.result == ACCEPTED and texts == ["Using minimum takeoff altitude: 2.50 m"]
        assert (await command_long(gcs, m.MAV_CMD_NAV_LAND)).result == ACCEPTED
        await wait_for(sim, lambda s: s.vehicle.on_ground and not s.vehicle.armed)
        assert (await command_long(gcs, m.MAV_CMD_COMPONENT_ARM_DISARM, 1)).result == ACCEPTED
        assert (await command_long(gcs, m.MAV_CMD_NAV_TAKEOFF, 0, 0, 0, 0, 0, 0, 584.0 + 6.0)).result == ACCEPTED
        await heartbeat(gcs, lambda h: h.custom_mode == PX4_HOLD.to_custom_mode())
        assert sim.vehicle.pos_ned_m[2] == pytest.approx(-6.0, abs=0.15)
        assert (await command_long(gcs, m.MAV_CMD_NAV_RETURN_TO_LAUNCH)).result == ACCEPTED
        assert sim.vehicle.mode == "AUTO.RTL"


async def test_message_interval_and_requests() -> None:
    async with simulator_with_client(speedup=10.0) as (sim, gcs):
        lpn = m.MAVLINK_MSG_ID_LOCAL_POSITION_NED
        assert (await command_long(gcs, m.MAV_CMD_SET_MESSAGE_INTERVAL, lpn, 20_000)).result == ACCEPTED
        t = [(await gcs.recv_match(type="LOCAL_POSITION_NED", timeout=HANG_S)).time_boot_ms for _ in range(6)]
        assert {b - a for a, b in itertools.pairwise(t[1:])} == {20}
        ack = await command_long(gcs, m.MAV_CMD_GET_MESSAGE_INTERVAL, lpn)
        assert ack.result == ACCEPTED
        iv = await gcs.recv_match(type="MESSAGE_INTERVAL", timeout=HANG_S)
        assert (iv.message_id, iv.interval_us) == (lpn, 20_000)
        assert (await command_long(gcs, m.MAV_CMD_SET_MESSAGE_INTERVAL, lpn, -1)).result == ACCEPTED
        t0 = sim.t_s  # the stream was off before this: frames still in flight are stamped earlier
        await wait_for(sim, lambda s: s.t_s > t0 + 1.0)
        got = []
        while (msg := gcs.recv_nowait()) is not None:
            if msg.get_type() in ("LOCAL_POSITION_NED", "ATTITUDE") and msg.time_boot_ms > t0 * 1000.0:
                got.append(msg.get_type())
        assert "LOCAL_POSITION_NED" not in got and "ATTITUDE" in got
        # ArduPilot DENIES a message id it cannot send (GCS_Common.cpp set_message_interval)
        assert (await command_long(gcs, m.MAV_CMD_SET_MESSAGE_INTERVAL, 12345, 1000)).result == m.MAV_RESULT_DENIED

        ack = await command_long(gcs, m.MAV_CMD_REQUEST_MESSAGE, m.MAVLINK_MSG_ID_AUTOPILOT_VERSION)
        assert ack.result == ACCEPTED
        ver = await gcs.recv_match(type="AUTOPILOT_VERSION", timeout=HANG_S)
        assert ver.capabilities & m.MAV_PROTOCOL_CAPABILITY_MAVLINK2
        assert ver.capabilities & m.MAV_PROTOCOL_CAPABILITY_SET_POSITION_TARGET_LOCAL_NED
        ack = await command_long(gcs, m.MAV_CMD_REQUEST_MESSAGE, m.MAVLINK_MSG_ID_HOME_POSITION)
        assert ack.result == ACCEPTED
        home = await gcs.recv_match(type="HOME_POSITION", timeout=HANG_S)
        assert (home.latitude, home.longitude, home.altitude) == (-353632620, 1491652370, 584000)
        assert (await command_long(gcs, m.MAV_CMD_REQUEST_MESSAGE, 9999)).result == FAILED
        assert (await command_long(gcs, m.MAV_CMD_REQUEST_AUTOPILOT_CAPABILITIES, 1)).result == ACCEPTED
        await gcs.recv_match(type="AUTOPILOT_VERSION", timeout=HANG_S)


async def test_timesync_and_mission_count() -> None:
    async with simulator_with_client(speedup=1.0) as (sim, gcs):
        gcs.send(gcs.mav.timesync_encode(0, 123456789))
        ts = await gcs.recv_match(type="TIMESYNC", timeout=HANG_S)
        assert ts.ts1 == 123456789
        assert 0 < ts.tc1 <= sim.t_s * 1e9  # our simulated clock in ns
        gcs.send(gcs.mav.mission_request_list_encode(1, 1))
        count = await gcs.recv_match(type="MISSION_COUNT", timeout=HANG_S)
        assert (count.count, count.target_system) == (0, 255)


async def test_parameters() -> None:
    async with simulator_with_client(profile="ardupilot") as (_sim, gcs):
        gcs.send(gcs.mav.param_request_list_encode(1, 1))
        values = {}
        while True:
            pv = await gcs.recv_match(type="PARAM_VALUE", timeout=HANG_S)
            values[pv.param_id] = (pv.param_value, pv.param_index, pv.param_count)
            if len(values) == pv.param_count:
                break
        assert values["GUID_TIMEOUT"][0] == 3.0
        assert values["SIM_RNG_MAX"][0] == 8.0
        assert sorted(v[1] for v in values.values()) == list(range(len(values)))
        gcs.send(gcs.mav.param_request_read_encode(1, 1, b"", values["WPNAV_SPEED"][1]))
        pv = await gcs.recv_match(type="PARAM_VALUE", timeout=HANG_S)
        assert (pv.param_id, pv.param_value) == ("WPNAV_SPEED", 500.0)
        gcs.send(gcs.mav.param_set_encode(1, 1, b"GUID_TIMEOUT", 1.5, m.MAV_PARAM_TYPE_REAL32))
        pv = await gcs.recv_match(type="PARAM_VALUE", timeout=HANG_S)
        assert (pv.param_id, pv.param_value) == ("GUID_TIMEOUT", 1.5)
        gcs.send(gcs.mav.param_set_encode(1, 1, b"GUID_TIMEOUT", 99.0, m.MAV_PARAM_TYPE_REAL32))
        text = await gcs.recv_match(type="STATUSTEXT", timeout=HANG_S)
        assert text.text == "GUID_TIMEOUT 99 not in [0.1, 5]"
        pv = await gcs.recv_match(type="PARAM_VALUE", timeout=HANG_S)
        assert pv.param_value == 1.5  # refused: the old value
        gcs.send(gcs.mav.param_request_read_encode(1, 1, b"NO_SUCH_PARAM", -1))
        gcs.send(gcs.mav.param_request_read_encode(1, 1, b"GUID_TIMEOUT", -1))
        pv = await gcs.recv_match(type="PARAM_VALUE", timeout=HANG_S)
        assert pv.param_id == "GUID_TIMEOUT"  # the unknown one got no answer


async def test_px4_parameters() -> None:
    async with simulator_with_client(profile="px4", params={"COM_OF_LOSS_T": 0.5}) as (_sim, gcs):
        gcs.send(gcs.mav.param_request_read_encode(1, 1, b"COM_OF_LOSS_T", -1))
        pv = await gcs.recv_match(type="PARAM_VALUE", timeout=HANG_S)
        assert pv.param_value == 0.5
        gcs.send(gcs.mav.param_request_read_encode(1, 1, b"GUID_TIMEOUT", -1))
        with pytest.raises(LinkTimeout):
            await gcs.recv_match(type="PARAM_VALUE", timeout=0.3)


async def test_two_links_and_tlog_read_back(tmp_path: Path) -> None:
    tlog = tmp_path / "sim.tlog"
    gcs2 = await MavlinkLink.open("tcpin:127.0.0.1:0", source_system=254, source_component=190)
    try:
        assert gcs2.local_address is not None
        tcp = f"tcp:127.0.0.1:{gcs2.local_address[1]}"
        async with simulator_with_client(links=[tcp], tlog_path=tlog) as (_sim, gcs):
            hb2 = await gcs2.recv_match(type="HEARTBEAT", timeout=HANG_S)
            assert hb2.get_srcSystem() == 1
            assert (await command_long(gcs, m.MAV_CMD_DO_SET_MODE, 1, CopterMode.GUIDED)).result == ACCEPTED
            # telemetry and STATUSTEXT go to every link; the ACK only to the link that asked
            await heartbeat(gcs2, lambda h: h.custom_mode == CopterMode.GUIDED)
            assert (await command_long(gcs2, m.MAV_CMD_COMPONENT_ARM_DISARM, 1)).result == ACCEPTED
            with pytest.raises(LinkTimeout):
                await gcs.recv_match(type="COMMAND_ACK", condition=lambda a: a.command == 400, timeout=0.3)
    finally:
        await gcs2.aclose()
    # pymavlink's own tlog reader sees frames out (telemetry) and in (the client's COMMAND_LONG)
    log = mavutil.mavlink_connection(str(tlog), dialect="ardupilotmega")
    types: dict[str, int] = {}
    while (msg := log.recv_match()) is not None:
        types[msg.get_type()] = types.get(msg.get_type(), 0) + 1
        if msg.get_type() == "COMMAND_LONG":
            assert msg.get_srcSystem() == 255
    assert types.get("HEARTBEAT", 0) >= 1 and types.get("COMMAND_LONG") == 1 and types.get("COMMAND_ACK") == 1
    assert (tmp_path / "sim.link1.tlog").stat().st_size > 0


async def test_classic_pymavlink_client() -> None:
    # A plain blocking mavutil connection (as in scripts and MAVProxy), run in a worker thread.
    sim = await Simulator.start(SimConfig(links=["udpin:127.0.0.1:0"], profile="px4", speedup=5.0))
    try:
        port = sim.links[0].local_address[1]  # type: ignore[index]

        def client() -> tuple[int, int, int]:
            conn = mavutil.mavlink_connection(f"udpout:127.0.0.1:{port}", source_system=255, dialect="ardupilotmega")
            try:
                conn.mav.heartbeat_send(m.MAV_TYPE_GCS, m.MAV_AUTOPILOT_INVALID, 0, 0, 0)
                hb = conn.wait_heartbeat(timeout=5)
                assert hb is not None
                conn.mav.command_long_send(1, 1, m.MAV_CMD_COMPONENT_ARM_DISARM, 0, 1, 0, 0, 0, 0, 0, 0)
                ack = conn.recv_match(type="COMMAND_ACK", blocking=True, timeout=5)
                assert ack is not None
                return hb.autopilot, ack.command, ack.result
            finally:
                conn.close()

        assert await asyncio.to_thread(client) == (m.MAV_AUTOPILOT_PX4, 400, ACCEPTED)
        assert sim.vehicle.armed
        assert Px4Mode.from_custom_mode(sim.vehicle.custom_mode) == PX4_HOLD
        assert sim.vehicle.custom_mode != PX4_OFFBOARD.to_custom_mode()
    finally:
        await sim.aclose()
