"""Pose stamps against the receive clock, over real loopback MAVLink (docs/hardening.md "Pose plausibility").

A review in session 28 found that the pose gate measured how far the vehicle could have moved by the stamps alone,
with a tolerance applied again from every accepted pose: forged LOCAL_POSITION_NED frames with the autopilot's ids,
each stamped 0.95 s after the previous, walked the navigator's pose 50 m and the setpoints followed; one frame
stamped ahead made the genuine stream stale and forced a re-anchor. Here the scripted autopilot stops following the
setpoints, so its position is the genuine one, and the forged frames come from its own socket and ids.

Time is the scripted autopilot's (the service's clock follows it): injected frames are paced by its ticks.
"""

from __future__ import annotations

import math
from typing import Any

import pytest
from pymavlink.dialects.v20 import ardupilotmega as mavlink2

from apf_companion.autopilot import MASK_VELOCITY
from apf_companion.goal import Route
from apf_companion.handling.poses import POSE_CONFLICT_TEXT
from apf_companion.navigator import State
from tests.conftest import within
from tests.service.test_service_mavlink import ScriptedAutopilot, fast_config, rig

pytestmark = pytest.mark.timeout(60)

ROUTE = Route.point(30.0, 0.0, -5.0, source="test")


async def fly_then_stand(ap: ScriptedAutopilot, now: Any) -> tuple[float, float, float]:
    """Flying for the goal, then the vehicle stops following the setpoints: its position, the genuine one."""
    await within(now, lambda: len(ap.setpoints()) > 20, 20.0, "flying")
    ap.follow_setpoints = False
    await ap.ticks_pass(3)
    return (ap.pos[0], ap.pos[1], ap.pos[2])


def forge(ap: ScriptedAutopilot, stamp_ms: int, pos: tuple[float, float, float]) -> None:
    """An ATTITUDE and a LOCAL_POSITION_NED from the autopilot's own socket and ids."""
    mav = ap.link.mav
    ap.link.send(mav.attitude_encode(stamp_ms, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0))
    ap.link.send(mav.local_position_ned_encode(stamp_ms, *pos, 0.0, 0.0, 0.0))


def position_setpoint_distances(ap: ScriptedAutopilot, since: int, genuine: tuple[float, float, float]) -> list[float]:
    """How far each position setpoint after the first ``since`` lies from the genuine position (brakes carry no
    position) [m]."""
    return [math.dist((m.x, m.y, m.z), genuine) for _, m in ap.setpoints()[since:] if m.type_mask != MASK_VELOCITY]


def navigator_offset_m(svc: Any, genuine: tuple[float, float, float]) -> float:
    pose = svc.navigator.pose
    assert pose is not None
    return math.dist(tuple(pose.pos_ned_m), genuine)


async def test_poses_each_stamped_0_95_s_after_the_last_never_walk_the_navigator_pose() -> None:
    """Ten frames 50 ms apart on the wire, each stamped 0.95 s after the previous and 5 m further east: the first
    gains no reach from its stamp (implausible), the others lead the receive clock by more than the tolerance
    (``pose_time_leads``); the genuine stream keeps the pose and the setpoints (before: pose 50 m east, setpoints up
    to 50 m from the vehicle)."""
    async with rig(route=ROUTE) as (svc, ap):
        genuine = await fly_then_stand(ap, svc.clock.now)
        c = svc.perception.counters
        n0, resets0 = len(ap.setpoints()), c.pose_resets
        stamp = ap.boot_ms()
        for i in range(1, 11):
            stamp += 950
            forge(ap, stamp, (genuine[0], genuine[1] + 5.0 * i, genuine[2]))
            await ap.ticks_pass(1)
        await ap.ticks_pass(20)
        assert navigator_offset_m(svc, genuine) < 0.5
        distances = position_setpoint_distances(ap, n0, genuine)
        assert len(distances) >= 20 and max(distances) < 1.0  # the usual step ahead (0.4 m here), nothing more
        assert c.pose_resets == resets0 and c.pose_time_leads >= 8  # none before: the genuine stream never leads
        assert svc.navigator.state is State.NAVIGATING and svc.perception.gate.confirmed


