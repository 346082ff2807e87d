"""Setpoints over loopback: every frame and type_mask combination, the GUIDED velocity timeout, the PX4 OFFBOARD
start rule and COM_OF_LOSS_T failsafe, global setpoints, collisions.

States that last only a while (a velocity until GUID_TIMEOUT) are observed after every physics step
(``StepWatch``), and setpoint streams are sent on simulated time from the same hook, so a loaded machine
cannot make the test look too late or send too seldom.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np
import pytest
from pymavlink.dialects.v20 import ardupilotmega as m

from apf_companion.autopilot import (
    MASK_ACCELERATION,
    MASK_POS_VEL,
    MASK_POS_VEL_ACCEL,
    MASK_POS_VEL_YAW,
    MASK_POSITION,
    MASK_POSITION_YAW,
    MASK_VELOCITY,
    POS_IGNORE,
    PX4_HOLD,
    PX4_OFFBOARD,
    VEL_IGNORE,
)
from apf_companion.links import MavlinkLink
from sim.vehicle import Simulator, SpawnConfig
from sim.vehicle.testing import command_long, simulator_with_client
from sim.world import World
from tests.conftest import HANG_S, StepWatch, wait_for, wait_sim_time

MASK_VEL_ACCEL = 0x0C07  # velocity + acceleration, no yaw
MASK_VEL_YAW_RATE = 0x05C7  # velocity + yaw rate
ARDU = {"WP_YAW_BEHAVIOR": 0.0}  # keep the heading fixed so body frames are checkable
# ArduCopter echoes its GUIDED submode's mask, not the one sent (GCS_MAVLink_Copter.cpp send_position_target_local_ned)
ECHO_VEL_ACCEL = 0x0C07  # VelAccel: position and yaw ignored


def ardu_echo(mask: int) -> int:
    """The POSITION_TARGET_LOCAL_NED type_mask ArduCopter reports for an accepted ``mask``."""
    pos, vel = mask & POS_IGNORE == 0, mask & VEL_IGNORE == 0
    if pos:
        return MASK_POS_VEL_ACCEL if vel else MASK_POSITION
    return ECHO_VEL_ACCEL if vel else MASK_ACCELERATION


def sp_local(
    link: MavlinkLink,
    frame: int,
    mask: int,
    pos: tuple[float, float, float] = (0.0, 0.0, 0.0),
    vel: tuple[float, float, float] = (0.0, 0.0, 0.0),
    acc: tuple[float, float, float] = (0.0, 0.0, 0.0),
    yaw: float = 0.0,
    yaw_rate: float = 0.0,
    target: tuple[int, int] = (1, 1),
) -> None:
    link.send(
        link.mav.set_position_target_local_ned_encode(
            0, target[0], target[1], frame, mask, *pos, *vel, *acc, yaw, yaw_rate
        )
    )


async def echo(link: MavlinkLink, mask: int) -> Any:
    return await link.recv_match(
        type="POSITION_TARGET_LOCAL_NED", condition=lambda e: e.type_mask == mask, timeout=HANG_S
    )


async def texts_until(link: MavlinkLink, needle: str) -> str:
    msg = await link.recv_match(type="STATUSTEXT", condition=lambda t: needle in t.text, timeout=HANG_S)
    return str(msg.text)


@pytest.mark.parametrize(
    ("frame", "pos_in", "expected"),
    [
        (m.MAV_FRAME_LOCAL_NED, (3.0, 4.0, -6.0), (3.0, 4.0, -6.0)),
        (m.MAV_FRAME_LOCAL_OFFSET_NED, (1.0, 1.0, 0.0), (1.0 + 1.0, 2.0 + 1.0, -5.0)),
        # heading 90 deg (east): body forward 2 m = east 2 m; positions are offsets from the vehicle
        (m.MAV_FRAME_BODY_NED, (2.0, 0.0, -1.0), (1.0, 2.0 + 2.0, -6.0)),
        (m.MAV_FRAME_BODY_OFFSET_NED, (0.0, 1.0, 0.0), (1.0 - 1.0, 2.0, -5.0)),
    ],
)
async def test_position_frames(
    frame: int, pos_in: tuple[float, float, float], expected: tuple[float, float, float]
) -> None:
    spawn = SpawnConfig(pos_ne_m=(1.0, 2.0), yaw_deg=90.0, airborne=True, alt_m=5.0)
    async with simulator_with_client(spawn=spawn, params=ARDU, speedup=10.0) as (sim, gcs):
        sp_local(gcs, frame, MASK_POSITION, pos=pos_in)
        e = await echo(gcs, MASK_POSITION)
        assert e.coordinate_frame == m.MAV_FRAME_LOCAL_NED
        np.testing.assert_allclose([e.x, e.y, e.z], expected, atol=1e-4)
        await wait_for(sim, lambda s: bool(np.allclose(s.vehicle.pos_ned_m, expected, atol=0.05)))


async def test_body_frame_velocity_and_yaw_are_heading_relative() -> None:
    spawn = SpawnConfig(yaw_deg=90.0, airborne=True)
    async with simulator_with_client(spawn=spawn, params=ARDU, speedup=10.0) as (sim, gcs):
        watch = StepWatch(sim, lambda s: s.vehicle.vel_ned_m_s.copy())
        sp_local(gcs, m.MAV_FRAME_BODY_NED, MASK_VELOCITY, vel=(1.0, 0.0, 0.0))
        e = await echo(gcs, ECHO_VEL_ACCEL)
        np.testing.assert_allclose([e.vx, e.vy, e.vz], [0.0, 1.0, 0.0], atol=1e-6)
        t_s = await watch.first(lambda s: abs(s.vehicle.vel_ned_m_s[1] - 1.0) < 0.02, within_s=3.0)
        assert abs(watch.sample_at(t_s)[0]) < 0.02
        # yaw in a body frame is relative to the current heading: +90 deg from east = south
        sp_local(gcs, m.MAV_FRAME_BODY_NED, MASK_POSITION_YAW, pos=(0.0, 0.0, 0.0), yaw=math.pi / 2)
        e = await echo(gcs, MASK_POSITION)
        assert e.yaw == 0.0  # ArduCopter does not echo the yaw target
        await wait_for(sim, lambda s: abs(abs(s.vehicle.yaw_rad) - math.pi) < 0.02)


@pytest.mark.parametrize(
    ("mask", "check"),
    [
        (MASK_POSITION, "pos"),
        (MASK_VELOCITY, "vel"),
        (MASK_ACCELERATION, "acc"),
        (MASK_POS_VEL, "pos"),
        (MASK_POS_VEL_ACCEL, "pos"),
        (MASK_VEL_ACCEL, "vel"),
        (MASK_POS_VEL_YAW, "yaw"),
        (MASK_POSITION_YAW, "yaw"),
        (MASK_VEL_YAW_RATE, "yaw_rate"),
    ],
)
async def test_accepted_type_masks(mask: int, check: str) -> None:
    spawn = SpawnConfig(airborne=True, alt_m=5.0)
    async with simulator_with_client(spawn=spawn, params=ARDU, speedup=10.0) as (sim, gcs):
        watch = StepWatch(sim, lambda s: None)
        pos, vel, acc = (4.0, 0.0, -5.0), (0.5, 0.0, 0.0), (0.5, 0.0, 0.0)
        if check == "vel":
            vel = (1.0, 0.0, 0.0)
        sp_local(gcs, m.MAV_FRAME_LOCAL_NED, mask, pos=pos, vel=vel, acc=acc, yaw=1.0, yaw_rate=0.5)
        await echo(gcs, ardu_echo(mask))
        assert not any("ignored" in t.text for t in sim.engine.statustexts)
        if check == "pos":
            await wait_for(sim, lambda s: s.vehicle.pos_ned_m[0] > 3.0)
        elif check == "vel":  # until GUID_TIMEOUT (3 s)
            await watch.first(lambda s: abs(s.vehicle.vel_ned_m_s[0] - 1.0) < 0.02, within_s=3.0)
        elif check == "acc":
            await watch.first(lambda s: s.vehicle.vel_ned_m_s[0] > 0.5, within_s=3.0)  # accelerating north
        elif check == "yaw":
            await wait_for(sim, lambda s: abs(s.vehicle.yaw_rad - 1.0) < 0.01)
        else:
            await wait_for(sim, lambda s: s.vehicle.yaw_rad > 1.0)


@pytest.mark.parametrize(
    "mask",
    [
        0x0DF9,  # x ignored only: any bit ignores the group; nothing left
        0x0DCF,  # position ignored, vx ignored
        0x09FF,  # yaw alone
        0x05FF,  # yaw rate alone
        0x0C38,  # position+acceleration
        0x0E3F,  # FORCE with an acceleration
        0x0FFF,
        0xFFFF,
    ],
)
async def test_invalid_type_masks_stop_the_vehicle_ardupilot(mask: int) -> None:
    """GCS_MAVLink_Copter.cpp: "input is not valid so stop" (mode_guided.init): no STATUSTEXT, the vehicle
    decelerates and holds, echoed as the velocity submode (0x0C07)."""
    async with simulator_with_client(spawn=SpawnConfig(airborne=True), speedup=10.0) as (sim, gcs):
        sp_local(gcs, m.MAV_FRAME_LOCAL_NED, MASK_POSITION, pos=(20.0, 0.0, -5.0))
        await echo(gcs, MASK_POSITION)
        await wait_for(sim, lambda s: s.vehicle.vel_ned_m_s[0] > 2.0)
        sp_local(gcs, m.MAV_FRAME_LOCAL_NED, mask, pos=(9.0, 9.0, -9.0), vel=(1.0, 1.0, 1.0), acc=(1.0, 1.0, 1.0))
        await echo(gcs, ECHO_VEL_ACCEL)
        await wait_for(sim, lambda s: float(np.linalg.norm(s.vehicle.vel_ned_m_s)) < 0.05)
        x_stop = sim.vehicle.pos_ned_m[0]
        assert 1.0 < x_stop < 12.0  # stopped on the way, not at the old target (20 m)
        await wait_sim_time(sim, sim.t_s + 4.0)  # and holds there (past GUID_TIMEOUT)
        assert abs(sim.vehicle.pos_ned_m[0] - x_stop) < 0.3
        assert not any("ignored" in t.text for t in sim.engine.statustexts)


async def test_invalid_frame_stops_and_non_finite_is_ignored_ardupilot() -> None:
    async with simulator_with_client(spawn=SpawnConfig(airborne=True), speedup=10.0) as (sim, gcs):
        sp_local(gcs, m.MAV_FRAME_LOCAL_NED, MASK_POSITION, pos=(3.0, 0.0, -5.0))
        await echo(gcs, MASK_POSITION)
        sp_local(gcs, m.MAV_FRAME_GLOBAL, MASK_POSITION, pos=(1.0, 1.0, -5.0))  # frame 0: stop, silently
        await echo(gcs, ECHO_VEL_ACCEL)
        assert not any("frame" in t.text for t in sim.engine.statustexts)
        sp_local(gcs, m.MAV_FRAME_LOCAL_NED, MASK_POSITION, pos=(math.nan, 1.0, -5.0))
        assert await texts_until(gcs, "finite") == "Setpoint ignored: not finite"
        await wait_for(sim, lambda s: float(np.linalg.norm(s.vehicle.vel_ned_m_s)) < 0.05)
        assert sim.vehicle.pos_ned_m[0] < 2.9  # stopped short of the position target


async def test_setpoints_outside_guided_are_ignored_ardupilot() -> None:
    spawn = SpawnConfig(airborne=True, mode="LOITER")
    async with simulator_with_client(spawn=spawn, speedup=10.0) as (sim, gcs):
        for _ in range(5):
            sp_local(gcs, m.MAV_FRAME_LOCAL_NED, MASK_VELOCITY, vel=(2.0, 0.0, 0.0))
        await wait_sim_time(sim, sim.t_s + 1.0)
        assert abs(sim.vehicle.vel_ned_m_s[0]) < 1e-6 and sim.vehicle.mode == "LOITER"


async def test_global_int_setpoint() -> None:
    async with simulator_with_client(spawn=SpawnConfig(airborne=True), speedup=10.0) as (sim, gcs):
        # 10 m north, 5 m east of home (flat earth at the home latitude), 7 m above home
        lat0, lon0 = -35.363262, 149.165237
        dlat = math.degrees(10.0 / 6378137.0)
        dlon = math.degrees(5.0 / (6378137.0 * math.cos(math.radians(lat0))))
        gcs.send(
            gcs.mav.set_position_target_global_int_encode(
                0, 1, 1, m.MAV_FRAME_GLOBAL_RELATIVE_ALT_INT, MASK_POSITION,
                round((lat0 + dlat) * 1e7), round((lon0 + dlon) * 1e7), 7.0, 0, 0, 0, 0, 0, 0, 0, 0,
            )
        )  # fmt: skip
        e = await echo(gcs, MASK_POSITION)
        np.testing.assert_allclose([e.x, e.y, e.z], [10.0, 5.0, -7.0], atol=0.02)
        # wait until the vehicle has settled (GLOBAL_POSITION_INT is checked to 3e-7 deg, about 3 cm)
        await wait_for(sim, lambda s: bool(np.allclose(s.vehicle.pos_ned_m, [10.0, 5.0, -7.0], atol=0.01)))
        t_ms = round(sim.t_s * 1000)
        gpi = await gcs.recv_match(
            type="GLOBAL_POSITION_INT", condition=lambda g: g.time_boot_ms >= t_ms, timeout=HANG_S
        )
        assert gpi.lat == pytest.approx((lat0 + dlat) * 1e7, abs=3)
        assert gpi.lon == pytest.approx((lon0 + dlon) * 1e7, abs=3)
        assert gpi.relative_alt == pytest.approx(7000, abs=60)
        assert gpi.alt == pytest.approx(584000 + 7000, abs=60)


async def test_guided_velocity_timeout_and_position_held() -> None:
    async with simulator_with_client(spawn=SpawnConfig(airborne=True), params={"GUID_TIMEOUT": 3.0}) as (sim, gcs):
        watch = StepWatch(sim, lambda s: (s.vehicle.vel_ned_m_s.copy(), s.vehicle.pos_ned_m.copy()))
        sp_local(gcs, m.MAV_FRAME_LOCAL_NED, MASK_VELOCITY, vel=(1.0, 0.0, 0.0))
        await echo(gcs, ECHO_VEL_ACCEL)
        t_rx = sim.engine.last_setpoint_t_s
        assert t_rx is not None
        await wait_sim_time(sim, t_rx + 3.0 + 1.5)
        vel, _ = watch.sample_at(t_rx + 2.9)
        assert vel[0] == pytest.approx(1.0, abs=0.02)  # still flying at 1 m/s
        vel, pos = watch.sample_at(t_rx + 3.0 + 1.5)
        assert abs(vel[0]) < 0.02  # stopped after GUID_TIMEOUT
        stop_n = float(pos[0])
        assert 2.5 < stop_n < 3.5
        # a position target is held indefinitely
        sp_local(gcs, m.MAV_FRAME_LOCAL_NED, MASK_POSITION, pos=(0.0, 2.0, -5.0))
        await echo(gcs, MASK_POSITION)
        t_rx = sim.engine.last_setpoint_t_s
        assert t_rx is not None
        await wait_sim_time(sim, t_rx + 12.0)
        np.testing.assert_allclose(sim.vehicle.pos_ned_m, [0.0, 2.0, -5.0], atol=0.02)
        assert sim.vehicle.mode == "GUIDED"


async def test_guided_timeout_follows_param() -> None:
    async with simulator_with_client(spawn=SpawnConfig(airborne=True), params={"GUID_TIMEOUT": 1.0}) as (sim, gcs):
        watch = StepWatch(sim, lambda s: s.vehicle.vel_ned_m_s.copy())
        sp_local(gcs, m.MAV_FRAME_LOCAL_NED, MASK_VELOCITY, vel=(0.0, 1.0, 0.0))
        await echo(gcs, ECHO_VEL_ACCEL)
        t_rx = sim.engine.last_setpoint_t_s
        assert t_rx is not None
        await wait_sim_time(sim, t_rx + 2.5)
        assert watch.sample_at(t_rx + 0.9)[1] > 0.8
        assert abs(watch.sample_at(t_rx + 2.5)[1]) < 0.02


async def stream(sim: Simulator, gcs: MavlinkLink, rate_hz: float, until_t_s: float) -> None:
    """Send a hover setpoint at ``rate_hz`` of simulated time until ``until_t_s`` (sent from the physics step)."""
    next_t = [sim.t_s]

    def send(s: Simulator) -> None:
        if next_t[0] <= s.t_s < until_t_s:
            sp_local(gcs, m.MAV_FRAME_LOCAL_NED, MASK_POSITION, pos=(0.0, 0.0, -5.0))
            next_t[0] += 1.0 / rate_hz

    send(sim)
    await StepWatch(sim, send).first(lambda s: s.t_s >= until_t_s, within_s=until_t_s - sim.t_s + 1.0)


async def test_px4_offboard_needs_a_setpoint_newer_than_com_of_loss_t() -> None:
    """offboardCheck.cpp: OFFBOARD is available while the last setpoint is newer than COM_OF_LOSS_T (no pre-stream)."""
    async with simulator_with_client(profile="px4", spawn=SpawnConfig(airborne=True), speedup=4.0) as (sim, gcs):
        texts: list[str] = []
        ack = await command_long(gcs, m.MAV_CMD_DO_SET_MODE, 1, 6, texts=texts)  # no setpoint yet
        assert ack.result == m.MAV_RESULT_TEMPORARILY_REJECTED
        assert "Switching to Offboard is currently not available" in texts
        sp_local(gcs, m.MAV_FRAME_LOCAL_NED, MASK_POSITION, pos=(0.0, 0.0, -5.0))
        await wait_for(sim, lambda s: s.engine.last_setpoint_t_s is not None)
        last = sim.engine.last_setpoint_t_s
        assert last is not None
        await wait_sim_time(sim, last + 1.1)  # COM_OF_LOSS_T = 1 s: stale
        assert (await command_long(gcs, m.MAV_CMD_DO_SET_MODE, 1, 6)).result == m.MAV_RESULT_TEMPORARILY_REJECTED
        sp_local(gcs, m.MAV_FRAME_LOCAL_NED, MASK_POSITION, pos=(0.0, 0.0, -5.0))  # one fresh setpoint is enough
        ack = await command_long(gcs, m.MAV_CMD_DO_SET_MODE, 1, 6)
        assert ack.result == m.MAV_RESULT_ACCEPTED
        assert sim.vehicle.custom_mode == PX4_OFFBOARD.to_custom_mode()


async def test_px4_offboard_loss_failsafe() -> None:
    async with simulator_with_client(profile="px4", spawn=SpawnConfig(airborne=True), speedup=4.0) as (sim, gcs):
        await stream(sim, gcs, 10.0, sim.t_s + 1.2)
        assert (await command_long(gcs, m.MAV_CMD_DO_SET_MODE, 1, 6)).result == m.MAV_RESULT_ACCEPTED
        assert sim.vehicle.mode == "OFFBOARD"
        sp_local(gcs, m.MAV_FRAME_LOCAL_NED, MASK_VELOCITY, vel=(1.0, 0.0, 0.0))
        await echo(gcs, MASK_VELOCITY)
        assert sim.vehicle.mode == "OFFBOARD"
        last = sim.engine.last_setpoint_t_s
        assert last is not None
        text = await texts_until(gcs, "Failsafe")
        assert text == "Failsafe: offboard signal lost, Hold"
        hb = await gcs.recv_match(type="HEARTBEAT", condition=lambda h: h.custom_mode != 6 << 16, timeout=HANG_S)
        assert hb.custom_mode == PX4_HOLD.to_custom_mode()
        assert hb.system_status == m.MAV_STATE_CRITICAL
        t_fs = next(s.t_s for s in sim.engine.statustexts if s.text.startswith("Failsafe"))
        assert 1.0 < t_fs - last <= 1.0 + 2 * sim.engine.dt  # COM_OF_LOSS_T = 1 s
        await wait_for(sim, lambda s: float(np.hypot(*s.vehicle.vel_ned_m_s[:2])) < 0.01)  # holds


async def test_px4_spawn_in_offboard_needs_the_stream_at_once() -> None:
    spawn = SpawnConfig(airborne=True, mode="OFFBOARD")
    async with simulator_with_client(profile="px4", spawn=spawn, speedup=10.0) as (sim, gcs):
        # nobody streams: the spawn's pretend stream ended at t = -0.1 s, so the failsafe fires at t = 0.9 s
        await texts_until(gcs, "Failsafe")
        assert sim.vehicle.mode == "AUTO.LOITER"
        t_fs = next(s.t_s for s in sim.engine.statustexts if s.text.startswith("Failsafe"))
        assert t_fs == pytest.approx(0.9, abs=2 * sim.engine.dt)


async def test_px4_setpoints_after_the_offboard_loss_failsafe_return_to_offboard() -> None:
    """src/modules/commander/failsafe/failsafe.cpp ``checkModeFallback``: the offboard-loss action is a mode
    fallback that keeps the user's intended mode (OFFBOARD) and clears with its condition, so a setpoint after the
    failsafe puts PX4 back into OFFBOARD by itself, with no mode request; the failsafe's CRITICAL ends."""
    spawn = SpawnConfig(airborne=True, mode="OFFBOARD")
    async with simulator_with_client(profile="px4", spawn=spawn, speedup=10.0) as (_sim, gcs):
        await texts_until(gcs, "Failsafe")
        hb = await gcs.recv_match(type="HEARTBEAT", condition=lambda h: h.custom_mode != 6 << 16, timeout=HANG_S)
        assert hb.custom_mode == PX4_HOLD.to_custom_mode() and hb.system_status == m.MAV_STATE_CRITICAL
        sp_local(gcs, m.MAV_FRAME_LOCAL_NED, MASK_POSITION, pos=(0.0, 0.0, -5.0))
        hb = await gcs.recv_match(type="HEARTBEAT", condition=lambda h: h.custom_mode == 6 << 16, timeout=HANG_S)
        assert hb.system_status == m.MAV_STATE_ACTIVE


