"""The service against a scripted MAVLink autopilot over real loopback UDP: identity, streams, bad input,
goals from a ground station, staleness and link loss.

The scripted autopilot is a plain ``MavlinkLink`` whose every message the test controls, so that faults a
real vehicle seldom produces (NaN poses, frozen timestamps, garbage bytes, a rogue sysid) can be injected.
Flights against the bundled simulator are in test_service_flight.py.
"""

from __future__ import annotations

import asyncio
import contextlib
import dataclasses
import math
import time
from collections.abc import AsyncIterator, Callable
from typing import Any

import pytest
from pymavlink.dialects.v20 import ardupilotmega as mavlink

from apf_companion.autopilot import MASK_POS_VEL, MASK_VELOCITY, CopterMode
from apf_companion.config import ServiceConfig, config_from_mapping
from apf_companion.goal import Route
from apf_companion.links import MavlinkLink
from apf_companion.navigator import State
from apf_companion.service import CompanionService

pytestmark = pytest.mark.timeout(60)

UINT16_MAX = 65535


class ScriptedAutopilot:
    """Heartbeat, LOCAL_POSITION_NED, ATTITUDE and an all-free OBSTACLE_DISTANCE, each switchable; follows
    DO_SET_MODE; records what the companion sends."""

    def __init__(self, link: MavlinkLink) -> None:
        self.link = link
        self.t0 = time.monotonic()
        self.pos = [0.0, 0.0, -5.0]
        self.custom_mode = int(CopterMode.LOITER)
        self.send_heartbeat = True
        self.send_pose = True
        self.freeze_pose_ms: int | None = None
        self.send_ranges = True
        self.follow_setpoints = True
        self.ranges_cm: list[int] | None = None
        self.received: list[tuple[float, Any]] = []
        self.sent_by: dict[str, tuple[int, int]] = {}

    def boot_ms(self) -> int:
        return int((time.monotonic() - self.t0) * 1000)

    def setpoints(self) -> list[tuple[float, Any]]:
        return [(t, m) for t, m in self.received if m.get_type() == "SET_POSITION_TARGET_LOCAL_NED"]

    def of_type(self, kind: str) -> list[Any]:
        return [m for _, m in self.received if m.get_type() == kind]

    async def run(self) -> None:
        async with asyncio.TaskGroup() as tg:
            tg.create_task(self._rx())
            tg.create_task(self._tx())

    async def _rx(self) -> None:
        async for msg in self.link.messages():
            self.received.append((time.monotonic(), msg))
            kind = msg.get_type()
            self.sent_by[kind] = (msg.get_srcSystem(), msg.get_srcComponent())
            if kind == "COMMAND_LONG" and msg.command == 176:
                self.custom_mode = int(msg.param2)
                self.link.send(self.link.mav.command_ack_encode(176, 0, 0, 0, 1, 191))
            elif kind == "SET_POSITION_TARGET_LOCAL_NED" and self.follow_setpoints and msg.type_mask != MASK_VELOCITY:
                self.pos = [msg.x, msg.y, msg.z]

    async def _tx(self) -> None:
        mav = self.link.mav
        n = 0
        while True:
            ms = self.boot_ms()
            if n % 20 == 0 and self.send_heartbeat:
                self.link.send(mav.heartbeat_encode(2, 3, 1 | 128, self.custom_mode, 4))
            if self.send_pose:
                t = ms if self.freeze_pose_ms is None else self.freeze_pose_ms
                self.link.send(mav.attitude_encode(t, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0))
                self.link.send(mav.local_position_ned_encode(t, *self.pos, 0.0, 0.0, 0.0))
            if n % 2 == 0 and self.send_ranges:
                cm = self.ranges_cm if self.ranges_cm is not None else [801] * 72
                self.link.send(mav.obstacle_distance_encode(ms * 1000, 0, cm, 0, 20, 800, 5.0, 0.0, 12))
            n += 1
            await asyncio.sleep(0.05)


def fast_config(**sections: dict[str, Any]) -> ServiceConfig:
    base: dict[str, Any] = {
        "link": {"connect": "udpin:127.0.0.1:0", "heartbeat_timeout_s": 1.5},
        "cycle": {"rate_hz": 20.0},
        "status": {"named_value_rate_hz": 10.0},
    }
    for key, value in sections.items():
        base[key] = base.get(key, {}) | value
    return config_from_mapping(base)