@pytest.mark.parametrize("aside_m", [4.0, 0.1], ids=["4m-aside", "beside"])
async def test_one_pose_stamped_ahead_neither_moves_the_setpoints_nor_makes_the_genuine_stream_stale(
    aside_m: float,
) -> None:
    """One frame stamped 0.95 s ahead. 4 m aside: before, accepted (4 m fit the reach of 0.95 s), 8 setpoints went
    4 m aside, the genuine poses were stale for 0.95 s and then re-anchored the pose (memory cleared, HOLDING).
    Beside the vehicle: before, accepted, and the genuine stream stale for 0.95 s (HOLDING). Now neither: the pose's
    time is held to its receipt, so it is implausible (4 m) or harmless (0.1 m), and the genuine poses after it
    are newer."""
    async with rig(route=ROUTE) as (svc, ap):
        genuine = await fly_then_stand(ap, svc.clock.now)
        c = svc.perception.counters
        n0, stale0, resets0, rx0 = len(ap.setpoints()), c.stale_poses, c.pose_resets, len(ap.received)
        forge(ap, ap.boot_ms() + 950, (genuine[0], genuine[1] + aside_m, genuine[2]))
        await ap.ticks_pass(60)
        assert max(position_setpoint_distances(ap, n0, genuine)) < 1.0
        assert c.stale_poses == stale0 and c.pose_resets == resets0
        assert svc.navigator.state is State.NAVIGATING and navigator_offset_m(svc, genuine) < 0.5
        assert not [m for _, m in ap.received[rx0:] if m.get_type() == "STATUSTEXT" and "HOLDING" in m.text]


async def test_a_late_burst_after_a_silent_link_is_accepted() -> None:
    """The link holds everything the autopilot sends for 2 s while the vehicle drifts 1 m east, then delivers it at
    once: the poses are late (stamped before their receipt), not early, and every one is accepted; the navigator's
    pose is where the vehicle is and the service navigates on."""
    cfg = fast_config(link={"heartbeat_timeout_s": 3.0})
    async with rig(cfg, route=ROUTE) as (svc, ap):
        await fly_then_stand(ap, svc.clock.now)
        c = svc.perception.counters
        rejected0 = (c.stale_poses, c.implausible_poses, c.pose_time_leads, c.pose_conflicts, c.pose_resets)
        held: list[Any] = []
        send = ap.link.send
        ap.link.send = held.append  # type: ignore[method-assign,assignment]
        for _ in range(40):
            ap.pos = [ap.pos[0], ap.pos[1] + 0.025, ap.pos[2]]
            await ap.ticks_pass(1)
        ap.link.send = send  # type: ignore[method-assign]
        poses = len([m for m in held if m.get_type() == "LOCAL_POSITION_NED"])
        accepted0 = c.poses
        for m in held:
            send(m)
        # The link's silence (2 s) is shorter than its timeout, so the navigator may never have left NAVIGATING:
        # wait until the burst has been read too, not only for the state.
        await within(
            svc.clock.now,
            lambda: svc.navigator.state is State.NAVIGATING and c.poses - accepted0 >= poses,
            5.0,
            "navigating again, the burst read",
        )
        assert c.poses - accepted0 >= poses
        assert (c.stale_poses, c.implausible_poses, c.pose_time_leads, c.pose_conflicts, c.pose_resets) == rejected0
        assert navigator_offset_m(svc, (ap.pos[0], ap.pos[1], ap.pos[2])) < 0.1


async def test_a_stream_stamped_ahead_of_the_genuine_one_brakes_and_never_walks_the_vehicle() -> None:
    """A forged stream, one frame per genuine one, stamped 60 ms ahead of the autopilot's clock and walking east at
    2 m/s: the genuine poses are older, so stale, and before nothing told the streams apart: the pose walked and
    the setpoints followed (6 m in 3 s). Now the stale genuine poses contradict the accepted forged ones of their
    time (``pose_conflicts``): the anchor is unconfirmed and the service brakes. When the forged stream stops,
    the genuine one re-anchors."""
    async with rig(route=ROUTE) as (svc, ap):
        genuine = await fly_then_stand(ap, svc.clock.now)
        c = svc.perception.counters
        n0, t0 = len(ap.setpoints()), ap.t_s
        for _ in range(60):
            forge(ap, ap.boot_ms() + 60, (genuine[0], genuine[1] + 2.0 * (ap.t_s - t0), genuine[2]))
            await ap.ticks_pass(1)
        assert max(position_setpoint_distances(ap, n0, genuine)) < 1.5
        assert c.pose_conflicts >= 40 and not svc.perception.gate.confirmed
        brakes = [m for _, m in ap.setpoints()[n0:] if m.type_mask == MASK_VELOCITY]
        assert len(brakes) >= 40 and all(m.vx == m.vy == m.vz == 0.0 for m in brakes)
        # The pilot is told why the vehicle brakes (no state change says it), once per log interval, not per pose.
        await ap.ticks_pass(2)
        said = [m for _, m in ap.received if m.get_type() == "STATUSTEXT" and m.text == POSE_CONFLICT_TEXT]
        assert len(said) == 1 and said[0].severity == mavlink2.MAV_SEVERITY_WARNING
        await within(svc.clock.now, lambda: svc.perception.gate.confirmed, 5.0, "the genuine stream re-anchors")
        await within(svc.clock.now, lambda: navigator_offset_m(svc, genuine) < 0.5, 5.0, "the genuine pose")
