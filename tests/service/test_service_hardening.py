"""Issue 9's service-side hardening over real loopback MAVLink: no value on the wire crashes the service, hostile
poses never become a setpoint's origin, DO_REPOSITION with an infinite altitude is refused, and the link-loss
recovery keeps the goal. The scripted autopilot (``ScriptedAutopilot``) is a plain pymavlink peer on 127.0.0.1.

As in test_service_mavlink.py, time is the scripted autopilot's (the service's clock follows it): injected
streams are paced by its ticks, waits are ``within`` its seconds, and absence checks wait for service cycles.
"""

from __future__ import annotations

import asyncio
import math
from typing import Any

import numpy as np
import pytest
from pymavlink.dialects.v20 import ardupilotmega as mavlink

from apf_companion.autopilot import MASK_POS_VEL, CopterMode
from apf_companion.goal import Route
from apf_companion.links import MavlinkLink
from apf_companion.navigator import State
from apf_companion.outbox import FLOAT32_MAX, Outbox
from apf_companion.setpoint import Setpoint, SetpointKind
from tests.conftest import counter_advances, within
from tests.service.test_service_mavlink import ScriptedAutopilot, fast_config, rig

pytestmark = pytest.mark.timeout(60)


async def test_outbox_never_raises_on_values_float32_cannot_carry() -> None:
    """NAMED_VALUE_FLOAT of 1e39 is clamped, a setpoint / command with one is skipped; all counted, none raise."""
    rx = await MavlinkLink.open("udpin:127.0.0.1:0", source_system=1, source_component=1)
    assert rx.local_address is not None
    tx = await MavlinkLink.open(f"udpout:127.0.0.1:{rx.local_address[1]}", source_system=1, source_component=191)
    try:
        out = Outbox(tx, dry_run=False, target_system=1, target_component=1, now_s=lambda: 0.0)
        out.named_value_float("APF_DGOAL", 1e39)
        out.named_value_float("APF_DGOAL", -math.inf)
        out.named_value_int("APF_REJ", 2**40)
        sp = Setpoint(
            pos_ned_m=(1e39, 0.0, 0.0), vel_ned_m_s=(0.0, 0.0, 0.0), type_mask=MASK_POS_VEL, kind=SetpointKind.HOLD
        )
        out.setpoint(sp)
        out.command_long(mavlink.MAV_CMD_DO_SET_MODE, 1e39)
        assert out.clamped_values == 3 and out.unsendable == 2 and out.send_errors == 0
        assert out.setpoints_sent == 0
        got = [await rx.recv_match(type="NAMED_VALUE_FLOAT", timeout=3.0) for _ in range(2)]
        assert [m.value for m in got] == pytest.approx([FLOAT32_MAX, -FLOAT32_MAX], rel=1e-6)
        nvi = await rx.recv_match(type="NAMED_VALUE_INT", timeout=3.0)
        assert nvi.value == 2**31 - 1
    finally:
        await tx.aclose()
        await rx.aclose()


async def test_3e38_pose_mid_flight_does_not_end_the_service() -> None:
    """The issue's crash: x = y = 3e38 (finite) overflowed the goal distance packed into NAMED_VALUE_FLOAT."""
    route = Route.point(30.0, 0.0, -5.0, source="test")
    async with rig(route=route) as (svc, ap):
        await within(svc.clock.now, lambda: len(ap.setpoints()) > 10, 10.0, "flying")
        for _ in range(20):
            ap.link.send(ap.link.mav.local_position_ned_encode(ap.boot_ms(), 3e38, 3e38, -5.0, 0, 0, 0))
            await ap.ticks_pass(1)
        hb0 = len(ap.of_type("HEARTBEAT"))
        await within(svc.clock.now, lambda: len(ap.of_type("HEARTBEAT")) >= hb0 + 2, 5.0, "the service is still alive")
        assert svc.outbox.send_errors == 0
        assert svc.perception.counters.out_of_bounds_poses >= 20
        assert svc.navigator.pose is not None and abs(svc.navigator.pose.pos_ned_m[0]) < 1e3
        assert all(abs(m.x) < 1e3 and abs(m.y) < 1e3 for _, m in ap.setpoints())
        assert all(abs(m.value) < 1e3 for m in ap.of_type("NAMED_VALUE_FLOAT"))