@contextlib.asynccontextmanager
async def rig(
    cfg: ServiceConfig | None = None, route: Route | None = None
) -> AsyncIterator[tuple[CompanionService, ScriptedAutopilot]]:
    cfg = cfg or fast_config()
    svc = await CompanionService.open(cfg, route=route)
    assert svc.link is not None and svc.link.local_address is not None
    port = svc.link.local_address[1]
    ap_link = await MavlinkLink.open(f"udpout:127.0.0.1:{port}", source_system=1, source_component=1)
    ap = ScriptedAutopilot(ap_link)
    async with asyncio.TaskGroup() as tg:
        svc_task = tg.create_task(svc.run())
        ap_task = tg.create_task(ap.run())
        try:
            yield svc, ap
        finally:
            svc.stop()
            await svc_task
            ap_task.cancel()
            await ap_link.aclose()


async def until(cond: Callable[[], bool], timeout_s: float, what: str) -> None:
    async with asyncio.timeout(timeout_s):
        while not cond():
            await asyncio.sleep(0.01)
    assert cond(), what


async def test_identity_heartbeat_and_stream_requests() -> None:
    cfg = fast_config(link={"component_id": 196})
    async with rig(cfg) as (svc, ap):
        await until(lambda: len(ap.of_type("HEARTBEAT")) >= 2, 5.0, "companion heartbeats")
        hb = ap.of_type("HEARTBEAT")[-1]
        assert hb.type == 18  # MAV_TYPE_ONBOARD_CONTROLLER
        assert hb.autopilot == 8  # MAV_AUTOPILOT_INVALID
        assert ap.sent_by["HEARTBEAT"] == (1, 196)  # the vehicle's sysid, our component; never 255/190
        assert hb.system_status == 3  # STANDBY: no goal
        intervals = {int(m.param1): m.param2 for m in ap.of_type("COMMAND_LONG") if m.command == 511}
        assert intervals[32] == pytest.approx(1e6 / 20.0)  # LOCAL_POSITION_NED
        assert intervals[30] == pytest.approx(1e6 / 20.0)  # ATTITUDE
        assert svc.navigator.state is State.IDLE and not ap.setpoints()


async def test_takeover_guided_then_fly_to_goal() -> None:
    route = Route.point(3.0, 0.0, -5.0, source="test")
    async with rig(route=route) as (svc, ap):
        await until(lambda: svc.navigator.state is State.ARRIVED, 20.0, "arrived")
        modes = [m for m in ap.of_type("COMMAND_LONG") if m.command == 176]
        assert modes and modes[0].param1 == 1 and modes[0].param2 == CopterMode.GUIDED
        sps = [m for _, m in ap.setpoints()]
        assert all(m.coordinate_frame == 1 and m.type_mask == MASK_POS_VEL for m in sps)
        assert ap.sent_by["SET_POSITION_TARGET_LOCAL_NED"] == (1, 191)
        assert all(m.target_system == 1 and m.target_component == 1 for m in sps)
        await until(lambda: any("ARRIVED" in m.text for m in ap.of_type("STATUSTEXT")), 2.0, "ARRIVED text")
        texts = [m.text for m in ap.of_type("STATUSTEXT")]
        assert any("NAVIGATING" in t for t in texts)
        await until(lambda: len(ap.of_type("NAMED_VALUE_FLOAT")) > 0, 3.0, "named values")
        names = {m.name for m in ap.of_type("NAMED_VALUE_FLOAT")}
        assert "APF_DGOAL" in names


async def test_bad_input_is_counted_and_never_a_setpoint() -> None:
    async with rig() as (svc, ap):
        await until(lambda: svc.navigator.pose is not None, 5.0, "pose")
        link = ap.link
        # Garbage bytes, a NaN pose, a rogue system's pose, out-of-range / malformed sectors.
        link.send_bytes(b"\xfd\x09\x00\x00\x00garbage" * 10)
        link.send_bytes(bytes(range(256)))
        link.send(link.mav.local_position_ned_encode(ap.boot_ms() + 5, math.nan, 0.0, -5.0, 0, 0, 0))
        rogue = await MavlinkLink.open(
            f"udpout:127.0.0.1:{svc.link.local_address[1]}",  # type: ignore[union-attr,index]
            source_system=7,
            source_component=1,
        )
        rogue.send(rogue.mav.local_position_ned_encode(ap.boot_ms() + 10, 50.0, 50.0, -5.0, 0, 0, 0))
        rogue.send(rogue.mav.heartbeat_encode(2, 3, 129, 4, 4))
        bad = [0] * 10 + [10] * 10 + [UINT16_MAX] * 52  # 0 and below-min readings are invalid
        link.send(link.mav.obstacle_distance_encode(ap.boot_ms() * 1000, 0, bad, 0, 20, 800, 5.0, 0.0, 12))
        link.send(link.mav.obstacle_distance_encode(ap.boot_ms() * 1000, 0, [100] * 72, 0, 20, 800, 0.0, 0.0, 12))
        await until(
            lambda: (
                svc.reporter.counters.foreign_messages >= 2
                and svc.perception.counters.bad_poses >= 1
                and svc.perception.counters.invalid_sectors >= 20
                and svc.perception.counters.bad_scans >= 1
                and svc.link is not None
                and svc.link.stats.bad_frames >= 1
            ),
            5.0,
            "all bad input counted",
        )
        await rogue.aclose()
        await asyncio.sleep(0.3)
        # No goal: none of it may have produced a setpoint; the rogue pose never became ours.
        assert not ap.setpoints()
        assert svc.navigator.state is State.IDLE
        pose = svc.navigator.pose
        assert pose is not None and abs(pose.pos_ned_m[0]) < 1.0


