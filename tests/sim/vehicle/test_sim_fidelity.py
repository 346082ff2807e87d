"""Protocol rules copied from the real autopilots (issue 8), over loopback UDP with a pymavlink client.

Each test names the source file the rule was checked against (docs/simulator.md has the table).
"""

from __future__ import annotations

import math

import numpy as np
import pytest
from pymavlink.dialects.v20 import ardupilotmega as m

from apf_companion.autopilot import MASK_POSITION, MASK_VELOCITY, CopterMode
from apf_companion.links import MavlinkLink
from sim.vehicle import SpawnConfig
from sim.vehicle.testing import angle_close, command_int, command_long, simulator_with_client, wait_for

NAN = math.nan
ACCEPTED = m.MAV_RESULT_ACCEPTED
PROFILES = ["ardupilot", "px4"]


Vec3 = tuple[float, float, float]
ZERO: Vec3 = (0.0, 0.0, 0.0)


def sp_local(link: MavlinkLink, frame: int, mask: int, *, pos: Vec3 = ZERO, vel: Vec3 = ZERO, acc: Vec3 = ZERO) -> None:
    link.send(link.mav.set_position_target_local_ned_encode(0, 1, 1, frame, mask, *pos, *vel, *acc, 0.0, 0.0))


@pytest.mark.parametrize("profile", PROFILES)
async def test_nan_params_mean_unused(profile: str) -> None:
    """MAVLink: NaN = unused. MAVSDK's action.arm() sends param2 = NaN; round(NaN) used to kill the simulator."""
    async with simulator_with_client(profile=profile, speedup=10.0) as (sim, gcs):
        ack = await command_long(gcs, m.MAV_CMD_COMPONENT_ARM_DISARM, 1, NAN, NAN, NAN, NAN, NAN, NAN)
        assert ack.result == ACCEPTED and sim.vehicle.armed
        ack = await command_long(gcs, m.MAV_CMD_DO_SET_MODE, NAN, NAN, NAN)  # no custom-mode flag: refused
        assert ack.result in (m.MAV_RESULT_UNSUPPORTED, m.MAV_RESULT_DENIED)
        ack = await command_long(gcs, m.MAV_CMD_SET_MESSAGE_INTERVAL, NAN, NAN)
        assert ack.result in (m.MAV_RESULT_DENIED, m.MAV_RESULT_FAILED)
        ack = await command_long(gcs, m.MAV_CMD_SET_MESSAGE_INTERVAL, m.MAVLINK_MSG_ID_ATTITUDE, NAN)  # = default
        assert ack.result == ACCEPTED
        assert (await command_long(gcs, m.MAV_CMD_REQUEST_MESSAGE, NAN)).result == m.MAV_RESULT_FAILED
        ack = await command_long(gcs, m.MAV_CMD_COMPONENT_ARM_DISARM, 0, NAN)
        assert ack.result == ACCEPTED and not sim.vehicle.armed
        await gcs.recv_match(type="HEARTBEAT", timeout=3.0)  # still alive
        assert sim.error is None


@pytest.mark.parametrize(("profile", "result"), [("ardupilot", m.MAV_RESULT_DENIED), ("px4", m.MAV_RESULT_FAILED)])
async def test_message_interval_for_an_unknown_id(profile: str, result: int) -> None:
    """ArduPilot GCS_Common.cpp set_message_interval: no ap_message -> DENIED; PX4 mavlink_receiver.cpp: FAILED."""
    async with simulator_with_client(profile=profile, speedup=10.0) as (_sim, gcs):
        assert (await command_long(gcs, m.MAV_CMD_SET_MESSAGE_INTERVAL, 12345, 100_000)).result == result


@pytest.mark.parametrize("profile", PROFILES)
async def test_gps_raw_int_on_request(profile: str) -> None:
    async with simulator_with_client(profile=profile, spawn=SpawnConfig(pos_ne_m=(10.0, 0.0)), speedup=10.0) as (
        _sim,
        gcs,
    ):
        ack = await command_long(gcs, m.MAV_CMD_SET_MESSAGE_INTERVAL, m.MAVLINK_MSG_ID_GPS_RAW_INT, 200_000)
        assert ack.result == ACCEPTED
        gps = await gcs.recv_match(type="GPS_RAW_INT", timeout=3.0)
        assert gps.fix_type >= m.GPS_FIX_TYPE_3D_FIX and gps.satellites_visible >= 8  # MAVSDK's "GPS ok"
        gpi = await gcs.recv_match(type="GLOBAL_POSITION_INT", timeout=3.0)
        assert (gps.lat, gps.lon) == (gpi.lat, gpi.lon)
        assert gps.lat > -353632620  # 10 m north of home