async def test_an_exception_in_a_handler_is_counted_and_survived() -> None:
    """Whatever escapes a handler is caught at the task's top: counted, logged once, the loop goes on."""
    route = Route.point(30.0, 0.0, -5.0, source="test")
    async with rig(route=route) as (svc, ap):
        await within(svc.clock.now, lambda: len(ap.setpoints()) > 5, 10.0, "flying")
        calls = 0

        def explode(yaw_rad: float, *, time_boot_ms: int | None = None, yaw_rate_rad_s: float = 0.0) -> None:
            nonlocal calls
            calls += 1
            raise RuntimeError("a handler bug")

        svc.perception.on_attitude = explode  # type: ignore[method-assign]
        await within(svc.clock.now, lambda: svc.counters.handler_errors >= 5, 5.0, "errors counted")
        assert svc.faults.kinds.get("rx:RuntimeError", 0) >= 5
        n = len(ap.setpoints())
        await within(svc.clock.now, lambda: len(ap.setpoints()) > n + 5, 5.0, "still sending setpoints")
        assert svc.navigator.state is State.NAVIGATING


async def test_hostile_poses_never_become_a_setpoint_origin(monkeypatch: pytest.MonkeyPatch) -> None:
    """1 km jumps, 1e30, a pose stamped 9 s ahead, one 10 s back, one at the goal: all rejected and counted; the
    genuine stream goes on, no setpoint leaves the corridor to the goal, and no ARRIVED from a spoofed pose."""
    booted_ms = 60_000  # the scripted autopilot booted a minute ago: a pose 10.5 s back fits in time_boot_ms
    monkeypatch.setattr(ScriptedAutopilot, "boot_ms", lambda self: int(self.t_s * 1e3) + booted_ms)
    route = Route.point(30.0, 0.0, -5.0, source="test")
    async with rig(route=route) as (svc, ap):
        await within(svc.clock.now, lambda: len(ap.setpoints()) > 10, 10.0, "flying")
        mav, n0 = ap.link.mav, len(ap.setpoints())
        hostile = [
            (0, (ap.pos[0] + 1000.0, 0.0, -5.0)),
            (0, (1e30, 1e30, -5.0)),
            (9000, (ap.pos[0], 50.0, -5.0)),  # stamped 9 s ahead, 50 m aside
            (-10_500, (ap.pos[0], 10.6, -5.0)),  # 10 s back without reboot evidence
            (0, (30.0, 0.0, -5.0)),  # at the goal
        ]
        for _ in range(3):
            for dt_ms, pos in hostile:
                ap.link.send(mav.local_position_ned_encode(ap.boot_ms() + dt_ms, *pos, 0, 0, 0))
                await ap.ticks_pass(1)  # between genuine poses
        c = svc.perception.counters
        await within(
            svc.clock.now,
            lambda: c.implausible_poses >= 6 and c.pose_time_leads >= 3 and c.pose_time_jumps >= 3,
            5.0,
            "hostile poses counted",
        )
        assert c.out_of_bounds_poses >= 3 and c.pose_resets == 0
        n1 = len(ap.setpoints())
        await within(
            svc.clock.now, lambda: len(ap.setpoints()) > n1 + 5, 5.0, "the genuine stream still drives the cycle"
        )
        assert svc.navigator.state is State.NAVIGATING
        for _, m in ap.setpoints()[n0:]:
            assert abs(m.y) < 1.0 and -1.0 < m.x < 31.0, (m.x, m.y)
        status = svc.reporter.status_dict(svc.clock.now())["counters"]
        assert status["implausible_poses"] >= 6 and status["pose_time_leads"] >= 3 and status["pose_time_jumps"] >= 3


