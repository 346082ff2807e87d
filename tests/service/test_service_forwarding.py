"""OBSTACLE_DISTANCE forwarding and range sensors on their own MAVLink ids, over real loopback UDP.

Against the scripted autopilot (tests/service/test_service_mavlink.py): what the service sends, the sensor ids it
accepts and rejects, the proximity echo it does not read back. Against the bundled simulator's ArduPilot profile:
PRX1_TYPE = 2 set over PARAM_SET, a reboot, the service's obstacles coming back as DISTANCE_SENSOR, and SYS_STATUS
marking proximity unhealthy 0.5 s (simulated) after the service stops (AP_Proximity_MAV.cpp).
"""

from __future__ import annotations

import asyncio
import contextlib

import numpy as np
import pytest
from pymavlink.dialects.v20 import ardupilotmega as m

from apf_companion.config import config_from_mapping
from apf_companion.links import MavlinkLink
from apf_companion.service import CompanionService
from sim.vehicle import SimConfig, Simulator, SpawnConfig
from sim.vehicle.proximity import PROXIMITY_TIMEOUT_S, ProximityStatus
from sim.vehicle.testing import command_long, drain
from sim.world import World
from tests.conftest import HANG_S, SimulatorClock, StepWatch, counter_advances, until, wait_sim_time
from tests.service.test_service_mavlink import fast_config, rig

pytestmark = [pytest.mark.timeout(120)]

FREE = 801
PRX = m.MAV_SYS_STATUS_SENSOR_PROXIMITY


def free_with(**cm: int) -> list[int]:
    out = [FREE] * 72
    for key, value in cm.items():
        out[int(key[1:])] = value
    return out


async def sensor_link(svc: CompanionService, system: int, component: int) -> MavlinkLink:
    assert svc.link is not None and svc.link.local_address is not None
    port = svc.link.local_address[1]
    return await MavlinkLink.open(f"udpout:127.0.0.1:{port}", source_system=system, source_component=component)


async def test_ranges_from_configured_sensor_ids_only() -> None:
    cfg = fast_config(sensors={"mavlink_sources": ["1/158"]})
    async with rig(cfg) as (svc, ap):
        ap.send_ranges = False
        await until(lambda: svc.navigator.pose is not None, 5.0, "pose")
        rogue, sensor = await sensor_link(svc, 1, 159), await sensor_link(svc, 1, 158)
        try:
            scans = svc.perception.counters.scans
            for _ in range(3):  # an unknown component of the vehicle: rejected, counted, never a point
                rogue.send(rogue.mav.obstacle_distance_encode(ap.boot_ms() * 1000, 0, free_with(s0=300), 0, 20, 800,
                                                              5.0, 0.0, m.MAV_FRAME_BODY_FRD))  # fmt: skip
            rogue.send(rogue.mav.distance_sensor_encode(ap.boot_ms(), 20, 800, 300, 0, 0, 0, 0))
            await until(lambda: svc.counters.rejected_ranges >= 4, 5.0, "rejected ranges counted")
            assert svc.perception.counters.scans == scans and len(svc.perception) == 0
            sensor.send(sensor.mav.obstacle_distance_encode(ap.boot_ms() * 1000, 0, free_with(s0=300), 0, 20, 800,
                                                            5.0, 0.0, m.MAV_FRAME_BODY_FRD))  # fmt: skip
            await until(lambda: len(svc.perception) > 0, 5.0, "the sensor's obstacle remembered")
            pts = svc.perception.points(svc.clock.now())
            near = pts[np.argmin(np.hypot(pts[:, 0] - 3.0, pts[:, 1]))]
            assert near[0] == pytest.approx(3.0, abs=0.05) and near[1] == pytest.approx(0.0, abs=0.05)
            status = svc.reporter.status_dict(svc.clock.now())
            assert status["counters"]["rejected_ranges"] == svc.counters.rejected_ranges >= 4
        finally:
            await rogue.aclose()
            await sensor.aclose()


