"""The ArduPilot profile's proximity library (PRX1_TYPE = 2), MAV_CMD_PREFLIGHT_REBOOT_SHUTDOWN and the dropping of
packets that carry the autopilot's own ids, over loopback UDP (rules: sim/vehicle/proximity.py, reboot.py).

Source files: AP_Proximity_MAV.cpp (OBSTACLE_DISTANCE, 500 ms timeout), AP_Proximity_Params.cpp (PRX1_TYPE
@RebootRequired), GCS_Common.cpp (send_proximity, handle_preflight_reboot), ArduCopter/GCS_Copter.cpp (SYS_STATUS
proximity bits), MAVLink_routing.cpp ("loopback of our own messages").
"""

from __future__ import annotations

import asyncio
from typing import Any

import pytest
from pymavlink.dialects.v20 import ardupilotmega as m

from apf_companion.autopilot import CopterMode
from apf_companion.errors import LinkTimeout
from apf_companion.links import MavlinkLink
from sim.vehicle import SpawnConfig
from sim.vehicle.proximity import PROXIMITY_TIMEOUT_S, Proximity, ProximityStatus
from sim.vehicle.testing import command_long, drain, simulator_with_client, wait_sim_time
from tests.conftest import HANG_S, StepWatch

PRX = m.MAV_SYS_STATUS_SENSOR_PROXIMITY
ACCEPTED = m.MAV_RESULT_ACCEPTED
FORCE_REBOOT = 20190226
FREE = 801


def obstacle_distance(mav: Any, distances: list[int], *, offset: float = 0.0) -> Any:
    return mav.obstacle_distance_encode(0, m.MAV_DISTANCE_SENSOR_LASER, distances, 5, 20, 800, 5.0, offset, 12)


def sectors(**cm: int) -> list[int]:
    """72 sectors of 5 deg, free except the ones named s<index>."""
    out = [FREE] * 72
    for key, value in cm.items():
        out[int(key[1:])] = value
    return out


async def set_param(gcs: MavlinkLink, name: str, value: float) -> float:
    gcs.send(gcs.mav.param_set_encode(1, 1, name.encode(), value, m.MAV_PARAM_TYPE_REAL32))
    pv = await gcs.recv_match(condition=lambda x: x.get_type() == "PARAM_VALUE" and x.param_id == name, timeout=HANG_S)
    return float(pv.param_value)


async def sys_status_bits(gcs: MavlinkLink) -> tuple[bool, bool, bool]:
    st = await gcs.recv_match(type="SYS_STATUS", timeout=HANG_S)
    return tuple(bool(f & PRX) for f in (st.onboard_control_sensors_present, st.onboard_control_sensors_enabled,
                                         st.onboard_control_sensors_health))  # type: ignore[return-value]  # fmt: skip


def test_obstacle_distance_faces_orientation_and_yaw_correction() -> None:
    """AP_Proximity_MAV.cpp: element j at j * increment + angle_offset + PRX1_YAW_CORR (increment negated with
    PRX1_ORIENT 1); each 45 deg face keeps its nearest reading; 0, UINT16_MAX and out-of-range readings skipped."""
    mav = m.MAVLink(None)
    msg = obstacle_distance(mav, sectors(s0=300, s1=250, s9=500, s18=0, s27=65535, s36=900, s45=10))
    prx = Proximity(2, 0, 0)
    prx.on_obstacle_distance(msg, t_s=1.0)
    # faces: 0 (-22.5..22.5: sectors 0-4 and 68-71) nearest 250; 1 (45 deg) 500; the rest invalid
    assert prx.faces_m == [2.5, 5.0, None, None, None, None, None, None]
    upside_down = Proximity(2, 1, 0)  # bearings mirrored: sector 9 (45 deg) -> -45 deg = face 7
    upside_down.on_obstacle_distance(msg, t_s=1.0)
    assert upside_down.faces_m == [2.5, None, None, None, None, None, None, 5.0]
    corrected = Proximity(2, 0, 90)  # +90 deg: face 0 -> 2, face 1 -> 3
    corrected.on_obstacle_distance(msg, t_s=1.0)
    assert corrected.faces_m == [None, None, 2.5, 5.0, None, None, None, None]
    corrected.on_obstacle_distance(obstacle_distance(mav, sectors(s0=400), offset=-90.0), t_s=2.0)
    assert corrected.faces_m == [4.0, None, None, None, None, None, None, None]  # replaced, angle_offset applied
    none = Proximity(0, 0, 0)
    none.on_obstacle_distance(msg, t_s=1.0)
    assert none.status(1.0) is ProximityStatus.NOT_CONNECTED and none.sensor_flags(1.0) == (0, 0, 0)
    assert prx.status(1.0 + PROXIMITY_TIMEOUT_S) is ProximityStatus.GOOD
    assert prx.status(1.0 + PROXIMITY_TIMEOUT_S + 1e-6) is ProximityStatus.NO_DATA


