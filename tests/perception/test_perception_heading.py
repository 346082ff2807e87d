"""The yaw a pose carries is the ATTITUDE yaw at the position's own time, not the latest one received."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st
from pymavlink.dialects.v20 import ardupilotmega as mavlink

from apf_companion.links.messages import ObstacleDistance3d, Source
from apf_companion.perception import HeadingTrack, PerceptionFrontEnd, PerceptionParams, euler_yaw_rate_rad_s
from apf_companion.perception.heading import MAX_EXTRAPOLATION_S

RATE = math.radians(30.0)  # a brisk turn [rad/s]


def straight_ahead(time_boot_ms: int, range_m: float) -> ObstacleDistance3d:
    """One return on the vehicle's nose (body FRD), measured at ``time_boot_ms``."""
    return ObstacleDistance3d(
        src=Source(1, 1),
        time_boot_ms=time_boot_ms,
        frame=mavlink.MAV_FRAME_BODY_FRD,
        x=range_m,
        y=0.0,
        z=0.0,
        min_distance=0.1,
        max_distance=20.0,
    )


def test_the_yaw_between_two_samples_is_interpolated_the_short_way_through_pi() -> None:
    h = HeadingTrack()
    assert h.at(1000) is None and h.latest_rad is None
    h.update(math.pi - 0.1, 1000, RATE)
    h.update(-math.pi + 0.1, 1100, RATE)  # crossed +-pi: 0.2 rad turned, not 2 pi - 0.2
    assert h.at(1050) == pytest.approx(math.pi, abs=1e-9) or h.at(1050) == pytest.approx(-math.pi, abs=1e-9)
    assert h.at(1025) == pytest.approx(math.pi - 0.05)
    assert [h.age_s(1050), h.age_s(1300), h.age_s(900)] == pytest.approx([0.0, 0.2, 0.1])


def test_a_position_newer_than_the_latest_attitude_gets_the_yaw_carried_by_the_rate_for_a_bounded_time() -> None:
    h = HeadingTrack()
    h.update(0.0, 1000, RATE)
    assert h.at(1100) == pytest.approx(0.1 * RATE)  # the usual case: 10 Hz streams, ATTITUDE sent second
    assert h.at(900) == pytest.approx(-0.1 * RATE)  # a position older than every sample
    assert h.at(5000) == pytest.approx(MAX_EXTRAPOLATION_S * RATE)  # the stream stalled: carried no further


def test_duplicates_and_reordered_samples_are_ignored_and_a_clock_restart_starts_over() -> None:
    h = HeadingTrack()
    h.update(0.0, 1000, 0.0)
    h.update(0.2, 1100, 0.0)
    h.update(0.9, 1050, 0.0)  # reordered datagram
    h.update(0.9, 1100, 0.0)  # duplicate time
    assert h.at(1100) == pytest.approx(0.2) and h.at(1050) == pytest.approx(0.1) and h.stale == 2
    h.update(-1.0, 200, 0.0)  # 0.9 s back: a late datagram, ignored
    assert h.latest_rad == pytest.approx(0.2)
    h.update(-1.0, 50, 0.0)  # more than a second back: a new boot, the old samples are on another clock
    assert h.latest_rad == -1.0 and h.at(60) == -1.0


def test_a_yaw_without_a_time_is_used_as_is_and_corrupt_fields_do_no_harm() -> None:
    h = HeadingTrack()
    h.update(0.3)
    assert h.at(123_456) == 0.3
    h.update(0.4, 1000, math.nan)
    assert h.at(1100) == 0.4
    h.update(0.5, 1100, 1e30)  # an implausible rate is no rate
    assert h.at(1200) == 0.5 and h.bad_rates == 2
    h.update(math.inf, 1200, 0.0)  # a non-finite yaw is not a sample
    assert h.latest_rad == 0.5
    h.update(3e38, 1300, 1.0)  # finite but absurd: wrapped, never overflows
    yaw = h.at(1400)
    assert yaw is not None and math.isfinite(yaw) and abs(yaw) <= math.pi
    assert math.isnan(euler_yaw_rate_rad_s(math.inf, 0.0, 0.0, 1.0))
    assert math.isnan(euler_yaw_rate_rad_s(0.0, 0.0, 0.0, math.nan))


@given(
    phi=st.floats(-0.6, 0.6),
    theta=st.floats(-0.6, 0.6),
    psi_dot=st.floats(-3.0, 3.0),
)
def test_body_rates_of_a_pure_heading_change_give_back_the_heading_rate(
    phi: float, theta: float, psi_dot: float
) -> None:
    """The simulator sends body rates (as the autopilots do); the service turns them back into psi_dot."""
    q = math.sin(phi) * math.cos(theta) * psi_dot
    r = math.cos(phi) * math.cos(theta) * psi_dot
    assert euler_yaw_rate_rad_s(phi, theta, q, r) == pytest.approx(psi_dot, abs=1e-12)