async def test_nan_and_rogue_pose_during_flight_do_not_move_setpoints() -> None:
    route = Route.point(30.0, 0.0, -5.0, source="test")
    async with rig(route=route) as (svc, ap):
        await until(lambda: len(ap.setpoints()) > 10, 10.0, "flying")
        ap.send_pose = False
        await asyncio.sleep(0.1)
        n0 = len(ap.setpoints())
        for k in range(10):  # only NaN poses now: the service must fall to HOLDING, never follow them
            ap.link.send(ap.link.mav.local_position_ned_encode(ap.boot_ms(), math.nan, math.nan, -5.0, 0, 0, 0))
            await asyncio.sleep(0.05 + 0.0 * k)
        await until(lambda: svc.navigator.state is State.HOLDING, 3.0, "holding")
        for _, m in ap.setpoints()[n0:]:
            assert all(math.isfinite(v) for v in (m.x, m.y, m.z, m.vx, m.vy, m.vz))
        assert svc.perception.counters.bad_poses >= 10


async def test_frozen_pose_holds_within_one_cycle() -> None:
    route = Route.point(30.0, 0.0, -5.0, source="test")
    # Ranges may be late on a loaded machine; only the pose's limit is under test here.
    cfg = fast_config(cycle={"rate_hz": 20.0, "pose_max_age_s": 0.3, "ranges_max_age_s": 5.0})
    async with rig(cfg, route) as (svc, ap):
        await until(lambda: len(ap.setpoints()) > 10, 10.0, "flying")
        frozen_at = time.monotonic()
        ap.freeze_pose_ms = ap.boot_ms()  # same timestamp and position over and over
        await until(lambda: svc.navigator.state is State.HOLDING, 3.0, "holding")

        # The HOLDING transition came on the first cycle after the pose aged past its limit:
        # the hold setpoint is the first one after the freeze that is not a navigation step.
        def holds() -> list[tuple[float, Any]]:
            return [(t, m) for t, m in ap.setpoints() if t > frozen_at and m.vx == 0 and m.vy == 0]

        await until(lambda: bool(holds()), 2.0, "the hold setpoint arrives")
        hold_t = holds()[0][0]
        nav_after = [m for t, m in ap.setpoints() if frozen_at < t < hold_t and m.vx != 0]
        # At most pose_max_age_s * rate_hz (+1 for the cycle in flight) steps on the frozen pose.
        assert len(nav_after) <= int(0.3 * 20) + 1
        await until(lambda: any(m.get_type() == "STATUSTEXT" for t, m in ap.received if t > frozen_at), 2.0, "text")
        changes = [m.text for t, m in ap.received if t > frozen_at and m.get_type() == "STATUSTEXT"]
        assert changes and "HOLDING" in changes[0] and "pose" in changes[0]
        ap.freeze_pose_ms = None
        await until(lambda: svc.navigator.state is State.NAVIGATING, 3.0, "navigating again")


async def test_heartbeat_lost_means_silence() -> None:
    route = Route.point(30.0, 0.0, -5.0, source="test")
    cfg = fast_config(safety={"resume_after_link_lost": False})  # resuming: test_service_hardening.py
    async with rig(cfg, route) as (svc, ap):
        await until(lambda: len(ap.setpoints()) > 10, 10.0, "flying")
        ap.send_heartbeat = False
        await until(lambda: svc.navigator.state is State.LINK_LOST, 4.0, "link lost")
        # Counted where the service sends, not timed where the autopilot receives: exact under any load.
        sent_at_loss = svc.outbox.setpoints_sent
        t_lost = time.monotonic()
        await asyncio.sleep(0.8)  # an absence check: a loaded machine can only make it pass too easily
        assert svc.outbox.setpoints_sent == sent_at_loss
        assert not [m for t, m in ap.received if t > t_lost + 0.2 and m.get_type() == "STATUSTEXT"]
        ap.send_heartbeat = True
        await until(lambda: svc.navigator.state is State.IDLE, 3.0, "idle after link back")
        await asyncio.sleep(0.3)
        assert svc.outbox.setpoints_sent == sent_at_loss  # no motion without a new goal