def test_obstacle_distance_reads_as_many_elements_as_arducopter_halves_rounded_up() -> None:
    """AP_Proximity_MAV.cpp reads MIN(360 / |increment| + 0.5, 72) elements: at 16 deg, 22.5 -> 23, so element 22
    (352 deg, face 0) counts. Python's round() gave 22 (a half to even) and dropped it; the simulator now uses the
    service's rule (``apf_companion.perception.obstacle_distance_element_count``)."""
    mav = m.MAVLink(None)
    distances = [FREE] * 72
    distances[22] = 300
    msg = mav.obstacle_distance_encode(0, m.MAV_DISTANCE_SENSOR_LASER, distances, 16, 20, 800, 16.0, 0.0, 12)
    prx = Proximity(2, 0, 0)
    prx.on_obstacle_distance(msg, t_s=1.0)
    assert prx.faces_m[0] == 3.0


async def test_prx1_type_takes_effect_after_reboot_and_reports_distance_sensors() -> None:
    spawn = SpawnConfig(yaw_deg=30.0)
    async with simulator_with_client(profile="ardupilot", spawn=spawn, speedup=2.0) as (sim, gcs):
        assert await set_param(gcs, "WPNAV_SPEED", 300.0) == 300.0
        assert await set_param(gcs, "PRX1_TYPE", 2.0) == 2.0
        gcs.send(obstacle_distance(gcs.mav, sectors(s0=300)))
        assert await sys_status_bits(gcs) == (False, False, False)  # PRX1_TYPE is read at boot only
        assert (await command_long(gcs, m.MAV_CMD_DO_SET_MODE, 1, CopterMode.GUIDED)).result == ACCEPTED
        ack = await command_long(gcs, m.MAV_CMD_SET_MESSAGE_INTERVAL, m.MAVLINK_MSG_ID_ATTITUDE, 250_000)
        assert ack.result == ACCEPTED
        await wait_sim_time(sim, 4.0)
        await drain(gcs)
        att = await gcs.recv_match(type="ATTITUDE", timeout=HANG_S)
        before_ms = att.time_boot_ms
        assert before_ms >= 4000

        assert (await command_long(gcs, m.MAV_CMD_PREFLIGHT_REBOOT_SHUTDOWN, 1)).result == ACCEPTED
        hb = await gcs.recv_match(type="HEARTBEAT", timeout=HANG_S)
        assert hb.system_status == m.MAV_STATE_BOOT  # the first sign of life is the booting firmware
        hb = await gcs.recv_match(
            condition=lambda x: x.get_type() == "HEARTBEAT" and x.system_status != m.MAV_STATE_BOOT, timeout=HANG_S
        )
        assert hb.custom_mode == CopterMode.STABILIZE
        att = await gcs.recv_match(type="ATTITUDE", timeout=HANG_S)
        assert (
            att.time_boot_ms < 2000 < before_ms
        )  # time since boot restarted (boot ends at 1 s, sim/vehicle/reboot.py)
        assert await set_param(gcs, "WPNAV_SPEED", 300.0) == 300.0  # stored parameters survive
        await command_long(gcs, m.MAV_CMD_GET_MESSAGE_INTERVAL, m.MAVLINK_MSG_ID_ATTITUDE)
        mi = await gcs.recv_match(type="MESSAGE_INTERVAL", timeout=HANG_S)
        assert mi.interval_us == 100_000  # SET_MESSAGE_INTERVAL is not stored: back to the default (10 Hz)
        assert await sys_status_bits(gcs) == (True, True, False)  # the MAVLink backend exists, no data yet

        # the GCS asks for DISTANCE_SENSOR (message intervals do not survive a reboot)
        ack = await command_long(gcs, m.MAV_CMD_SET_MESSAGE_INTERVAL, m.MAVLINK_MSG_ID_DISTANCE_SENSOR, 200_000)
        assert ack.result == ACCEPTED
        # the companion streams OBSTACLE_DISTANCE at 10 Hz of simulated time (here from the GCS's link: the
        # proximity library takes it from anyone), body bearings 5-10 deg and 180 deg
        watch: StepWatch[ProximityStatus] = StepWatch(sim, lambda s: s.engine.proximity.status(s.t_s))
        streaming = asyncio.get_running_loop().create_task(stream(sim, gcs, sectors(s1=300, s2=250, s36=420)))
        try:
            faces: dict[int, Any] = {}
            while len(faces) < 2:
                ds = await gcs.recv_match(type="DISTANCE_SENSOR", timeout=HANG_S)
                faces[ds.orientation] = ds
            assert faces[0].current_distance == 250 and faces[0].id == 10
            assert faces[4].current_distance == 420 and faces[4].id == 14  # body 180 deg: YAW_180
            assert (faces[0].min_distance, faces[0].max_distance) == (20, 800)
            assert await sys_status_bits(gcs) == (True, True, True)
            for _ in range(4):
                ds = await gcs.recv_match(type="DISTANCE_SENSOR", timeout=HANG_S)
                assert ds.orientation in (0, 4)  # never-valid faces are not sent
        finally:
            streaming.cancel()
        last = sim.engine.proximity.last_update_s
        assert last is not None
        # the companion stops: unhealthy 0.5 s (simulated) after the last message, not before
        t_bad = await watch.first(lambda s: s.engine.proximity.status(s.t_s) is not ProximityStatus.GOOD, within_s=3.0)
        assert PROXIMITY_TIMEOUT_S < t_bad - last <= PROXIMITY_TIMEOUT_S + sim.engine.dt + 1e-9
        await drain(gcs)
        await gcs.recv_match(type="SYS_STATUS", timeout=HANG_S)  # may have been built before t_bad
        assert await sys_status_bits(gcs) == (True, True, False)
        await drain(gcs)
        with pytest.raises(LinkTimeout):  # NoData: no DISTANCE_SENSOR at all
            await gcs.recv_match(type="DISTANCE_SENSOR", timeout=1.0)