def test_in_a_turn_a_return_is_placed_on_the_surface_it_saw() -> None:
    """Vehicle at the origin turning at 30 deg/s; ATTITUDE at t, LOCAL_POSITION_NED 100 ms later (both 10 Hz).
    A return straight ahead at 10 m, measured with the position, must land 10 m along the true heading: with the
    latest yaw it landed 0.52 m to the side."""
    p = PerceptionFrontEnd(PerceptionParams())
    for k in range(5):
        att_ms = 1000 + 100 * k
        lpn_ms = att_ms + 100
        p.on_attitude(RATE * att_ms / 1000.0, time_boot_ms=att_ms, yaw_rate_rad_s=RATE)
        pose = p.on_local_position(lpn_ms, (0.0, 0.0, -5.0), 10.0 + lpn_ms / 1000.0)  # service = boot + 10 s
        assert pose is not None and pose.yaw_rad == pytest.approx(RATE * lpn_ms / 1000.0)
    t_ms = 1500  # the newest position's time
    p.on_obstacle_distance_3d(straight_ahead(t_ms, 10.0), 11.52)
    true_yaw = RATE * t_ms / 1000.0
    want = 10.0 * np.array([math.cos(true_yaw), math.sin(true_yaw)])
    got = p.points(11.52)[0, :2]
    assert float(np.linalg.norm(got - want)) < 0.01
    stale_yaw = RATE * 1.4  # what the latest ATTITUDE said when this position arrived
    old = 10.0 * np.array([math.cos(stale_yaw), math.sin(stale_yaw)])
    assert float(np.linalg.norm(old - want)) > 0.5


def test_the_front_end_counts_reordered_attitudes_and_corrupt_rates() -> None:
    p = PerceptionFrontEnd(PerceptionParams())
    p.on_attitude(0.1, time_boot_ms=2000, yaw_rate_rad_s=0.0)
    p.on_attitude(0.2, time_boot_ms=1900, yaw_rate_rad_s=0.0)  # reordered
    p.on_attitude(0.3, time_boot_ms=2100, yaw_rate_rad_s=math.inf)
    p.on_attitude(math.nan, time_boot_ms=2200)
    c = p.counters
    assert (c.stale_attitudes, c.bad_attitude_rates, c.bad_poses) == (1, 1, 1)
    pose = p.on_local_position(2150, (0.0, 0.0, -5.0), 10.0)
    assert pose is not None and pose.yaw_rad == pytest.approx(0.3)  # held, not carried by the corrupt rate


def test_without_attitude_for_a_second_the_position_flies_on_but_no_range_is_placed() -> None:
    """ATTITUDE stopped (a stream rate set to 0, a link dropping it) while LOCAL_POSITION_NED goes on: the
    navigator still gets the position, but a scan is not placed with a heading a second old (it may be turning)."""
    p = PerceptionFrontEnd(PerceptionParams())
    p.on_attitude(0.0, time_boot_ms=1000, yaw_rate_rad_s=RATE)
    assert p.on_local_position(1900, (0.0, 0.0, -5.0), 10.9) is not None and len(p.history) == 1
    pose = p.on_local_position(2100, (0.2, 0.0, -5.0), 11.1)  # 1.1 s after the last ATTITUDE
    assert pose is not None and pose.pos_ned_m[0] == 0.2
    assert p.counters.poses_without_heading == 1 and len(p.history) == 1
    p.on_obstacle_distance_3d(straight_ahead(2100, 5.0), 11.1)
    assert len(p) == 0 and p.counters.scans_without_pose == 1
    p.on_attitude(RATE * 1.2, time_boot_ms=2200, yaw_rate_rad_s=RATE)  # the stream is back
    assert p.on_local_position(2250, (0.3, 0.0, -5.0), 11.25) is not None and len(p.history) == 2


def test_the_heading_now_is_carried_to_the_autopilots_present_and_lapses_with_the_stream() -> None:
    """What the OBSTACLE_DISTANCE forwarder rotates its sectors by: the autopilot turns them back with its heading
    at arrival, not with the one of the latest ATTITUDE."""
    p = PerceptionFrontEnd(PerceptionParams())
    assert p.yaw_now(10.0) is None  # no pose: no autopilot clock yet
    p.on_attitude(0.0, time_boot_ms=1000, yaw_rate_rad_s=RATE)
    p.on_local_position(1000, (0.0, 0.0, -5.0), 10.0)  # the autopilot's 1.0 s is the service's 10.0 s
    assert p.yaw_now(10.1) == pytest.approx(0.1 * RATE)
    assert p.yaw_now(10.9) == pytest.approx(MAX_EXTRAPOLATION_S * RATE)
    assert p.yaw_now(11.1) is None  # no ATTITUDE for 1.1 s
