"""The service against a scripted MAVLink autopilot over real loopback UDP: identity, streams, bad input,
goals from a ground station, staleness and link loss.

The scripted autopilot is a plain ``MavlinkLink`` whose every message the test controls, so that faults a
real vehicle seldom produces (NaN poses, frozen timestamps, garbage bytes, a rogue sysid) can be injected.
Flights against the bundled simulator are in test_service_flight.py.

Time is the scripted autopilot's: its clock advances one ``TICK_S`` per stream pass, and the service runs on a
``SimulatorClock`` that follows it, so a loaded machine only slows both down together. Waits are on conditions
within autopilot seconds (``within``); absence checks wait for the service's own cycles (``counter_advances``).
"""

from __future__ import annotations

import asyncio
import contextlib
import dataclasses
import math
from collections.abc import AsyncIterator
from typing import Any

import numpy as np
import pytest
from pymavlink.dialects.v20 import ardupilotmega as mavlink

from apf_companion.autopilot import MASK_POS_VEL, MASK_VELOCITY, CopterMode
from apf_companion.config import ServiceConfig, config_from_mapping
from apf_companion.goal import Route, route_outside_limits
from apf_companion.links import MavlinkLink, SigningParams
from apf_companion.navigator import State
from apf_companion.service import CompanionService
from tests.conftest import SimulatorClock, counter_advances, within

pytestmark = pytest.mark.timeout(60)

UINT16_MAX = 65535
TICK_S = 0.05  # the scripted autopilot's stream period: its clock (and the service's) moves one tick per pass


class ScriptedAutopilot:
    """Heartbeat, LOCAL_POSITION_NED, ATTITUDE and an all-free OBSTACLE_DISTANCE, each switchable; follows
    DO_SET_MODE; records what the companion sends, stamped with its own clock (``t_s``)."""

    def __init__(self, link: MavlinkLink) -> None:
        self.link = link
        self.ticks = 0  # stream passes so far: the autopilot's clock
        self.pos = [0.0, 0.0, -5.0]
        self.custom_mode = int(CopterMode.LOITER)
        self.send_heartbeat = True
        self.send_pose = True
        self.freeze_pose_ms: int | None = None
        self.send_ranges = True
        self.follow_setpoints = True
        self.lose_set_mode = 0  # DO_SET_MODE commands still to lose on the way in (a lossy link)
        self.ranges_cm: list[int] | None = None
        self.received: list[tuple[float, Any]] = []
        self.sent_by: dict[str, tuple[int, int]] = {}

    @property
    def t_s(self) -> float:
        """The autopilot's clock [s]; the service's ``SimulatorClock`` follows it."""
        return self.ticks * TICK_S

    def boot_ms(self) -> int:
        return int(self.t_s * 1000)

    async def ticks_pass(self, n: int) -> None:
        """Wait until the autopilot's clock has moved on by ``n`` ticks."""
        await counter_advances(lambda: self.ticks, n, "autopilot ticks")

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
            self.received.append((self.t_s, msg))
            kind = msg.get_type()
            self.sent_by[kind] = (msg.get_srcSystem(), msg.get_srcComponent())
            if kind == "COMMAND_LONG" and msg.command == 176 and self.lose_set_mode > 0:
                self.lose_set_mode -= 1
            elif kind == "COMMAND_LONG" and msg.command == 176:
                self.custom_mode = int(msg.param2)
                self.link.send(self.link.mav.command_ack_encode(176, 0, 0, 0, 1, 191))
            elif kind == "SET_POSITION_TARGET_LOCAL_NED" and self.follow_setpoints and msg.type_mask != MASK_VELOCITY:
                self.pos = [msg.x, msg.y, msg.z]

    async def _tx(self) -> None:
        mav = self.link.mav
        while True:
            n = self.ticks
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
            self.ticks += 1
            # Pacing, not a wait: the stream's rate on the wall clock. Time itself is the tick count, which the
            # service's clock follows, so a starved task slows both sides and changes no result.
            await asyncio.sleep(TICK_S)


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
    cfg: ServiceConfig | None = None,
    route: Route | None = None,
    custom_mode: int = int(CopterMode.LOITER),
    *,
    ap_signing: SigningParams | None = None,
) -> AsyncIterator[tuple[CompanionService, ScriptedAutopilot]]:
    """The service and a scripted autopilot (which signs its frames with ``ap_signing``) over loopback UDP."""
    cfg = cfg or fast_config()
    clock = SimulatorClock(1.0)
    svc = await CompanionService.open(cfg, route=route, clock=clock)
    assert svc.link is not None and svc.link.local_address is not None
    port = svc.link.local_address[1]
    ap_link = await MavlinkLink.open(
        f"udpout:127.0.0.1:{port}", source_system=1, source_component=1, signing=ap_signing
    )
    ap = ScriptedAutopilot(ap_link)
    ap.custom_mode = custom_mode  # the mode of its first HEARTBEAT
    clock.follow(ap)
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