async def test_a_sustained_new_position_is_accepted_after_a_hold_and_a_statustext() -> None:
    """An EKF reset: every pose from now on is 20 m east. Rejected until ``pose_reset_samples`` consistent ones,
    then the service holds at the new position for ``reset_hold_s`` and says so before it navigates on."""
    route = Route.point(30.0, 0.0, -5.0, source="test")
    cfg = fast_config(safety={"pose_reset_samples": 5, "reset_hold_s": 1.0})
    async with rig(cfg, route) as (svc, ap):
        await within(svc.clock.now, lambda: len(ap.setpoints()) > 10, 10.0, "flying")
        ap.follow_setpoints = False
        ap.pos = [ap.pos[0], ap.pos[1] + 20.0, ap.pos[2]]
        await within(svc.clock.now, lambda: svc.perception.counters.pose_resets == 1, 5.0, "re-anchored")
        assert svc.perception.counters.implausible_poses >= 4
        await within(svc.clock.now, lambda: any("reset" in m.text for m in ap.of_type("STATUSTEXT")), 3.0, "announced")
        text = next(m.text for m in ap.of_type("STATUSTEXT") if "reset" in m.text)
        assert "HOLDING" in text
        t_reset = next(t for t, m in ap.received if m.get_type() == "STATUSTEXT" and "reset" in m.text)
        await within(svc.clock.now, lambda: svc.navigator.state is State.NAVIGATING, 5.0, "navigating after the hold")
        after = [(t, m) for t, m in ap.setpoints() if t > t_reset]
        holds = [m for t, m in after if t < t_reset + 0.8]
        assert holds and all(m.vx == 0 and m.vy == 0 and abs(m.y - ap.pos[1]) < 0.5 for m in holds)


async def test_do_reposition_with_infinite_altitude_is_refused() -> None:
    route = Route.point(30.0, 0.0, -5.0, source="test")
    async with rig(route=route) as (svc, ap):
        await within(svc.clock.now, lambda: len(ap.setpoints()) > 5, 10.0, "flying")
        port = svc.link.local_address[1]  # type: ignore[union-attr,index]
        gcs = await MavlinkLink.open(f"udpout:127.0.0.1:{port}", source_system=255, source_component=190)
        try:
            for z in (math.inf, -math.inf):
                gcs.send(gcs.mav.command_int_encode(1, 191, 1, 192, 0, 0, -1, 1, 0, math.nan, 0, 50000, z))
                ack = await gcs.recv_match(type="COMMAND_ACK", timeout=3.0)
                assert ack.result == mavlink.MAV_RESULT_DENIED
            assert svc.counters.bad_goals == 2
            assert svc.navigator.route is not None and svc.navigator.route.source == "test"
            gcs.send(gcs.mav.command_int_encode(1, 191, 1, 192, 0, 0, -1, 1, 0, math.nan, 0, 50000, math.nan))
            ack = await gcs.recv_match(type="COMMAND_ACK", timeout=3.0)
            assert ack.result == mavlink.MAV_RESULT_ACCEPTED  # NaN: keep the altitude
        finally:
            await gcs.aclose()


def _near_count(svc: Any, north_m: float, east_m: float) -> int:
    pts = svc.perception.points(svc.clock.now())
    return int(np.count_nonzero(np.hypot(pts[:, 0] - north_m, pts[:, 1] - east_m) < 0.5))


async def test_a_flood_of_all_free_scans_does_not_erase_a_remembered_obstacle() -> None:
    """The genuine 72-sector scan sees an obstacle 3 m ahead every 100 ms; 600 "all free" scans from the same
    ids in between, and DISTANCE_SENSOR "free" beams from another sensor, never clear it."""
    async with rig() as (svc, ap):
        ap.ranges_cm = [300] + [801] * 71  # forward (north at yaw 0): an obstacle at 3 m
        await within(svc.clock.now, lambda: _near_count(svc, 3.0, 0.0) > 0, 5.0, "obstacle remembered")
        mav, lowest = ap.link.mav, 1
        for k in range(600):
            ms = ap.boot_ms()
            ap.link.send(mav.obstacle_distance_encode(ms * 1000, 0, [801] * 72, 0, 20, 800, 5.0, 0.0, 12))
            ap.link.send(mav.distance_sensor_encode(ms, 20, 800, 801, 0, 1, 0, 0))  # forward beam: free
            if k % 20 == 0:
                await ap.ticks_pass(1)  # 20 free scans per tick, between the genuine scans (every 2 ticks)
                lowest = min(lowest, _near_count(svc, 3.0, 0.0))
        await within(svc.clock.now, lambda: svc.perception.counters.clears_refused > 0, 3.0, "foreign clears refused")
        assert lowest >= 1 and _near_count(svc, 3.0, 0.0) >= 1
        # Once the obstacle is really gone, the same sensor clears it after clear_scans over clear_span_s.
        ap.ranges_cm = None
        await within(svc.clock.now, lambda: _near_count(svc, 3.0, 0.0) == 0, 5.0, "cleared by consistent evidence")


