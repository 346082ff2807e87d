"""Issue 9's service-side hardening over real loopback MAVLink: no value on the wire crashes the service, hostile
poses never become a setpoint's origin, DO_REPOSITION with an infinite altitude is refused, and the link-loss
recovery keeps the goal. The scripted autopilot (``ScriptedAutopilot``) is a plain pymavlink peer on 127.0.0.1.
"""

from __future__ import annotations

import asyncio
import math

import pytest
from pymavlink.dialects.v20 import ardupilotmega as mavlink

from apf_companion.autopilot import MASK_POS_VEL
from apf_companion.goal import Route
from apf_companion.links import MavlinkLink
from apf_companion.navigator import State
from apf_companion.outbox import FLOAT32_MAX, Outbox
from apf_companion.setpoint import Setpoint, SetpointKind
from tests.test_service_mavlink import rig, until

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
        await until(lambda: len(ap.setpoints()) > 10, 10.0, "flying")
        for _ in range(20):
            ap.link.send(ap.link.mav.local_position_ned_encode(ap.boot_ms(), 3e38, 3e38, -5.0, 0, 0, 0))
            await asyncio.sleep(0.02)
        hb0 = len(ap.of_type("HEARTBEAT"))
        await until(lambda: len(ap.of_type("HEARTBEAT")) >= hb0 + 2, 5.0, "the service is still alive")
        assert svc.outbox.send_errors == 0


async def test_an_exception_in_a_handler_is_counted_and_survived() -> None:
    """Whatever escapes a handler is caught at the task's top: counted, logged once, the loop goes on."""
    route = Route.point(30.0, 0.0, -5.0, source="test")
    async with rig(route=route) as (svc, ap):
        await until(lambda: len(ap.setpoints()) > 5, 10.0, "flying")
        calls = 0

        def explode(yaw_rad: float) -> None:
            nonlocal calls
            calls += 1
            raise RuntimeError("a handler bug")

        svc.perception.on_attitude = explode  # type: ignore[method-assign]
        await until(lambda: svc.counters.handler_errors >= 5, 5.0, "errors counted")
        assert svc.faults.kinds.get("rx:RuntimeError", 0) >= 5
        n = len(ap.setpoints())
        await until(lambda: len(ap.setpoints()) > n + 5, 5.0, "still sending setpoints")
        assert svc.navigator.state is State.NAVIGATING