async def test_sys_status_geofence_and_prearm_bits() -> None:
    """ArduPilot GCS.cpp update_sensor_status_flags: geofence healthy unless breached (MAVProxy says "fence breach"
    when the bit drops); PREARM_CHECK healthy when armed or when arming would pass."""
    fence, prearm = m.MAV_SYS_STATUS_GEOFENCE, m.MAV_SYS_STATUS_PREARM_CHECK
    async with simulator_with_client(profile="ardupilot", speedup=10.0) as (_sim, gcs):
        st = await gcs.recv_match(type="SYS_STATUS", timeout=3.0)
        assert st.onboard_control_sensors_health & fence
        assert st.onboard_control_sensors_present & prearm and st.onboard_control_sensors_health & prearm
        assert (await command_long(gcs, m.MAV_CMD_DO_SET_MODE, 1, CopterMode.LAND)).result == ACCEPTED
        st = await gcs.recv_match(
            type="SYS_STATUS", condition=lambda s: not s.onboard_control_sensors_health & prearm, timeout=3.0
        )
        assert st.onboard_control_sensors_health & fence  # LAND is not armable; the fence is still fine
    async with simulator_with_client(profile="px4", speedup=10.0) as (_sim, gcs):
        st = await gcs.recv_match(type="SYS_STATUS", timeout=3.0)
        assert st.onboard_control_sensors_health & fence


@pytest.mark.parametrize("use_reposition", [False, True])
async def test_ardupilot_target_during_takeoff_ends_the_takeoff(use_reposition: bool) -> None:
    """mode_guided.cpp set_pos_NED_m / set_destination: a new target switches the submode from TakeOff to Pos; the
    vehicle flies to it instead of finishing the climb (it used to be ACKed and dropped when the takeoff ended)."""
    async with simulator_with_client(profile="ardupilot", speedup=10.0) as (sim, gcs):
        assert (await command_long(gcs, m.MAV_CMD_DO_SET_MODE, 1, CopterMode.GUIDED)).result == ACCEPTED
        assert (await command_long(gcs, m.MAV_CMD_COMPONENT_ARM_DISARM, 1)).result == ACCEPTED
        assert (await command_long(gcs, m.MAV_CMD_NAV_TAKEOFF, 0, 0, 0, 0, 0, 0, 10.0)).result == ACCEPTED
        await wait_for(sim, lambda s: s.vehicle.pos_ned_m[2] < -1.5)
        if use_reposition:
            lat = round((-35.363262 + math.degrees(6.0 / 6378137.0)) * 1e7)
            ack = await command_int(
                gcs,
                m.MAV_CMD_DO_REPOSITION,
                frame=m.MAV_FRAME_GLOBAL_RELATIVE_ALT_INT,
                params=(-1, 0, 0, 0),
                x=lat,
                y=1491652370,
                z=4.0,
            )
            assert ack.result == ACCEPTED
        else:
            sp_local(gcs, m.MAV_FRAME_LOCAL_NED, MASK_POSITION, pos=(6.0, 0.0, -4.0))
        await wait_for(sim, lambda s: bool(np.allclose(s.vehicle.pos_ned_m, [6.0, 0.0, -4.0], atol=0.05)))
        assert sim.vehicle.pos_ned_m[2] > -4.3  # never climbed on towards 10 m
        in_air = m.MAV_LANDED_STATE_IN_AIR  # no longer TAKEOFF
        await gcs.recv_match(type="EXTENDED_SYS_STATE", condition=lambda x: x.landed_state == in_air, timeout=2.0)


async def test_ardupilot_reposition_outside_guided_needs_the_flag() -> None:
    """GCS_MAVLink_Copter.cpp handle_command_int_do_reposition: not GUIDED and no CHANGE_MODE flag -> DENIED."""
    async with simulator_with_client(spawn=SpawnConfig(airborne=True, mode="LOITER"), speedup=10.0) as (sim, gcs):
        ack = await command_int(
            gcs, m.MAV_CMD_DO_REPOSITION, frame=m.MAV_FRAME_GLOBAL_RELATIVE_ALT_INT, x=-353632620, y=1491652370, z=5
        )
        assert ack.result == m.MAV_RESULT_DENIED and sim.vehicle.mode == "LOITER"