async def test_one_forward_beam_does_not_keep_the_service_moving_sideways() -> None:
    """The 72-sector source stops; a forward DISTANCE_SENSOR beam keeps reporting free (ranges stay "fresh"
    globally). The goal is east (sideways at yaw 0): no step may go there once its sector is unknown."""
    route = Route.point(0.0, 30.0, -5.0, source="test")
    async with rig(route=route) as (svc, ap):
        await within(svc.clock.now, lambda: len(ap.setpoints()) > 10, 10.0, "flying east")
        ap.send_ranges = False
        stop = ap.t_s

        async def beam() -> None:
            while True:
                ap.link.send(ap.link.mav.distance_sensor_encode(ap.boot_ms(), 20, 800, 801, 0, 1, 0, 0))
                await ap.ticks_pass(1)  # one beam per autopilot tick

        task = asyncio.create_task(beam())
        try:
            max_age_s = svc.config.safety.sector_max_age_s
            await within(
                svc.clock.now,
                lambda: svc.navigator.counters.unknown_direction_holds > 5,
                5.0,
                "held at the unknown side",
            )
            east = ap.pos[1]
            await within(svc.clock.now, lambda: ap.t_s > stop + max_age_s + 0.8, 5.0, "0.5 s more of holds")
            late = [m for t, m in ap.setpoints() if t > stop + max_age_s + 0.3]
            assert late and all(m.vx == 0 and m.vy == 0 for m in late)
            assert svc.navigator.ranges_fresh(svc.clock.now())  # globally the beam keeps ranges "fresh"
            assert ap.pos[1] == pytest.approx(east, abs=0.05)  # not moving sideways
        finally:
            task.cancel()


async def test_link_lost_then_heartbeat_back_resumes_the_kept_goal() -> None:
    """LINK_LOST: silence, goal kept. Heartbeat back in GUIDED: a HOLDING, then NAVIGATING with fresh inputs."""
    route = Route.point(30.0, 0.0, -5.0, source="test")
    async with rig(route=route) as (svc, ap):
        await within(
            svc.clock.now, lambda: svc.navigator.engaged and len(ap.setpoints()) > 10, 10.0, "flying in GUIDED"
        )
        ap.send_heartbeat = False
        await within(svc.clock.now, lambda: svc.navigator.state is State.LINK_LOST, 4.0, "link lost")
        t_lost = ap.t_s
        await counter_advances(lambda: svc.navigator.counters.cycles, 10, "cycles in LINK_LOST")  # 0.5 s at 20 Hz
        assert not [m for t, m in ap.setpoints() if t > t_lost + 0.2]
        assert svc.navigator.route is not None and svc.navigator.route.source == "test"
        ap.send_heartbeat = True
        await within(svc.clock.now, lambda: svc.navigator.state is State.NAVIGATING, 5.0, "navigating again")

        def texts() -> list[str]:
            return [m.text for t, m in ap.received if t > t_lost and m.get_type() == "STATUSTEXT"]

        await within(svc.clock.now, lambda: bool(texts()), 3.0, "the resume is announced")
        assert "HOLDING" in texts()[0] and "heartbeat back" in texts()[0]
        n = len(ap.setpoints())
        await within(
            svc.clock.now, lambda: len(ap.setpoints()) > n + 5 and ap.pos[0] > 2.0, 10.0, "moving towards the goal"
        )