async def test_px4_a_mode_change_after_the_offboard_loss_failsafe_keeps_setpoints_from_returning() -> None:
    """The pilot's mode request ends the fallback (the user's intended mode is no longer OFFBOARD), even one for the
    failsafe's own Hold: setpoints then leave the vehicle in the pilot's mode."""
    spawn = SpawnConfig(airborne=True, mode="OFFBOARD")
    async with simulator_with_client(profile="px4", spawn=spawn, speedup=10.0) as (sim, gcs):
        await texts_until(gcs, "Failsafe")
        ack = await command_long(gcs, m.MAV_CMD_DO_SET_MODE, 1, PX4_HOLD.main, PX4_HOLD.sub)
        assert ack.result == m.MAV_RESULT_ACCEPTED and sim.vehicle.mode == "AUTO.LOITER"
        before = sim.engine.last_setpoint_t_s  # the spawn's pretend stream
        sp_local(gcs, m.MAV_FRAME_LOCAL_NED, MASK_POSITION, pos=(0.0, 0.0, -5.0))
        await wait_for(sim, lambda s: s.engine.last_setpoint_t_s != before)
        last = sim.engine.last_setpoint_t_s
        assert last is not None
        await wait_sim_time(sim, last + 0.5)  # well inside COM_OF_LOSS_T: the offboard signal is there
        assert sim.vehicle.mode == "AUTO.LOITER"