async def test_forwarding_sends_body_frd_sectors_and_ignores_the_echo() -> None:
    cfg = fast_config(sensors={"forward_obstacle_distance": True, "forward_rate_hz": 20.0})
    async with rig(cfg) as (svc, ap):
        ap.ranges_cm = free_with(s0=300, s18=450)  # heading 0: ahead and to the right (east)
        await until(lambda: len(svc.perception) >= 2 and svc.outbox.obstacle_distances_sent >= 3, 5.0, "forwarded")
        od = [x for x in ap.of_type("OBSTACLE_DISTANCE")][-1]
        assert ap.sent_by["OBSTACLE_DISTANCE"] == (1, 191)  # the vehicle's sysid, our component
        assert od.frame == m.MAV_FRAME_BODY_FRD and (od.increment, od.increment_f, od.angle_offset) == (5, 5.0, 0.0)
        assert (od.min_distance, od.max_distance) == (10, 800)
        d = list(od.distances)
        assert abs(d[0] - 300) <= 2 and abs(d[18] - 450) <= 2
        # the scripted sensor covers every direction: the rest is "no obstacle" (a few sectors next to the two
        # returns may hold the wall the memory fills between them: none here, they are far apart)
        assert sum(1 for x in d if x == FREE) == 70
        # the autopilot's DISTANCE_SENSOR echo of its proximity faces (id 10 + face) is not read back; a
        # rangefinder's (id 0) still is
        scans = svc.perception.counters.scans
        ap.send_ranges = False
        link = ap.link
        link.send(link.mav.distance_sensor_encode(ap.boot_ms(), 20, 800, 150, 0, 10, m.MAV_SENSOR_ROTATION_NONE, 0))
        await until(lambda: svc.counters.proximity_echoes_ignored == 1, 5.0, "echo ignored")
        link.send(link.mav.distance_sensor_encode(ap.boot_ms(), 20, 800, 150, 0, 0, m.MAV_SENSOR_ROTATION_NONE, 0))
        await until(lambda: svc.perception.counters.scans == scans + 1, 5.0, "rangefinder read")
        # no pose: nothing is forwarded (counted), and the autopilot will mark proximity unhealthy
        ap.send_pose = False
        await until(lambda: svc.counters.forward_skipped >= 3, 5.0, "skipped without a pose")
        sent = svc.outbox.obstacle_distances_sent
        # an absence: three more forwarding periods pass (counted as skipped), and still nothing was sent
        await counter_advances(lambda: svc.counters.forward_skipped, 3, "forwarding periods without a pose")
        assert svc.outbox.obstacle_distances_sent == sent
        assert svc.reporter.status_dict(svc.clock.now())["counters"]["obstacle_distances_sent"] == sent


async def test_on_px4_the_autopilots_obstacle_distance_is_the_echo_of_the_forwarded_one() -> None:
    """PX4 streams OBSTACLE_DISTANCE from its collision-prevention map, which holds every OBSTACLE_DISTANCE it
    received (streams/OBSTACLE_DISTANCE.hpp sends obstacle_distance_fused): while forwarding, the autopilot's own
    is our obstacles coming back, and would keep them alive for ever. Counted and dropped; a sensor's is read."""
    cfg = fast_config(
        autopilot={"profile": "px4"}, sensors={"forward_obstacle_distance": True, "mavlink_sources": ["1/158"]}
    )
    async with rig(cfg) as (svc, ap):
        ap.ranges_cm = free_with(s0=300)  # from the autopilot's ids (1/1): PX4's map
        await until(lambda: svc.counters.proximity_echoes_ignored >= 3, 5.0, "echoes ignored")
        assert svc.perception.counters.scans == 0 and len(svc.perception) == 0
        sensor = await sensor_link(svc, 1, 158)  # a sensor of its own
        try:
            sensor.send(sensor.mav.obstacle_distance_encode(ap.boot_ms() * 1000, 0, free_with(s0=300), 0, 20, 800,
                                                            5.0, 0.0, m.MAV_FRAME_BODY_FRD))  # fmt: skip
            await until(lambda: len(svc.perception) > 0, 5.0, "the sensor's obstacle remembered")
        finally:
            await sensor.aclose()


async def test_forwarding_is_off_by_default() -> None:
    async with rig() as (svc, ap):
        await until(lambda: len(ap.of_type("HEARTBEAT")) >= 2 and svc.perception.counters.scans > 3, 5.0, "running")
        assert not ap.of_type("OBSTACLE_DISTANCE") and svc.outbox.obstacle_distances_sent == 0


