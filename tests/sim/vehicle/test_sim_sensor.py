"""The range sensor: OBSTACLE_DISTANCE / DISTANCE_SENSOR / OBSTACLE_DISTANCE_3D against hand-computed geometry
(over loopback), configuration, noise and dropout, zenoh output, and sensor-only mode."""

from __future__ import annotations

import asyncio
import math
import socket
import subprocess
import sys

import numpy as np
import pytest
from pymavlink.dialects.v20 import ardupilotmega as m

from apf_companion.errors import ConfigError, LinkTimeout
from apf_companion.links import MavlinkLink
from apf_companion.links.zenoh import ZenohConfig, ZenohLink
from apf_companion.perception import decode_laserscan_cdr, decode_scan_json
from sim.vehicle import RangeSensorConfig, SimConfig, Simulator, SpawnConfig, ZenohOutput, scan_world
from sim.vehicle.sensor import obstacle_distance_msg
from sim.vehicle.sensor_only import SensorOnlyConfig, SensorSimulator
from sim.vehicle.testing import simulator_with_client
from sim.world import World
from tests.conftest import HANG_S, free_port, until

YAW_DEG = 30.0
FREE_CM = 801
UINT16_MAX = 65535


def hand_world() -> World:
    # Vehicle at the origin heading 30 deg. A point obstacle 4 m away at world bearing 75 deg (body 45 deg:
    # sector 9), and a 0.5 m cylinder with its centre 3 m away at world bearing 210 deg (body 180 deg: sector 36).
    pt = 4.0 * np.array([math.cos(math.radians(75)), math.sin(math.radians(75))])
    cyl = 3.0 * np.array([math.cos(math.radians(210)), math.sin(math.radians(210))])
    return World.from_obstacles([pt, cyl], [0.0, 0.5])


def expected_sectors() -> list[int]:
    out = [FREE_CM] * 72
    out[9] = 400
    out[36] = 250
    # the cylinder subtends asin(0.5 / 3) = 9.6 deg either side of 180: sectors 35/37 see it along their
    # window edge 2.5 deg off its centre line, sectors 34/38 along theirs 7.5 deg off; 33/39 miss it
    for off_deg, sectors in ((2.5, (35, 37)), (7.5, (34, 38))):
        a = math.radians(off_deg)
        edge = 3.0 * math.cos(a) - math.sqrt(0.5**2 - (3.0 * math.sin(a)) ** 2)
        for i in sectors:
            out[i] = round(edge * 100)
    return out


async def test_obstacle_distance_matches_hand_geometry() -> None:
    spawn = SpawnConfig(pos_ne_m=(0.0, 0.0), yaw_deg=YAW_DEG, airborne=True, alt_m=5.0)
    async with simulator_with_client(world=hand_world(), spawn=spawn, speedup=5.0) as (_sim, gcs):
        od = await gcs.recv_match(type="OBSTACLE_DISTANCE", timeout=HANG_S)
        od2 = await gcs.recv_match(type="OBSTACLE_DISTANCE", timeout=HANG_S)
        assert od.frame == m.MAV_FRAME_BODY_FRD
        assert (od.increment, od.increment_f, od.angle_offset) == (5, 5.0, 0.0)
        assert (od.min_distance, od.max_distance) == (20, 800)
        assert od.sensor_type == m.MAV_DISTANCE_SENSOR_LASER
        assert list(od.distances) == expected_sectors()
        assert od2.time_usec - od.time_usec == 100_000  # 10 Hz of simulated time
        assert (od.get_srcSystem(), od.get_srcComponent()) == (1, 1)


