"""The pure engine on its simulated clock (no sockets): dynamics limits, repeatability, RTL, auto-disarm,
failsafe actions, reposition, the result record; and the CLI as a subprocess (result JSON on SIGTERM)."""

from __future__ import annotations

import asyncio
import json
import math
import signal
import socket
import sys
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from pymavlink.dialects.v20 import ardupilotmega as m

from apf_companion.autopilot import MASK_POS_VEL, MASK_POSITION, MASK_VELOCITY, Autopilot, CopterMode
from apf_companion.errors import ConfigError
from apf_companion.links import MavlinkLink
from apf_companion.perception import euler_yaw_rate_rad_s
from sim.vehicle import Dynamics, EngineConfig, SimConfig, Simulator, SpawnConfig, VehicleEngine
from sim.vehicle.geo import latlon_to_ne
from sim.vehicle.telemetry import build
from sim.world import World, load_world
from tests.conftest import HANG_S, free_port

GCS = m.MAVLink(None, srcSystem=255, srcComponent=190)


def wire(msg: Any) -> Any:
    """Pack and parse, as a message that crossed a link."""
    return GCS.decode(bytearray(msg.pack(GCS)))


class Rig:
    def __init__(self, **cfg: Any) -> None:
        self.out: list[tuple[int | None, Any]] = []
        self.engine = VehicleEngine(EngineConfig(**cfg), n_links=1, emit=lambda link, msg: self.out.append((link, msg)))

    def run(self, seconds: float) -> None:
        for _ in range(round(seconds / self.engine.dt)):
            self.engine.step()

    def cmd(self, command: int, *p: float) -> int:
        params = [float(x) for x in p] + [0.0] * (7 - len(p))
        self.out.clear()
        self.engine.handle(wire(GCS.command_long_encode(1, 1, command, 0, *params)), 0)
        acks = [msg.result for _, msg in self.out if msg.get_type() == "COMMAND_ACK"]
        assert len(acks) == 1
        return int(acks[0])

    def setpoint(self, mask: int, pos: tuple[float, ...] = (0, 0, 0), vel: tuple[float, ...] = (0, 0, 0)) -> None:
        msg = GCS.set_position_target_local_ned_encode(0, 1, 1, 1, mask, *pos, *vel, 0, 0, 0, 0, 0)
        self.engine.handle(wire(msg), 0)


def test_speed_and_acceleration_limits() -> None:
    rig = Rig(spawn=SpawnConfig(airborne=True), params={"WP_YAW_BEHAVIOR": 0.0})
    speeds, accels = [], []
    for i in range(600):
        if i % 100 == 0:  # re-sent every second, as GUIDED velocity control needs
            rig.setpoint(MASK_VELOCITY, vel=(20.0, 0.0, 0.0))
        rig.engine.step()
        speeds.append(float(np.hypot(*rig.engine.state.vel_ned_m_s[:2])))
        accels.append(float(np.hypot(*rig.engine.state.acc_ned_m_s2[:2])))
    assert max(speeds) <= 5.0 * 1.05 + 1e-9  # WPNAV_SPEED
    assert max(accels) <= 2.5 + 1e-9  # WPNAV_ACCEL
    assert speeds[-1] == pytest.approx(5.0, abs=0.01)


def test_position_control_does_not_overshoot() -> None:
    rig = Rig(spawn=SpawnConfig(airborne=True))
    rig.setpoint(MASK_POSITION, pos=(20.0, 0.0, -5.0))
    north = []
    for _ in range(2000):
        rig.engine.step()
        north.append(float(rig.engine.state.pos_ned_m[0]))
    assert max(north) <= 20.0 + 0.05
    assert north[-1] == pytest.approx(20.0, abs=0.01)
    res = rig.engine.result()
    assert res["path_length_m"] == pytest.approx(20.0, abs=0.1)