async def test_simulated_arducopter_reports_the_forwarded_obstacles_back() -> None:
    """PRX1_TYPE = 2 set over PARAM_SET works only after a reboot; then the service's OBSTACLE_DISTANCE comes back
    as DISTANCE_SENSOR and SYS_STATUS proximity is healthy, until 0.5 s after the service stops."""
    speedup = 2.0
    cfg = config_from_mapping(
        {
            "link": {"connect": "udpin:127.0.0.1:0"},
            "sensors": {"forward_obstacle_distance": True, "forward_rate_hz": 10.0},
        }
    )
    svc = await CompanionService.open(cfg, clock=SimulatorClock(speedup))
    assert svc.link is not None and svc.link.local_address is not None
    gcs = await MavlinkLink.open("udpin:127.0.0.1:0", source_system=255, source_component=190)
    assert gcs.local_address is not None
    world = World.from_obstacles([[3.0, 0.0]], 0.5)  # a cylinder 2.5 m ahead (vehicle heading north)
    sim = await Simulator.start(
        SimConfig(
            links=[f"udpout:127.0.0.1:{gcs.local_address[1]}", f"udpout:127.0.0.1:{svc.link.local_address[1]}"],
            world=world,
            spawn=SpawnConfig(pos_ne_m=(0.0, 0.0)),
            speedup=speedup,
        )
    )
    assert isinstance(svc.clock, SimulatorClock)
    svc.clock.follow(sim)
    try:
        async with asyncio.TaskGroup() as tg:
            task = tg.create_task(svc.run())
            await gcs.recv_match(type="HEARTBEAT", timeout=HANG_S)
            gcs.send(gcs.mav.param_set_encode(1, 1, b"PRX1_TYPE", 2.0, m.MAV_PARAM_TYPE_REAL32))
            await gcs.recv_match(condition=lambda x: x.get_type() == "PARAM_VALUE", timeout=HANG_S)
            assert sim.engine.proximity.status(sim.t_s) is ProximityStatus.NOT_CONNECTED  # not before a reboot
            assert (await command_long(gcs, m.MAV_CMD_PREFLIGHT_REBOOT_SHUTDOWN, 1)).result == m.MAV_RESULT_ACCEPTED
            await gcs.recv_match(
                condition=lambda x: x.get_type() == "HEARTBEAT" and x.system_status != m.MAV_STATE_BOOT, timeout=HANG_S
            )
            interval = (m.MAVLINK_MSG_ID_DISTANCE_SENSOR, 200_000)
            assert (await command_long(gcs, m.MAV_CMD_SET_MESSAGE_INTERVAL, *interval)).result == m.MAV_RESULT_ACCEPTED
            ahead = await gcs.recv_match(
                condition=lambda x: x.get_type() == "DISTANCE_SENSOR" and x.orientation == m.MAV_SENSOR_ROTATION_NONE,
                timeout=HANG_S,
            )
            assert ahead.id == 10 and ahead.current_distance == pytest.approx(250, abs=3)
            await drain(gcs)
            st = await gcs.recv_match(type="SYS_STATUS", timeout=HANG_S)
            assert st.onboard_control_sensors_present & st.onboard_control_sensors_health & PRX
            watch: StepWatch[bool] = StepWatch(sim, lambda s: s.engine.proximity.status(s.t_s) is ProximityStatus.GOOD)
            svc.stop()  # the service (and its forwarding) ends
            await task
            last = sim.engine.proximity.last_update_s
            assert last is not None
            t_bad = await watch.first(lambda s: s.engine.proximity.status(s.t_s) is not ProximityStatus.GOOD,
                                      within_s=3.0)  # fmt: skip
            assert PROXIMITY_TIMEOUT_S < t_bad - last <= PROXIMITY_TIMEOUT_S + sim.engine.dt + 1e-9
            await wait_sim_time(sim, t_bad + 0.01)
            await drain(gcs)
            st = await gcs.recv_match(type="SYS_STATUS", timeout=HANG_S)
            assert st.onboard_control_sensors_present & PRX and not st.onboard_control_sensors_health & PRX
    finally:
        with contextlib.suppress(Exception):
            await svc.aclose()
        await sim.aclose()
        await gcs.aclose()