async def test_distance_sensor_and_obstacle_distance_3d() -> None:
    spawn = SpawnConfig(pos_ne_m=(0.0, 0.0), yaw_deg=YAW_DEG, airborne=True, alt_m=5.0)
    sensor = RangeSensorConfig(messages=frozenset({"distance_sensor", "obstacle_distance_3d"}))
    async with simulator_with_client(world=hand_world(), spawn=spawn, sensor=sensor, speedup=5.0) as (_sim, gcs):
        readings: dict[int, int] = {}
        while len(readings) < 8:
            ds = await gcs.recv_match(type="DISTANCE_SENSOR", timeout=HANG_S)
            assert ds.id == ds.orientation
            assert ds.horizontal_fov == pytest.approx(math.radians(45.0))
            readings[ds.orientation] = ds.current_distance
        # body 45 deg -> YAW_45 (1); body 180 deg -> YAW_180 (4); the cylinder's edge also reaches into no other
        assert readings == {0: FREE_CM, 1: 400, 2: FREE_CM, 3: FREE_CM, 4: 250, 5: FREE_CM, 6: FREE_CM, 7: FREE_CM}
        pts: dict[int, tuple[float, float, float]] = {}
        while len(pts) < 2:
            o3 = await gcs.recv_match(type="OBSTACLE_DISTANCE_3D", timeout=HANG_S)
            assert o3.frame == m.MAV_FRAME_BODY_FRD
            pts[o3.obstacle_id] = (o3.x, o3.y, o3.z)
        r = 4.0 / math.sqrt(2)
        np.testing.assert_allclose(pts[0], (r, r, 0.0), atol=1e-5)  # ahead-right, 45 deg
        np.testing.assert_allclose(pts[1], (-2.5, 0.0, 0.0), atol=1e-5)  # the cylinder's face, behind
        with pytest.raises(LinkTimeout):
            await gcs.recv_match(type="OBSTACLE_DISTANCE", timeout=0.3)


def test_sector_configuration_offset_and_count() -> None:
    # a point at body bearing 47 deg: with angle_offset 10 and increment 10 the centres are 10, 20, ...;
    # 47 lies in the window of centre 50 (45..55) = sector 4; 36 sectors are used, the rest is UINT16_MAX
    cfg = RangeSensorConfig(sectors=36, increment_deg=10.0, angle_offset_deg=10.0)
    b = math.radians(47.0)
    world = World.from_obstacles([[3.0 * math.cos(b), 3.0 * math.sin(b)]], 0.0)
    scan = scan_world(
        world, cfg, t_s=1.0, pos_ned_m=np.array([0.0, 0.0, -2.0]), yaw_rad=0.0, min_range_m=0.2,
        max_range_m=8.0, noise_sd_m=0.0, dropout_prob=0.0, rng=np.random.default_rng(0),
    )  # fmt: skip
    msg = obstacle_distance_msg(m.MAVLink(None), scan, cfg)
    assert list(msg.distances[:36]) == [300 if i == 4 else FREE_CM for i in range(36)]
    assert list(msg.distances[36:]) == [UINT16_MAX] * 36
    assert (msg.increment_f, msg.angle_offset, msg.increment) == (10.0, 10.0, 10)
    assert msg.time_usec == 1_000_000


def test_noise_dropout_and_height() -> None:
    world = World.from_obstacles([[5.0, 0.0], [0.0, 5.0]], 0.0, heights_m=[math.inf, 3.0])

    def scan(noise: float, drop: float, alt: float, seed: int = 0) -> np.ndarray:
        return scan_world(
            world, RangeSensorConfig(), t_s=0.0, pos_ned_m=np.array([0.0, 0.0, -alt]), yaw_rad=0.0,
            min_range_m=0.2, max_range_m=8.0, noise_sd_m=noise, dropout_prob=drop, rng=np.random.default_rng(seed),
        ).ranges_m  # fmt: skip

    clean = scan(0.0, 0.0, 2.0)
    assert clean[0] == 5.0 and clean[18] == 5.0  # below the 3 m top the short one is seen
    assert np.isinf(scan(0.0, 0.0, 4.0)[18])  # above it: not
    assert np.isnan(scan(0.0, 1.0, 2.0)).all()  # dropout = unknown
    noisy = np.array([scan(0.2, 0.0, 2.0, seed)[0] for seed in range(400)])
    assert abs(noisy.mean() - 5.0) < 0.05 and 0.15 < noisy.std() < 0.25
    np.testing.assert_array_equal(scan(0.2, 0.3, 2.0, 7), scan(0.2, 0.3, 2.0, 7))  # seeded


@pytest.mark.parametrize("encoding", ["json", "cdr"])
async def test_zenoh_output(encoding: str) -> None:
    port = free_port()
    out = ZenohOutput(listen=(f"tcp/127.0.0.1:{port}",), encoding=encoding)
    spawn = SpawnConfig(pos_ne_m=(0.0, 0.0), yaw_deg=YAW_DEG, airborne=True)
    sim = await Simulator.start(SimConfig(world=hand_world(), spawn=spawn, zenoh=out, speedup=5.0))
    try:
        sub_link = await ZenohLink.open(ZenohConfig(connect=(f"tcp/127.0.0.1:{port}",)))
        try:
            sub = await sub_link.subscribe(out.key)
            sample = await sub.recv(timeout=HANG_S)
            if encoding == "json":
                assert sample.encoding.startswith("application/json")
                scan = decode_scan_json(sample.payload, t_s=0.0)
            else:
                assert sample.encoding.startswith("application/cdr")
                scan = decode_laserscan_cdr(sample.payload, t_s=0.0)
        finally:
            await sub_link.aclose()
    finally:
        await sim.aclose()
    expected = np.array(expected_sectors(), dtype=np.float64) / 100.0
    got = np.asarray(scan.ranges_m)
    bearings = np.degrees(np.asarray(scan.bearings_rad)) % 360.0
    order = np.argsort(bearings)
    np.testing.assert_allclose(bearings[order], np.arange(72) * 5.0, atol=1e-4)
    got = got[order]
    finite = expected < 8.0
    np.testing.assert_allclose(got[finite], expected[finite], atol=0.006)
    assert np.isinf(got[~finite]).all()