async def stream(sim: Any, link: MavlinkLink, distances: list[int]) -> None:
    """OBSTACLE_DISTANCE every 0.1 s of simulated time until cancelled."""
    while True:
        link.send(obstacle_distance(link.mav, distances))
        await wait_sim_time(sim, sim.t_s + 0.1)


async def test_reboot_refused_while_armed_unless_forced() -> None:
    """GCS_Common.cpp handle_preflight_reboot: armed -> FAILED unless y/param6 = 20190226; param1 not 1 or 3 ->
    UNSUPPORTED; 3 (bootloader) restarts like 1 on SITL."""
    async with simulator_with_client(profile="ardupilot", speedup=5.0) as (sim, gcs):
        assert (await command_long(gcs, m.MAV_CMD_PREFLIGHT_REBOOT_SHUTDOWN, 0)).result == m.MAV_RESULT_UNSUPPORTED
        assert (await command_long(gcs, m.MAV_CMD_COMPONENT_ARM_DISARM, 1)).result == ACCEPTED
        ack = await command_long(gcs, m.MAV_CMD_PREFLIGHT_REBOOT_SHUTDOWN, 1)
        assert ack.result == m.MAV_RESULT_FAILED and sim.vehicle.armed and sim.engine.boot.reboots == 0
        ack = await command_long(gcs, m.MAV_CMD_PREFLIGHT_REBOOT_SHUTDOWN, 3, 0, 0, 0, 0, FORCE_REBOOT)
        assert ack.result == ACCEPTED
        assert not sim.vehicle.armed and sim.engine.boot.reboots == 1
        with pytest.raises(LinkTimeout):  # down, then booting: commands are not read
            await command_long(gcs, m.MAV_CMD_COMPONENT_ARM_DISARM, 1, timeout=0.05)
    async with simulator_with_client(profile="px4", speedup=5.0) as (_sim, gcs):
        ack = await command_long(gcs, m.MAV_CMD_PREFLIGHT_REBOOT_SHUTDOWN, 1)
        assert ack.result == m.MAV_RESULT_UNSUPPORTED  # not modelled for PX4


@pytest.mark.parametrize(("profile", "dropped"), [("ardupilot", True), ("px4", False)])
async def test_packets_with_the_autopilots_own_ids(profile: str, dropped: bool) -> None:
    """MAVLink_routing.cpp: a packet from the autopilot's own sysid/compid is "loopback of our own messages" and is
    not processed: a sensor that poses as 1/1 never gets its stream requests answered."""
    async with simulator_with_client(profile=profile, source_system=1, source_component=1, speedup=5.0) as (
        sim,
        gcs,
    ):
        if dropped:
            with pytest.raises(LinkTimeout):
                await command_long(gcs, m.MAV_CMD_SET_MESSAGE_INTERVAL, m.MAVLINK_MSG_ID_ATTITUDE, 50_000)
            assert sim.engine.own_id_drops >= 1
        else:
            ack = await command_long(gcs, m.MAV_CMD_SET_MESSAGE_INTERVAL, m.MAVLINK_MSG_ID_ATTITUDE, 50_000)
            assert ack.result == ACCEPTED and sim.engine.own_id_drops == 0