async def test_identity_heartbeat_and_stream_requests() -> None:
    cfg = fast_config(link={"component_id": 196})
    async with rig(cfg) as (svc, ap):
        await within(svc.clock.now, lambda: len(ap.of_type("HEARTBEAT")) >= 2, 5.0, "companion heartbeats")
        hb = ap.of_type("HEARTBEAT")[-1]
        assert hb.type == 18  # MAV_TYPE_ONBOARD_CONTROLLER
        assert hb.autopilot == 8  # MAV_AUTOPILOT_INVALID
        assert ap.sent_by["HEARTBEAT"] == (1, 196)  # the vehicle's sysid, our component; never 255/190
        assert hb.system_status == 3  # STANDBY: no goal
        intervals = {int(m.param1): m.param2 for m in ap.of_type("COMMAND_LONG") if m.command == 511}
        assert intervals[32] == pytest.approx(1e6 / 20.0)  # LOCAL_POSITION_NED
        assert intervals[30] == pytest.approx(1e6 / 20.0)  # ATTITUDE
        assert svc.navigator.state is State.IDLE and not ap.setpoints()


async def test_goal_adoption_asks_for_the_autopilot_target_reports() -> None:
    async with rig(fast_config(goal={"adopt_autopilot_target": True})) as (svc, ap):
        await within(svc.clock.now, lambda: len(ap.of_type("COMMAND_LONG")) >= 5, 5.0, "stream requests")
        intervals = {int(m.param1): m.param2 for m in ap.of_type("COMMAND_LONG") if m.command == 511}
        assert intervals[mavlink.MAVLINK_MSG_ID_POSITION_TARGET_GLOBAL_INT] == pytest.approx(200_000.0)
        assert intervals[mavlink.MAVLINK_MSG_ID_POSITION_TARGET_LOCAL_NED] == pytest.approx(200_000.0)


async def test_takeover_guided_then_fly_to_goal() -> None:
    route = Route.point(3.0, 0.0, -5.0, source="test")
    async with rig(route=route) as (svc, ap):
        await within(svc.clock.now, lambda: svc.navigator.state is State.ARRIVED, 20.0, "arrived")
        modes = [m for m in ap.of_type("COMMAND_LONG") if m.command == 176]
        assert modes and modes[0].param1 == 1 and modes[0].param2 == CopterMode.GUIDED
        sps = [m for _, m in ap.setpoints()]
        assert all(m.coordinate_frame == 1 and m.type_mask == MASK_POS_VEL for m in sps)
        assert ap.sent_by["SET_POSITION_TARGET_LOCAL_NED"] == (1, 191)
        assert all(m.target_system == 1 and m.target_component == 1 for m in sps)
        await within(
            svc.clock.now, lambda: any("ARRIVED" in m.text for m in ap.of_type("STATUSTEXT")), 2.0, "ARRIVED text"
        )
        texts = [m.text for m in ap.of_type("STATUSTEXT")]
        assert any("NAVIGATING" in t for t in texts)
        await within(svc.clock.now, lambda: len(ap.of_type("NAMED_VALUE_FLOAT")) > 0, 3.0, "named values")
        names = {m.name for m in ap.of_type("NAMED_VALUE_FLOAT")}
        assert "APF_DGOAL" in names