async def test_sensor_only_follows_an_external_autopilot() -> None:
    ap_port = free_port(socket.SOCK_DGRAM)
    companion = await MavlinkLink.open("udpin:127.0.0.1:0", source_system=42, source_component=191)
    assert companion.local_address is not None
    # the "external autopilot" is a simulator in an empty world, sending to the sensor's udpin
    autopilot = await Simulator.start(
        SimConfig(
            links=[f"udpout:127.0.0.1:{ap_port}"],
            spawn=SpawnConfig(pos_ne_m=(0.0, 0.0), yaw_deg=YAW_DEG, airborne=True),
            sensor=RangeSensorConfig(messages=frozenset()),
            speedup=1.0,
        )
    )
    sensor = await SensorSimulator.start(
        SensorOnlyConfig(
            autopilot=f"udpin:127.0.0.1:{ap_port}",
            outputs=(f"udpout:127.0.0.1:{companion.local_address[1]}",),
            world=hand_world(),
            rate_hz=20.0,
        )
    )
    try:
        od = await companion.recv_match(type="OBSTACLE_DISTANCE", timeout=HANG_S)
        assert list(od.distances) == expected_sectors()
        assert od.time_usec % 1000 == 0  # the autopilot's time_boot_ms of the pose used
        assert (od.get_srcSystem(), od.get_srcComponent()) == (1, m.MAV_COMP_ID_PERIPHERAL)  # not the autopilot's
        assert sensor.sysid == 1
        # the sensor asked the autopilot for 20 Hz position and attitude (the autopilot's link 0 now streams so)
        telemetry = autopilot.engine.telemetry

        def streams_at_20_hz() -> bool:
            ids = (m.MAVLINK_MSG_ID_LOCAL_POSITION_NED, m.MAVLINK_MSG_ID_ATTITUDE)
            return all(telemetry.interval_us(0, i) == 50_000 for i in ids)

        await until(streams_at_20_hz, HANG_S, "20 Hz position and attitude")
        t = [(await companion.recv_match(type="OBSTACLE_DISTANCE", timeout=HANG_S)).time_usec for _ in range(3)]
        assert t == sorted(t)
        res = sensor.result()
        assert res["scans"] >= 4 and not res["collided"]
        assert res["min_clearance_m"] == pytest.approx(2.5, abs=1e-6)
    finally:
        await sensor.aclose()
        await autopilot.aclose()
        await companion.aclose()


@pytest.mark.parametrize("compid", [1, m.MAV_COMP_ID_PERIPHERAL])
async def test_sensor_only_needs_its_own_component_id(compid: int) -> None:
    """Against an autopilot that streams nothing unasked (as ArduCopter): posing as 1/1, the sensor's stream
    requests are dropped (MAVLink_routing.cpp) and it says what it is waiting for; as 1/158 it gets its pose."""
    ap_port = free_port(socket.SOCK_DGRAM)
    companion = await MavlinkLink.open("udpin:127.0.0.1:0", source_system=42, source_component=191)
    assert companion.local_address is not None
    autopilot = await Simulator.start(
        SimConfig(
            links=[f"udpout:127.0.0.1:{ap_port}"],
            spawn=SpawnConfig(pos_ne_m=(0.0, 0.0), yaw_deg=YAW_DEG, airborne=True),
            sensor=RangeSensorConfig(messages=frozenset()),
            rates_hz={"LOCAL_POSITION_NED": 0.0, "ATTITUDE": 0.0},
            speedup=1.0,
        )
    )
    sensor = await SensorSimulator.start(
        SensorOnlyConfig(
            autopilot=f"udpin:127.0.0.1:{ap_port}",
            outputs=(f"udpout:127.0.0.1:{companion.local_address[1]}",),
            world=hand_world(),
            source_component=compid,
        )
    )
    loop = asyncio.get_running_loop()
    try:
        if compid == 1:
            await until(lambda: sensor.heartbeats >= 2, what="autopilot heartbeats")
            reason = sensor.waiting_for(loop.time())
            assert reason is not None and "no LOCAL_POSITION_NED or ATTITUDE" in reason and "1/1" in reason
            assert sensor.scans == 0 and autopilot.engine.own_id_drops >= 2
        else:
            od = await companion.recv_match(type="OBSTACLE_DISTANCE", timeout=HANG_S)
            assert list(od.distances) == expected_sectors()
            assert sensor.waiting_for(loop.time()) is None and autopilot.engine.own_id_drops == 0
    finally:
        await sensor.aclose()
        await autopilot.aclose()
        await companion.aclose()