async def test_heartbeat_back_in_loiter_drops_the_goal_and_sends_nothing() -> None:
    route = Route.point(30.0, 0.0, -5.0, source="test")
    async with rig(route=route) as (svc, ap):
        await within(
            svc.clock.now, lambda: svc.navigator.engaged and len(ap.setpoints()) > 10, 10.0, "flying in GUIDED"
        )
        n_modes = len([m for m in ap.of_type("COMMAND_LONG") if m.command == 176])
        ap.send_heartbeat = False
        await within(svc.clock.now, lambda: svc.navigator.state is State.LINK_LOST, 4.0, "link lost")
        ap.custom_mode = int(CopterMode.LOITER)  # the pilot took the vehicle during the outage
        ap.send_heartbeat = True
        await within(svc.clock.now, lambda: svc.navigator.state is State.IDLE, 4.0, "idle")
        t_back = ap.t_s
        await counter_advances(lambda: svc.navigator.counters.cycles, 10, "cycles after the link is back")
        assert svc.navigator.route is None
        assert not [m for t, m in ap.setpoints() if t > t_back]
        assert len([m for m in ap.of_type("COMMAND_LONG") if m.command == 176]) == n_modes  # no new takeover


async def test_rejected_input_is_in_named_value_int_and_the_status() -> None:
    async with rig() as (svc, ap):
        await within(svc.clock.now, lambda: svc.navigator.pose is not None, 5.0, "pose")
        mav = ap.link.mav
        for _ in range(5):
            ap.link.send(mav.local_position_ned_encode(ap.boot_ms(), 500.0, 0.0, -5.0, 0, 0, 0))  # a jump
        ap.link.send_bytes(b"\xfd\x09\x00\x00\x00garbage" * 3)

        def nvi(name: str) -> int:
            got = [m.value for m in ap.of_type("NAMED_VALUE_INT") if m.name == name]
            return got[-1] if got else -1

        # Both from the same burst of NAMED_VALUE_INTs; APF_ERRORS comes after APF_RJPOSE, so wait for it too.
        await within(
            svc.clock.now, lambda: nvi("APF_RJPOSE") >= 5 and nvi("APF_ERRORS") >= 0, 5.0, "rejected poses reported"
        )
        status = svc.reporter.status_dict(svc.clock.now())
        assert status["rejected"]["APF_RJPOSE"] >= 5 and status["counters"]["implausible_poses"] >= 5
        assert "nav_unknown_direction_holds" in status["counters"] and nvi("APF_ERRORS") == 0


async def test_an_odometry_reset_counter_change_re_anchors_at_the_first_jump() -> None:
    route = Route.point(30.0, 0.0, -5.0, source="test")
    cfg = fast_config(safety={"pose_reset_samples": 50, "reset_hold_s": 0.5})
    async with rig(cfg, route) as (svc, ap):
        await within(
            svc.clock.now, lambda: svc.navigator.engaged and len(ap.setpoints()) > 10, 10.0, "flying in GUIDED"
        )
        mav, cov = ap.link.mav, [math.nan] * 21

        def odometry(counter: int) -> None:
            ap.link.send(
                mav.odometry_encode(
                    ap.boot_ms() * 1000, 1, 12, *ap.pos, [1, 0, 0, 0], 0, 0, 0, 0, 0, 0, cov, cov, reset_counter=counter
                )
            )

        # The service has read each ODOMETRY once it reads a pose sent after it (one socket, in order).
        odometry(7)
        await counter_advances(lambda: svc.perception.counters.poses, 2, "poses after ODOMETRY 7")
        ap.follow_setpoints = False
        odometry(8)  # the estimator announces a reset: the first pose after it reports it (a reset within reach)
        await within(svc.clock.now, lambda: svc.perception.counters.pose_resets == 1, 3.0, "the memory forgotten")
        assert svc.perception.counters.estimator_resets == 1
        ap.pos = [ap.pos[0], ap.pos[1] + 20.0, ap.pos[2]]  # a jump later in the window is the reset too
        await within(svc.clock.now, lambda: svc.perception.counters.pose_resets == 2, 3.0, "re-anchored")
        assert svc.perception.counters.implausible_poses <= 2  # not the 50 consistent samples
        await within(svc.clock.now, lambda: any("reset" in m.text for m in ap.of_type("STATUSTEXT")), 3.0, "announced")
        status = svc.reporter.status_dict(svc.clock.now())
        assert status["counters"]["estimator_resets"] == 1 and status["counters"]["pose_resets"] == 2