async def test_a_long_statustext_arrives_whole_in_chunks() -> None:
    """Armed in GUIDED at start (a restart mid-flight): the hold's STATUSTEXT is longer than one message and comes
    in MAVLink 2 chunks sharing a non-zero id, numbered from 0, that join to the whole text (it was cut at 50)."""
    async with rig(custom_mode=int(CopterMode.GUIDED)) as (svc, ap):

        def chunks() -> list[Any]:
            return [m for m in ap.of_type("STATUSTEXT") if m.id != 0]

        await within(svc.clock.now, lambda: any(len(m.text) < 50 for m in chunks()), 5.0, "a long STATUSTEXT")
        got = chunks()
        assert len({m.id for m in got}) == 1 and [m.chunk_seq for m in got] == list(range(len(got)))
        text = "".join(m.text for m in got)
        assert text == "APF HOLDING: started with the vehicle flying in guided control: holding, send a fresh goal"


async def test_a_takeover_whose_mode_commands_are_lost_waits_past_its_deadline() -> None:
    """The link loses the first five DO_SET_MODE (the lossy batch's seed 10 lost four): the HEARTBEATs say LOITER
    all along, but no command was answered, so that is no refusal; the sixth, sent past the 5 s deadline, is
    ACCEPTED and the flight goes on. Before session 19 the takeover failed at 5 s and dropped the goal."""
    route = Route.point(3.0, 0.0, -5.0, source="test")
    async with rig(route=route) as (svc, ap):
        ap.lose_set_mode = 5
        await within(svc.clock.now, lambda: svc.navigator.state is State.ARRIVED, 30.0, "arrived")
        modes = [m for m in ap.of_type("COMMAND_LONG") if m.command == 176]
        assert len(modes) >= 6 and svc.reporter.counters.mode_requests >= 6
        assert ap.t_s > 5.0 and svc.navigator.route is not None