async def test_sensor_only_without_an_autopilot_says_so() -> None:
    sensor = await SensorSimulator.start(
        SensorOnlyConfig(autopilot=f"udpin:127.0.0.1:{free_port(socket.SOCK_DGRAM)}", outputs=("udpout:127.0.0.1:9",))
    )
    try:
        reason = sensor.waiting_for(asyncio.get_running_loop().time())
        assert reason is not None and reason.startswith("no HEARTBEAT")
    finally:
        await sensor.aclose()
    with pytest.raises(ConfigError, match="source_component"):
        SensorOnlyConfig(autopilot="udpin:127.0.0.1:1", outputs=("udpout:127.0.0.1:9",), source_component=0)


def test_sensor_cli_says_what_it_waits_for() -> None:
    """`apf-sim sensor` with no autopilot: "started as 1/158", then what is missing, not "ready" and then nothing."""
    port = free_port(socket.SOCK_DGRAM)
    out = subprocess.run(
        [sys.executable, "-m", "sim", "sensor", "--autopilot", f"udpin:127.0.0.1:{port}",
         "--output", "udpout:127.0.0.1:9", "--duration", "2.5"],
        capture_output=True, text=True, timeout=HANG_S, check=True,
    ).stdout  # fmt: skip
    assert "started as 1/158" in out
    assert "apf-sim sensor waiting: no HEARTBEAT" in out
    assert "ready" not in out


async def test_sensor_only_scans_with_the_yaw_at_its_positions_time() -> None:
    """A real sensor measures at the attitude of the moment; the sensor-only simulator scans at the latest
    LOCAL_POSITION_NED, so it takes the ATTITUDE yaw at that position's time (carried by the rate), not the
    latest ATTITUDE (0.2 s older here: 11.5 degrees at 1 rad/s, two sectors)."""
    sensor_port = free_port(socket.SOCK_DGRAM)
    companion = await MavlinkLink.open("udpin:127.0.0.1:0", source_system=42, source_component=191)
    assert companion.local_address is not None
    autopilot = await MavlinkLink.open(f"udpout:127.0.0.1:{sensor_port}", source_system=1, source_component=1)
    sensor = await SensorSimulator.start(
        SensorOnlyConfig(
            autopilot=f"udpin:127.0.0.1:{sensor_port}",
            outputs=(f"udpout:127.0.0.1:{companion.local_address[1]}",),
            world=World.from_obstacles([np.array([5.0, 0.0])], [0.0]),  # a point 5 m north
            rate_hz=20.0,
        )
    )
    mav = autopilot.mav
    try:

        async def feed() -> None:
            while True:
                autopilot.send(mav.heartbeat_encode(m.MAV_TYPE_QUADROTOR, m.MAV_AUTOPILOT_ARDUPILOTMEGA, 0, 0, 0))
                autopilot.send(mav.attitude_encode(1000, 0.0, 0.0, 0.0, 0.0, 0.0, 1.0))  # yaw 0, turning 1 rad/s
                autopilot.send(mav.local_position_ned_encode(1200, 0.0, 0.0, -5.0, 0.0, 0.0, 0.0))
                await asyncio.sleep(0.05)

        feeder = asyncio.create_task(feed())
        try:
            od = await companion.recv_match(type="OBSTACLE_DISTANCE", timeout=HANG_S)
        finally:
            feeder.cancel()
        # the point is at body bearing -11.5 deg: sector 70 (-10 deg) holds it, sector 0 (the latest yaw's) does not
        assert od.distances[70] == 500 and od.distances[0] == FREE_CM
    finally:
        await sensor.aclose()
        await autopilot.aclose()
        await companion.aclose()