async def test_px4_offboard_takes_off_from_the_ground() -> None:
    async with simulator_with_client(profile="px4", speedup=4.0) as (sim, gcs):
        t0 = sim.t_s
        await stream(sim, gcs, 10.0, t0 + 1.2)
        assert (await command_long(gcs, m.MAV_CMD_DO_SET_MODE, 1, 6)).result == m.MAV_RESULT_ACCEPTED
        assert (await command_long(gcs, m.MAV_CMD_COMPONENT_ARM_DISARM, 1)).result == m.MAV_RESULT_ACCEPTED
        await stream(sim, gcs, 10.0, sim.t_s + 6.0)
        assert sim.vehicle.pos_ned_m[2] == pytest.approx(-5.0, abs=0.1)


async def test_collision_crashes_and_freezes() -> None:
    world = World.from_obstacles([[5.0, 0.0]], 0.5)
    async with simulator_with_client(world=world, spawn=SpawnConfig(airborne=True), speedup=10.0) as (sim, gcs):
        sp_local(gcs, m.MAV_FRAME_LOCAL_NED, MASK_POSITION, pos=(10.0, 0.0, -5.0))
        text = await texts_until(gcs, "Crash")
        assert text.startswith("Crash: hit cylinder 0 clearance 0.2")
        hb = await gcs.recv_match(type="HEARTBEAT", timeout=HANG_S)
        assert hb.system_status == m.MAV_STATE_EMERGENCY
        assert not hb.base_mode & m.MAV_MODE_FLAG_SAFETY_ARMED
        res = sim.result()
        assert res["collided"] and res["crashed"]
        assert res["crashed_at"]["obstacle_id"] == 0
        assert res["crashed_at"]["pos_ned_m"][0] == pytest.approx(5.0 - 0.5 - 0.25, abs=0.06)
        assert res["min_clearance_m"] < 0.25
        frozen = sim.vehicle.pos_ned_m.copy()
        await wait_sim_time(sim, sim.t_s + 1.0)
        np.testing.assert_array_equal(sim.vehicle.pos_ned_m, frozen)
        ack = await command_long(gcs, m.MAV_CMD_COMPONENT_ARM_DISARM, 1)
        assert ack.result == m.MAV_RESULT_FAILED