async def test_do_reposition_from_gcs_replaces_goal() -> None:
    route = Route.point(30.0, 0.0, -5.0, source="test")
    async with rig(route=route) as (svc, ap):
        await until(lambda: len(ap.setpoints()) > 5, 10.0, "flying")
        port = svc.link.local_address[1]  # type: ignore[union-attr,index]
        gcs = await MavlinkLink.open(f"udpout:127.0.0.1:{port}", source_system=255, source_component=190)
        try:
            # Addressed to the autopilot (not to us): ignored and counted.
            gcs.send(gcs.mav.command_int_encode(1, 1, 1, 192, 0, 0, -1, 1, 0, math.nan, 0, 50000, -5.0))
            # Addressed to us: LOCAL_NED, x/y in metres * 1e4 -> (0, 5, -5).
            gcs.send(gcs.mav.command_int_encode(1, 191, 1, 192, 0, 0, -1, 1, 0, math.nan, 0, 50000, -5.0))
            ack = await gcs.recv_match(type="COMMAND_ACK", timeout=3.0)
            assert ack.command == 192 and ack.result == 0
            assert ack.target_system == 255 and ack.target_component == 190
            target = svc.navigator.active_target_ned_m
            await until(lambda: svc.navigator.active_target_ned_m is not None, 2.0, "target")
            target = svc.navigator.active_target_ned_m
            assert target is not None and target.tolist() == pytest.approx([0.0, 5.0, -5.0])
            assert svc.navigator.route is not None and svc.navigator.route.source == "mavlink:255/190"
            # COMMAND_LONG cannot carry a frame: COMMAND_INT_ONLY; unsupported frame: UNSUPPORTED.
            gcs.send(gcs.mav.command_long_encode(1, 191, 192, 0, -1, 1, 0, math.nan, 0, 0, -5.0))
            ack = await gcs.recv_match(type="COMMAND_ACK", timeout=3.0)
            assert ack.result == mavlink.MAV_RESULT_COMMAND_INT_ONLY  # 8 (7 is COMMAND_LONG_ONLY)
            gcs.send(gcs.mav.command_int_encode(1, 191, 12, 192, 0, 0, -1, 1, 0, math.nan, 0, 0, -5.0))
            ack = await gcs.recv_match(type="COMMAND_ACK", timeout=3.0)
            assert ack.result == 3
            await until(lambda: svc.navigator.state is State.ARRIVED, 20.0, "arrived at the new goal")
            assert math.dist(ap.pos[:2], (0.0, 5.0)) <= 0.7 + 0.1
            assert svc.reporter.counters.foreign_messages >= 1
        finally:
            await gcs.aclose()


async def test_global_reposition_is_placed_about_the_vehicle() -> None:
    async with rig() as (svc, ap):
        await until(lambda: svc.navigator.pose is not None, 5.0, "pose")
        lat0, lon0 = 47.0, 8.0
        ap.link.send(
            ap.link.mav.global_position_int_encode(
                ap.boot_ms(), int(lat0 * 1e7), int(lon0 * 1e7), 500_000, 5_000, 0, 0, 0, 0
            )
        )
        await until(lambda: svc.handlers.global_ref is not None, 2.0, "global reference")
        port = svc.link.local_address[1]  # type: ignore[union-attr,index]
        gcs = await MavlinkLink.open(f"udpout:127.0.0.1:{port}", source_system=255, source_component=190)
        try:
            dlat = 10.0 / 6_378_137.0 * 180.0 / math.pi  # 10 m north
            x = round((lat0 + dlat) * 1e7)
            gcs.send(gcs.mav.command_int_encode(1, 191, 6, 192, 0, 0, -1, 1, 0, math.nan, x, int(lon0 * 1e7), 8.0))
            ack = await gcs.recv_match(type="COMMAND_ACK", timeout=3.0)
            assert ack.result == 0
            route = svc.navigator.route
            assert route is not None
            north, east, down = route.waypoints_ned_m[0]
            assert north == pytest.approx(ap.pos[0] + 10.0, abs=0.05)
            assert east == pytest.approx(ap.pos[1], abs=0.05)
            assert down == pytest.approx(-5.0 - 3.0, abs=0.01)  # 8 m above home, vehicle at 5 m
        finally:
            await gcs.aclose()


async def test_dry_run_sends_nothing() -> None:
    cfg = dataclasses.replace(fast_config(), dry_run=True)
    route = Route.point(3.0, 0.0, -5.0, source="test")
    async with rig(cfg, route) as (svc, ap):
        # Dry run plans from the pose every cycle (nothing moves the vehicle along the plan) and logs it.
        await until(lambda: svc.navigator.counters.planner_steps > 10, 10.0, "planning")
        assert svc.navigator.last_output is not None and svc.navigator.last_output.decision == "GREEDY"
        assert not ap.received
        assert svc.outbox.setpoints_sent == 0