def test_same_seed_same_flight_with_actuation_noise() -> None:
    def fly(seed: int) -> np.ndarray:
        rig = Rig(spawn=SpawnConfig(airborne=True), seed=seed, params={"SIM_POS_NOISE": 0.1})
        rig.setpoint(MASK_POSITION, pos=(10.0, 5.0, -5.0))
        rig.run(8.0)
        return np.array(rig.engine.trajectory_ned_m)

    a, b, c = fly(3), fly(3), fly(4)
    np.testing.assert_array_equal(a, b)
    assert not np.array_equal(a, c)
    quiet = Rig(spawn=SpawnConfig(airborne=True))
    quiet.setpoint(MASK_POSITION, pos=(10.0, 5.0, -5.0))
    quiet.run(8.0)
    dev = np.abs(a[-30:, :2] - np.array(quiet.engine.trajectory_ned_m)[-30:, :2])
    assert 0.005 < dev.max() < 1.0  # noisy, but the controller keeps it near the target


def test_rtl_returns_home_and_lands() -> None:
    rig = Rig(spawn=SpawnConfig(pos_ne_m=(10.0, 10.0), airborne=True, alt_m=5.0))
    assert rig.cmd(m.MAV_CMD_NAV_RETURN_TO_LAUNCH) == m.MAV_RESULT_ACCEPTED
    rig.run(8.0)
    assert rig.engine.state.alt_m > 10.0  # climbs towards RTL_ALT (15 m) first
    rig.run(60.0)
    snap = rig.engine.snapshot()
    assert snap.on_ground and not snap.armed and snap.mode == "RTL"
    np.testing.assert_allclose(snap.pos_ned_m, [0.0, 0.0, 0.0], atol=0.1)


def test_auto_disarm_when_left_on_the_ground() -> None:
    rig = Rig()
    assert rig.cmd(m.MAV_CMD_COMPONENT_ARM_DISARM, 1) == m.MAV_RESULT_ACCEPTED
    rig.run(9.9)
    assert rig.engine.armed
    rig.run(0.2)
    assert not rig.engine.armed
    assert rig.engine.statustexts[-1].text == "Auto disarm: landed"


def test_a_takeoff_late_in_the_disarm_delay_is_not_disarmed() -> None:
    """ArduCopter restarts the landed-disarm timer while the motors spool for a takeoff (motors.cpp
    auto_disarm_check): NAV_TAKEOFF accepted 9.5 s after arming (DISARM_DELAY 10 s) climbs, it is not disarmed;
    left on the ground without one, the same vehicle is disarmed at 10 s (the test above)."""
    rig = Rig(dynamics=Dynamics.ARDUCOPTER)  # its spool-up keeps the vehicle on the ground for a while
    while not rig.engine.startup.origin_set:  # GUIDED needs the EKF origin
        rig.run(0.5)
    guided = rig.cmd(m.MAV_CMD_DO_SET_MODE, m.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED, CopterMode.GUIDED)
    assert guided == m.MAV_RESULT_ACCEPTED
    assert rig.cmd(m.MAV_CMD_COMPONENT_ARM_DISARM, 1) == m.MAV_RESULT_ACCEPTED
    rig.run(9.5)
    assert rig.cmd(m.MAV_CMD_NAV_TAKEOFF, 0, 0, 0, 0, 0, 0, 5.0) == m.MAV_RESULT_ACCEPTED
    rig.run(3.0)
    assert rig.engine.armed
    assert "Auto disarm: landed" not in [t.text for t in rig.engine.statustexts]
    rig.run(10.0)
    assert rig.engine.armed and rig.engine.state.alt_m > 4.0


def test_px4_offboard_loss_action_land() -> None:
    rig = Rig(profile=Autopilot.PX4, spawn=SpawnConfig(airborne=True, mode="OFFBOARD"), params={"COM_OBL_RC_ACT": 4})
    rig.run(1.0)
    assert rig.engine.mode_name() == "AUTO.LAND"
    assert rig.engine.statustexts[-1].text == "Failsafe: offboard signal lost, Land"
    rig.run(15.0)
    assert rig.engine.state.on_ground and not rig.engine.armed