async def test_ardupilot_echoes_a_velocity_target_as_0x0c07() -> None:
    """GCS_MAVLink_Copter.cpp send_position_target_local_ned: the VelAccel submode's mask, yaw 0."""
    async with simulator_with_client(spawn=SpawnConfig(airborne=True), speedup=10.0) as (_sim, gcs):
        sp_local(gcs, m.MAV_FRAME_LOCAL_NED, MASK_VELOCITY, vel=(0.5, 0.0, 0.0))
        echo = await gcs.recv_match(type="POSITION_TARGET_LOCAL_NED", timeout=3.0)
        assert echo.type_mask == 0x0C07
        assert (echo.vx, echo.x, echo.yaw) == (0.5, 0.0, 0.0)


async def test_ardupilot_condition_yaw_turns_the_vehicle() -> None:
    """GCS_MAVLink_Copter.cpp handle_MAV_CMD_CONDITION_YAW: angle [0, 360], param4 0 absolute / 1 relative."""
    spawn = SpawnConfig(airborne=True)
    async with simulator_with_client(spawn=spawn, params={"WP_YAW_BEHAVIOR": 0.0}, speedup=10.0) as (sim, gcs):
        sp_local(gcs, m.MAV_FRAME_LOCAL_NED, MASK_POSITION, pos=(0.0, 0.0, -5.0))
        assert (await command_long(gcs, m.MAV_CMD_CONDITION_YAW, 90, 0, 1, 0)).result == ACCEPTED
        await wait_for(sim, lambda s: angle_close(s.vehicle.yaw_rad, math.pi / 2, 0.01))
        assert (await command_long(gcs, m.MAV_CMD_CONDITION_YAW, 45, 0, -1, 1)).result == ACCEPTED  # 45 deg ccw
        await wait_for(sim, lambda s: angle_close(s.vehicle.yaw_rad, math.pi / 4, 0.01))
        assert (await command_long(gcs, m.MAV_CMD_CONDITION_YAW, 400, 0, 1, 0)).result == m.MAV_RESULT_FAILED
        assert (await command_long(gcs, m.MAV_CMD_CONDITION_YAW, 10, 0, 1, 2)).result == m.MAV_RESULT_FAILED
        np.testing.assert_allclose(sim.vehicle.pos_ned_m, [0.0, 0.0, -5.0], atol=0.02)  # it turned in place
    async with simulator_with_client(profile="px4", spawn=spawn, speedup=10.0) as (_sim, gcs):
        assert (await command_long(gcs, m.MAV_CMD_CONDITION_YAW, 90, 0, 1, 0)).result == m.MAV_RESULT_UNSUPPORTED


async def test_px4_setpoint_rules() -> None:
    """PX4 mavlink_receiver.cpp handle_message_set_position_target_local_ned: LOCAL_NED / BODY_NED only, any
    position / velocity / acceleration combination (position + acceleration too), no FORCE."""
    async with simulator_with_client(profile="px4", spawn=SpawnConfig(airborne=True), speedup=4.0) as (sim, gcs):
        texts: list[str] = []

        async def text(needle: str) -> None:
            msg = await gcs.recv_match(type="STATUSTEXT", condition=lambda t: needle in t.text, timeout=3.0)
            texts.append(msg.text)

        sp_local(gcs, m.MAV_FRAME_LOCAL_OFFSET_NED, MASK_POSITION, pos=(1.0, 0.0, 0.0))
        await text("coordinate frame 7")  # "... unsupported": STATUSTEXT holds 50 characters
        sp_local(gcs, m.MAV_FRAME_LOCAL_NED, 0x0E3F, acc=(1.0, 0.0, 0.0))  # acceleration with FORCE
        await text("force not supported")
        sp_local(gcs, m.MAV_FRAME_LOCAL_NED, 0x0FFF)
        await text("SET_POSITION_TARGET_LOCAL_NED invalid")
        assert sim.engine.last_setpoint_t_s is None  # invalid setpoints are no proof of life
        # position + acceleration (ArduCopter refuses it): PX4 flies the position
        sp_local(gcs, m.MAV_FRAME_LOCAL_NED, 0x0C38, pos=(3.0, 0.0, -5.0))
        assert (await command_long(gcs, m.MAV_CMD_DO_SET_MODE, 1, 6)).result == ACCEPTED  # OFFBOARD
        for _ in range(30):
            sp_local(gcs, m.MAV_FRAME_LOCAL_NED, 0x0C38, pos=(3.0, 0.0, -5.0))
            t0_s = sim.t_s
            await wait_for(sim, lambda s: s.t_s >= t0_s + 0.1)  # noqa: B023
        assert sim.vehicle.mode == "OFFBOARD"
        assert sim.vehicle.pos_ned_m[0] > 2.0
        assert not any("type_mask" in t.text for t in sim.engine.statustexts)