async def test_bad_input_is_counted_and_never_a_setpoint() -> None:
    async with rig() as (svc, ap):
        await within(svc.clock.now, lambda: svc.navigator.pose is not None, 5.0, "pose")
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
        await within(
            svc.clock.now,
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
        await counter_advances(lambda: svc.navigator.counters.cycles, 6, "cycles after the bad input")
        # No goal: none of it may have produced a setpoint; the rogue pose never became ours.
        assert not ap.setpoints()
        assert svc.navigator.state is State.IDLE
        pose = svc.navigator.pose
        assert pose is not None and abs(pose.pos_ned_m[0]) < 1.0


async def test_nan_and_rogue_pose_during_flight_do_not_move_setpoints() -> None:
    route = Route.point(30.0, 0.0, -5.0, source="test")
    async with rig(route=route) as (svc, ap):
        await within(svc.clock.now, lambda: len(ap.setpoints()) > 10, 10.0, "flying")
        ap.send_pose = False
        await ap.ticks_pass(2)
        n0 = len(ap.setpoints())
        for _ in range(10):  # only NaN poses now: the service must fall to HOLDING, never follow them
            ap.link.send(ap.link.mav.local_position_ned_encode(ap.boot_ms(), math.nan, math.nan, -5.0, 0, 0, 0))
            await ap.ticks_pass(1)
        await within(svc.clock.now, lambda: svc.navigator.state is State.HOLDING, 3.0, "holding")
        for _, m in ap.setpoints()[n0:]:
            assert all(math.isfinite(v) for v in (m.x, m.y, m.z, m.vx, m.vy, m.vz))
        assert svc.perception.counters.bad_poses >= 10


async def test_frozen_pose_holds_within_one_cycle() -> None:
    route = Route.point(30.0, 0.0, -5.0, source="test")
    # Ranges may be late on a loaded machine; only the pose's limit is under test here.
    cfg = fast_config(cycle={"rate_hz": 20.0, "pose_max_age_s": 0.3, "ranges_max_age_s": 5.0})
    async with rig(cfg, route) as (svc, ap):
        await within(svc.clock.now, lambda: len(ap.setpoints()) > 10, 10.0, "flying")
        frozen_at = ap.t_s
        ap.freeze_pose_ms = ap.boot_ms()  # same timestamp and position over and over
        await within(svc.clock.now, lambda: svc.navigator.state is State.HOLDING, 3.0, "holding")

        # The HOLDING transition came on the first cycle after the pose aged past its limit:
        # the hold setpoint is the first one after the freeze that is not a navigation step.
        def holds() -> list[tuple[float, Any]]:
            return [(t, m) for t, m in ap.setpoints() if t > frozen_at and m.vx == 0 and m.vy == 0]

        await within(svc.clock.now, lambda: bool(holds()), 2.0, "the hold setpoint arrives")
        hold_t = holds()[0][0]
        nav_after = [m for t, m in ap.setpoints() if frozen_at < t < hold_t and m.vx != 0]
        # At most pose_max_age_s * rate_hz (+1 for the cycle in flight) steps on the frozen pose.
        assert len(nav_after) <= int(0.3 * 20) + 1
        await within(
            svc.clock.now,
            lambda: any(m.get_type() == "STATUSTEXT" for t, m in ap.received if t > frozen_at),
            2.0,
            "text",
        )
        changes = [m.text for t, m in ap.received if t > frozen_at and m.get_type() == "STATUSTEXT"]
        assert changes and "HOLDING" in changes[0] and "pose" in changes[0]
        ap.freeze_pose_ms = None
        await within(svc.clock.now, lambda: svc.navigator.state is State.NAVIGATING, 3.0, "navigating again")


async def test_heartbeat_lost_means_silence() -> None:
    route = Route.point(30.0, 0.0, -5.0, source="test")
    cfg = fast_config(safety={"resume_after_link_lost": False})  # resuming: test_service_hardening.py
    async with rig(cfg, route) as (svc, ap):
        await within(svc.clock.now, lambda: len(ap.setpoints()) > 10, 10.0, "flying")
        ap.send_heartbeat = False
        await within(svc.clock.now, lambda: svc.navigator.state is State.LINK_LOST, 4.0, "link lost")
        # Counted where the service sends, not timed where the autopilot receives: exact under any load.
        sent_at_loss = svc.outbox.setpoints_sent
        t_lost = ap.t_s
        await counter_advances(lambda: svc.navigator.counters.cycles, 16, "cycles in LINK_LOST")  # 0.8 s at 20 Hz
        assert svc.outbox.setpoints_sent == sent_at_loss
        assert not [m for t, m in ap.received if t > t_lost + 0.2 and m.get_type() == "STATUSTEXT"]
        ap.send_heartbeat = True
        await within(svc.clock.now, lambda: svc.navigator.state is State.IDLE, 3.0, "idle after link back")
        await counter_advances(lambda: svc.navigator.counters.cycles, 6, "cycles after the link is back")
        assert svc.outbox.setpoints_sent == sent_at_loss  # no motion without a new goal


async def test_do_reposition_from_gcs_replaces_goal() -> None:
    route = Route.point(30.0, 0.0, -5.0, source="test")
    async with rig(route=route) as (svc, ap):
        await within(svc.clock.now, lambda: len(ap.setpoints()) > 5, 10.0, "flying")
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
            await within(svc.clock.now, lambda: svc.navigator.active_target_ned_m is not None, 2.0, "target")
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
            await within(svc.clock.now, lambda: svc.navigator.state is State.ARRIVED, 20.0, "arrived at the new goal")
            assert math.dist(ap.pos[:2], (0.0, 5.0)) <= 0.7 + 0.1
            assert svc.reporter.counters.foreign_messages >= 1
        finally:
            await gcs.aclose()


@contextlib.asynccontextmanager
async def gcs_for(svc: CompanionService) -> AsyncIterator[MavlinkLink]:
    """A ground station (255/190) talking to the service's link."""
    assert svc.link is not None and svc.link.local_address is not None
    gcs = await MavlinkLink.open(
        f"udpout:127.0.0.1:{svc.link.local_address[1]}", source_system=255, source_component=190
    )
    try:
        yield gcs
    finally:
        await gcs.aclose()


async def test_a_goal_beyond_the_altitude_or_distance_limit_is_refused() -> None:
    """The fuzz sent DO_REPOSITION z = -8576 m from a ground station: refused (counted), the goal unchanged."""
    route = Route.point(30.0, 0.0, -5.0, source="test")
    async with rig(route=route) as (svc, ap):
        await within(svc.clock.now, lambda: len(ap.setpoints()) > 5, 10.0, "flying")
        async with gcs_for(svc) as gcs:
            for x_e4, z in ((0, -8576.0), (30_000_000, -5.0)):  # 8.5 km up; 3 km north
                bad = svc.counters.bad_goals
                gcs.send(gcs.mav.command_int_encode(1, 191, 1, 192, 0, 0, -1, 1, 0, math.nan, x_e4, 50000, z))
                ack = await gcs.recv_match(type="COMMAND_ACK", timeout=3.0)
                assert ack.command == 192 and ack.result != mavlink.MAV_RESULT_ACCEPTED
                assert svc.counters.bad_goals == bad + 1
                assert svc.navigator.route is not None and svc.navigator.route.source == "test"
            assert all(m.z > -10.0 for _, m in ap.setpoints())  # no setpoint went up towards it


async def test_a_goal_below_the_altitude_floor_is_refused_one_at_5_m_or_keeping_the_altitude_is_flown() -> None:
    """A review sent DO_REPOSITION LOCAL_NED z = +30 (30 m below home) and z = +1000: both were ACCEPTED and the
    second was one setpoint at z = +1000 (only a fence floor, where the autopilot has one, stood in the way). Now
    ``goal.min_altitude_m`` (1 m above home by default) refuses them like the other limits (TEMPORARILY_REJECTED,
    ``bad_goals``); a goal 5 m up (the bundled flights') and one keeping the altitude (NaN z) are flown."""
    async with rig(route=Route.point(30.0, 0.0, -5.0, source="test")) as (svc, ap):
        await within(svc.clock.now, lambda: len(ap.setpoints()) > 5, 10.0, "flying")
        async with gcs_for(svc) as gcs:
            for z in (30.0, 1000.0, 0.0):  # 30 m and 1 km below home; on the ground at home: under 1 m
                bad = svc.counters.bad_goals
                gcs.send(gcs.mav.command_int_encode(1, 191, 1, 192, 0, 0, -1, 1, 0, math.nan, 30_000, 0, z))
                ack = await gcs.recv_match(type="COMMAND_ACK", timeout=3.0)
                assert (ack.command, ack.result) == (192, mavlink.MAV_RESULT_TEMPORARILY_REJECTED)
                assert svc.counters.bad_goals == bad + 1
                assert svc.navigator.route is not None and svc.navigator.route.source == "test"
            assert all(m.z < -1.0 for _, m in ap.setpoints() if m.type_mask != MASK_VELOCITY)  # none went down
            for z, down in ((-5.0, -5.0), (math.nan, math.nan)):
                gcs.send(gcs.mav.command_int_encode(1, 191, 1, 192, 0, 0, -1, 1, 0, math.nan, 30_000, 0, z))
                ack = await gcs.recv_match(type="COMMAND_ACK", timeout=3.0)
                assert (ack.command, ack.result) == (192, mavlink.MAV_RESULT_ACCEPTED)
                route = svc.navigator.route
                assert route is not None and route.source == "mavlink:255/190"
                assert route.waypoints_ned_m[0].tolist() == pytest.approx([3.0, 0.0, down], nan_ok=True)
            assert svc.counters.bad_goals == 3


async def test_a_goal_outside_the_flying_area_is_refused() -> None:
    """With bapf-nav's flying area set (``planner.params.nav_area_ne_m``), a ground station's goal outside it is
    refused and counted (the planner would give up at once); one inside is flown."""
    cfg = fast_config(planner={"params": {"nav_area_ne_m": [-10.0, -10.0, 40.0, 10.0]}})
    async with rig(cfg, route=Route.point(30.0, 0.0, -5.0, source="test")) as (svc, ap):
        await within(svc.clock.now, lambda: len(ap.setpoints()) > 5, 10.0, "flying")
        async with gcs_for(svc) as gcs:
            bad = svc.counters.bad_goals
            gcs.send(gcs.mav.command_int_encode(1, 191, 1, 192, 0, 0, -1, 1, 0, math.nan, 500_000, 50_000, -5.0))
            ack = await gcs.recv_match(type="COMMAND_ACK", timeout=3.0)
            assert ack.command == 192 and ack.result != mavlink.MAV_RESULT_ACCEPTED  # north 50 m: outside
            assert svc.counters.bad_goals == bad + 1
            assert svc.navigator.route is not None and svc.navigator.route.source == "test"
            gcs.send(gcs.mav.command_int_encode(1, 191, 1, 192, 0, 0, -1, 1, 0, math.nan, 200_000, 50_000, -5.0))
            ack = await gcs.recv_match(type="COMMAND_ACK", timeout=3.0)
            assert ack.command == 192 and ack.result == mavlink.MAV_RESULT_ACCEPTED  # north 20 m, east 5 m
            assert svc.navigator.route is not None and svc.navigator.route.source == "mavlink:255/190"


def test_route_limits() -> None:
    up = Route.point(0.0, 0.0, -121.0, source="t")
    assert route_outside_limits(up, None, max_altitude_m=120.0, max_distance_m=0.0) is not None
    assert route_outside_limits(up, None, max_altitude_m=0.0, max_distance_m=0.0) is None  # 0 = off
    keep = Route.point(10.0, 0.0, None, source="t")  # NaN down: keep the altitude
    assert route_outside_limits(keep, (0.0, 0.0, -5.0), max_altitude_m=120.0, max_distance_m=100.0) is None
    assert route_outside_limits(keep, (-95.0, 0.0, -5.0), max_altitude_m=120.0, max_distance_m=100.0) is not None
    assert route_outside_limits(keep, None, max_altitude_m=120.0, max_distance_m=5.0) is None  # no pose yet
    area = (-10.0, -10.0, 40.0, 10.0)
    assert route_outside_limits(keep, None, max_altitude_m=0.0, max_distance_m=0.0, area_ne_m=area) is None
    far = Route(waypoints_ned_m=np.array([[10.0, 0.0, -5.0], [41.0, 0.0, -5.0]]), source="t")
    why = route_outside_limits(far, None, max_altitude_m=0.0, max_distance_m=0.0, area_ne_m=area)
    assert why is not None and why.startswith("waypoint 1 ") and "nav_area_ne_m" in why
    l_shape = ((-10.0, -10.0), (40.0, -10.0), (40.0, 0.0), (20.0, 0.0), (20.0, 10.0), (-10.0, 10.0))  # notch NE
    notch = Route(waypoints_ned_m=np.array([[10.0, 5.0, -5.0], [30.0, 5.0, -5.0]]), source="t")
    why = route_outside_limits(notch, None, max_altitude_m=0.0, max_distance_m=0.0, area_ne_m=l_shape)
    assert why is not None and why.startswith("waypoint 1 ") and "[[-10.0, -10.0], [40.0, -10.0]" in why


def test_route_altitude_floor() -> None:
    """``min_altitude_m``: a waypoint lower above home is refused, saying how far below home it is; NaN down
    (keep the altitude) passes; a negative floor lets goals lie that far below home; None: no floor."""
    below = Route(waypoints_ned_m=np.array([[0.0, 0.0, -5.0], [3.0, 0.0, 1000.0]]), source="t")
    why = route_outside_limits(below, None, max_altitude_m=120.0, max_distance_m=0.0, min_altitude_m=1.0)
    assert why == "waypoint 1 is 1000 m below home (goal.min_altitude_m = 1)"
    low = Route.point(3.0, 0.0, -0.5, source="t")
    why = route_outside_limits(low, None, max_altitude_m=120.0, max_distance_m=0.0, min_altitude_m=1.0)
    assert why == "waypoint 0 is 0.5 m above home (goal.min_altitude_m = 1)"
    for ok, floor in ((Route.point(3.0, 0.0, -5.0, source="t"), 1.0), (Route.point(3.0, 0.0, None, source="t"), 1.0),
                      (Route.point(3.0, 0.0, 30.0, source="t"), -50.0), (below, None)):  # fmt: skip
        assert route_outside_limits(ok, None, max_altitude_m=0.0, max_distance_m=0.0, min_altitude_m=floor) is None


async def test_commands_broadcast_to_system_0_are_answered() -> None:
    """MAVProxy addresses commands to target_system 0 by default: they are ours too (MAVLink routing)."""
    async with rig(route=Route.point(30.0, 0.0, -5.0, source="test")) as (svc, ap):
        await within(svc.clock.now, lambda: len(ap.setpoints()) > 5, 10.0, "flying")
        port = svc.link.local_address[1]  # type: ignore[union-attr,index]
        gcs = await MavlinkLink.open(f"udpout:127.0.0.1:{port}", source_system=255, source_component=190)
        try:
            local = mavlink.MAV_FRAME_LOCAL_NED
            reposition = mavlink.MAV_CMD_DO_REPOSITION
            gcs.send(gcs.mav.command_int_encode(0, 0, local, reposition, 0, 0, -1, 1, 0, math.nan, 0, 40000, -5.0))
            ack = await gcs.recv_match(type="COMMAND_ACK", timeout=3.0)
            assert (ack.command, ack.result) == (reposition, mavlink.MAV_RESULT_ACCEPTED)
            await within(
                svc.clock.now,
                lambda: svc.navigator.route is not None and svc.navigator.route.source == "mavlink:255/190",
                2.0,
                "goal",
            )
            # a command we do not handle: UNSUPPORTED when addressed to our component, left to the autopilot when
            # addressed to all components (our UNSUPPORTED beside its ACCEPTED would read as a refusal)
            gcs.send(gcs.mav.command_long_encode(0, 0, mavlink.MAV_CMD_DO_SET_SERVO, 0, 1, 1500, 0, 0, 0, 0, 0))
            gcs.send(gcs.mav.command_long_encode(0, 191, mavlink.MAV_CMD_DO_SET_HOME, 0, 1, 0, 0, 0, 0, 0, 0))
            ack = await gcs.recv_match(type="COMMAND_ACK", timeout=3.0)
            assert (ack.command, ack.result) == (mavlink.MAV_CMD_DO_SET_HOME, mavlink.MAV_RESULT_UNSUPPORTED)
            assert svc.counters.commands_for_us == 3
        finally:
            await gcs.aclose()


async def test_global_reposition_is_placed_about_the_vehicle() -> None:
    async with rig() as (svc, ap):
        await within(svc.clock.now, lambda: svc.navigator.pose is not None, 5.0, "pose")
        lat0, lon0 = 47.0, 8.0
        ap.link.send(
            ap.link.mav.global_position_int_encode(
                ap.boot_ms(), int(lat0 * 1e7), int(lon0 * 1e7), 500_000, 5_000, 0, 0, 0, 0
            )
        )
        await within(svc.clock.now, lambda: svc.handlers.global_ref is not None, 2.0, "global reference")
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


async def test_the_global_reference_pairs_a_global_position_with_the_pose_of_its_time() -> None:
    """GLOBAL_POSITION_INT and LOCAL_POSITION_NED of one instant may arrive in either order: the reference waits
    for the pose of the global position's own time, not the latest one (one stream period apart is 0.5 m at
    5 m/s; the fence test saw a vertex 2 cm off under load)."""
    async with rig() as (svc, ap):
        await within(svc.clock.now, lambda: svc.navigator.pose is not None, 5.0, "pose")
        ap.send_pose = False  # from here the test sends the poses, with the attitude they need
        mav = ap.link.mav
        await ap.ticks_pass(2)
        t = ap.boot_ms() + 20
        ap.link.send(mav.global_position_int_encode(t, 470_000_000, 80_000_000, 500_000, 5_000, 0, 0, 0, 0))
        await ap.ticks_pass(4)
        assert svc.handlers.global_ref is None  # its pose has not arrived
        ap.link.send(mav.attitude_encode(t, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0))
        ap.link.send(mav.local_position_ned_encode(t, 0.06, 0.03, -5.0, 0.0, 0.0, 0.0))
        await within(svc.clock.now, lambda: svc.handlers.global_ref is not None, 2.0, "global reference")
        ref = svc.handlers.global_ref
        assert ref is not None and ref.pos_ned_m == pytest.approx((0.06, 0.03, -5.0))
        assert ref.lat_deg == pytest.approx(47.0)


async def test_dry_run_sends_nothing() -> None:
    cfg = dataclasses.replace(fast_config(), dry_run=True)
    route = Route.point(3.0, 0.0, -5.0, source="test")
    async with rig(cfg, route) as (svc, ap):
        # Dry run plans from the pose every cycle (nothing moves the vehicle along the plan) and logs it.
        await within(svc.clock.now, lambda: svc.navigator.counters.planner_steps > 10, 10.0, "planning")
        assert svc.navigator.last_output is not None and svc.navigator.last_output.decision == "GREEDY"
        assert not ap.received
        assert svc.outbox.setpoints_sent == 0