def test_reposition_in_guided() -> None:
    rig = Rig(spawn=SpawnConfig(airborne=True))
    lat0, lon0 = -35.363262, 149.165237
    lat = round((lat0 + math.degrees(4.0 / 6378137.0)) * 1e7)
    msg = GCS.command_int_encode(
        1,
        1,
        m.MAV_FRAME_GLOBAL_RELATIVE_ALT_INT,
        m.MAV_CMD_DO_REPOSITION,
        0,
        0,
        -1,
        0,
        0,
        0,
        lat,
        round(lon0 * 1e7),
        6.0,
    )
    rig.engine.handle(wire(msg), 0)
    assert [x.result for _, x in rig.out if x.get_type() == "COMMAND_ACK"] == [m.MAV_RESULT_ACCEPTED]
    rig.run(10.0)
    np.testing.assert_allclose(rig.engine.state.pos_ned_m, [4.0, 0.0, -6.0], atol=0.02)


def test_forest_result_record() -> None:
    rig = Rig(world=load_world("forest"), spawn=SpawnConfig(airborne=True), seed=9)
    rig.setpoint(MASK_POSITION, pos=(3.0, 12.0, -5.0))
    rig.run(10.0)
    res = json.loads(json.dumps(rig.engine.result(), allow_nan=False))
    assert res["schema"] == "apf.sim_result/1" and res["profile"] == "ardupilot"
    assert not res["collided"] and res["crashed_at"] is None
    assert res["sim_time_s"] == pytest.approx(10.0)
    assert res["path_length_m"] == pytest.approx(9.0, abs=0.05)
    assert len(res["trajectory_ned_m"]) == len(res["trajectory_t_s"]) == 101
    # nearest true surface along (3, 3..12): the trunk at (6, 13) r 0.3 -> from (3, 12): sqrt(9 + 1) - 0.3
    # (minus up to a centimetre of controller overshoot past the target)
    assert math.sqrt(10.0) - 0.3 - 0.01 < res["min_clearance_m"] <= math.sqrt(10.0) - 0.3 + 1e-9
    assert res["world"]["name"] == "forest" and len(res["world"]["circles_ne_m"]) == 12


def test_invalid_configuration_names_the_parameter() -> None:
    with pytest.raises(ConfigError, match="GUID_TIMEOUT"):
        Rig(params={"GUID_TIMEOUT": 99.0})
    with pytest.raises(ConfigError, match=r"spawn\.mode"):
        Rig(spawn=SpawnConfig(mode="OFFBOARD"))  # not an ArduPilot mode
    with pytest.raises(ConfigError, match="physics_rate_hz"):
        EngineConfig(physics_rate_hz=1.0)


def test_crash_inside_an_obstacle_at_spawn() -> None:
    rig = Rig(world=World.from_obstacles([[0.0, 0.0]], 1.0))
    assert rig.engine.crashed
    assert rig.engine.result()["crashed_at"]["obstacle_id"] == 0
    assert rig.cmd(m.MAV_CMD_COMPONENT_ARM_DISARM, 1) == m.MAV_RESULT_FAILED
    assert CopterMode(rig.engine.custom_mode) is CopterMode.STABILIZE


async def test_cli_writes_result_on_sigterm(tmp_path: Path) -> None:
    result = tmp_path / "out" / "result.json"
    port = free_port(socket.SOCK_DGRAM)
    proc = await asyncio.create_subprocess_exec(
        sys.executable, "-m", "sim.vehicle.cli", "vehicle", "--profile", "px4", "--paper-field", "reference:30",
        "--seed", "2", "--airborne", "--speedup", "5", "--link", f"udpout:127.0.0.1:{port}",
        "--result-json", str(result), "--tlog", str(tmp_path / "sim.tlog"),
        stdout=asyncio.subprocess.PIPE, stderr=asyncio.subprocess.PIPE,
    )  # fmt: skip
    assert proc.stdout is not None
    gcs = await MavlinkLink.open(f"udpin:127.0.0.1:{port}", source_system=255, source_component=190)
    try:
        async with asyncio.timeout(HANG_S):
            line = await proc.stdout.readline()
            assert line.startswith(b"apf-sim vehicle ready: profile=px4 world=paper-field:reference:30")
            # Half a simulated second has passed once the vehicle says so (however slow the machine is).
            await gcs.recv_match(
                type=("ATTITUDE", "LOCAL_POSITION_NED"), condition=lambda msg: msg.time_boot_ms > 600, timeout=HANG_S
            )
            proc.send_signal(signal.SIGTERM)
            out, err = await proc.communicate()
    finally:
        await gcs.aclose()
        if proc.returncode is None:
            proc.kill()
            await proc.wait()
    assert proc.returncode == 0, err.decode()
    assert b"apf-sim vehicle done" in out
    res = json.loads(result.read_text())
    assert res["profile"] == "px4" and res["sim_time_s"] > 0.5 and not res["collided"]
    assert len(res["world"]["circles_ne_m"]) == 30
    assert (tmp_path / "sim.tlog").stat().st_size > 0


@pytest.mark.parametrize("speedup", [math.inf, 20.0])
async def test_the_simulator_stops_its_physics_at_its_duration(speedup: float) -> None:
    """``SimConfig.duration_s``: the clock stops at the first physics step at or after it (0.255 s at 40 Hz: the
    11th step, 0.275 s), however long its owner takes to notice ``finished``."""
    link = f"udpout:127.0.0.1:{free_port(socket.SOCK_DGRAM)}"
    cfg = SimConfig(links=[link], speedup=speedup, physics_rate_hz=40.0, duration_s=0.255)
    async with await Simulator.start(cfg) as sim:
        async with asyncio.timeout(HANG_S):
            await sim.finished.wait()
        assert sim.t_s == pytest.approx(0.275) and sim.error is None
    assert sim.result()["sim_time_s"] == pytest.approx(0.275)  # closed: its clock ended where it stopped
    with pytest.raises(ConfigError, match="duration"):
        SimConfig(duration_s=math.nan)


async def test_cli_duration_and_bad_arguments(tmp_path: Path) -> None:
    result = tmp_path / "r.json"
    port = free_port(socket.SOCK_DGRAM)
    proc = await asyncio.create_subprocess_exec(
        sys.executable, "-m", "sim.vehicle.cli", "vehicle", "--world", "corridor", "--duration", "3",
        "--actuation-noise", "0.1",
        "--speedup", "inf", "--link", f"udpout:127.0.0.1:{port}", "--result-json", str(result),
        stdout=asyncio.subprocess.PIPE, stderr=asyncio.subprocess.PIPE,
    )  # fmt: skip
    async with asyncio.timeout(HANG_S):
        _, err = await proc.communicate()
    assert proc.returncode == 0, err.decode()
    res = json.loads(result.read_text())
    # --duration is simulated time, honoured within one physics step (100 Hz) even as fast as the CPU allows: it
    # ran 30 s, the simulated time of the CLI's 50 ms polling, when the CLI stopped the simulator.
    assert 3.0 <= res["sim_time_s"] <= 3.0 + 0.01 and res["on_ground"] and res["speedup"] is None
    assert res["params"]["SIM_POS_NOISE"] == 0.1 and res["params"]["GUID_TIMEOUT"] == 3.0
    bad = await asyncio.create_subprocess_exec(
        sys.executable, "-m", "sim.vehicle.cli", "vehicle", "--param", "GUID_TIMEOUT=99", "--duration", "1",
        "--link", f"udpout:127.0.0.1:{port}",
        stdout=asyncio.subprocess.PIPE, stderr=asyncio.subprocess.PIPE,
    )  # fmt: skip
    async with asyncio.timeout(HANG_S):
        _, err = await bad.communicate()
    assert bad.returncode == 2 and b"GUID_TIMEOUT 99 not in [0.1, 5]" in err


def test_auto_dynamics_is_the_profiles_own_vehicle() -> None:
    """``auto`` (the CLIs' default): ArduCopter's controller shape for ArduPilot, the simple response for PX4."""
    assert SimConfig(profile="ardupilot", dynamics="auto").dynamics is Dynamics.ARDUCOPTER
    assert SimConfig(profile="px4", dynamics="auto").dynamics is Dynamics.SIMPLE
    assert SimConfig(profile="ardupilot").dynamics is Dynamics.SIMPLE  # the in-process API keeps its default


def test_long_statustext_goes_in_chunks() -> None:
    """A parameter refusal longer than 50 characters arrives whole, in MAVLink 2 chunks sharing one id."""
    rig = Rig()
    name = next(iter(dict(rig.engine.params.items())))
    rig.engine.handle(wire(GCS.param_set_encode(1, 1, name.encode(), float("nan"), m.MAV_PARAM_TYPE_REAL32)), 0)
    texts = [wire(msg) for _, msg in rig.out if msg.get_type() == "STATUSTEXT"]
    assert texts, "a refused value is announced"
    rig.out.clear()
    rig.engine.statustext(m.MAV_SEVERITY_WARNING, "x" * 60 + "END")
    chunks = [wire(msg) for _, msg in rig.out if msg.get_type() == "STATUSTEXT"]
    assert [c.chunk_seq for c in chunks] == [0, 1] and len({c.id for c in chunks}) == 1 and chunks[0].id != 0
    assert "".join(c.text for c in chunks) == "x" * 60 + "END"


def test_arducopter_reports_a_position_only_guided_target_as_a_location() -> None:
    """GCS_MAVLINK_Copter::send_position_target_global_int: WP/Pos submodes only, MAV_FRAME_GLOBAL, AMSL."""
    rig = Rig(spawn=SpawnConfig(airborne=True, mode="GUIDED"))
    rig.run(0.2)
    rig.setpoint(MASK_POSITION, (12.0, -4.0, -7.0))
    rig.run(0.1)
    msg = wire(build(rig.engine, m.MAVLINK_MSG_ID_POSITION_TARGET_GLOBAL_INT))
    assert msg.coordinate_frame == m.MAV_FRAME_GLOBAL and msg.type_mask == MASK_POSITION
    home = rig.engine.cfg.home
    assert latlon_to_ne(home, msg.lat_int * 1e-7, msg.lon_int * 1e-7) == pytest.approx((12.0, -4.0), abs=0.02)
    assert msg.alt == pytest.approx(home.alt_amsl_m + 7.0)
    rig.setpoint(MASK_POS_VEL, (12.0, -4.0, -7.0), (1.0, 0.0, 0.0))  # a companion's stream: PosVelAccel
    rig.run(0.1)
    assert build(rig.engine, m.MAVLINK_MSG_ID_POSITION_TARGET_GLOBAL_INT) is None


def test_attitude_carries_body_rates_that_give_back_the_heading_rate() -> None:
    """ATTITUDE's rates are gyro (body) rates on both autopilots; while the vehicle turns and tilts, the service's
    Euler conversion gets the simulator's heading rate back (with level-body rates it would be off by cos(roll))."""
    rig = Rig(spawn=SpawnConfig(airborne=True, mode="GUIDED"))
    rig.run(0.2)
    rig.setpoint(MASK_POSITION, (-8.0, 12.0, -5.0))  # behind and to the right: a turn while accelerating
    seen = 0
    for _ in range(round(6.0 / rig.engine.dt)):
        rig.engine.step()
        roll, pitch = rig.engine.state.attitude_rad()
        psi_dot = rig.engine.state.yaw_rate_rad_s
        if abs(psi_dot) < 0.05 or max(abs(roll), abs(pitch)) < 0.02:
            continue
        msg = wire(build(rig.engine, m.MAVLINK_MSG_ID_ATTITUDE))
        assert euler_yaw_rate_rad_s(msg.roll, msg.pitch, msg.pitchspeed, msg.yawspeed) == pytest.approx(
            psi_dot, rel=1e-5, abs=1e-6
        )
        assert msg.yawspeed != pytest.approx(psi_dot, rel=1e-6)  # body r differs from psi_dot while tilted
        seen += 1
    assert seen > 10
