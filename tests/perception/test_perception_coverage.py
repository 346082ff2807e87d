"""Where the range sensors look in the body frame (``LookCoverage``), learnt from the scans the front end places,
and the heading that points the sensor's centre along a step (``setpoint.look_yaw``, ``navigation.Heading``)."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st
from pymavlink.dialects.v20 import ardupilotmega as mavlink

from apf_companion.links.messages import DistanceSensor, ObstacleDistance, Source
from apf_companion.navigation.heading import Heading
from apf_companion.perception import PerceptionFrontEnd, PerceptionParams
from apf_companion.perception.coverage import LookCoverage, wrap_pi_upper
from apf_companion.setpoint import hold, look_yaw, navigate

SRC = Source(1, 1)
U16 = 65535


def _arc(first_deg: float, sectors: int, increment_deg: float = 10.0) -> tuple[np.ndarray, float]:
    """Body bearings [rad] of ``sectors`` elements from ``first_deg``, and their half width."""
    deg = first_deg + increment_deg * np.arange(sectors)
    return np.deg2rad(deg), math.radians(increment_deg / 2.0)


def _offset_deg(cov: LookCoverage, now_s: float = 0.0) -> float:
    return math.degrees(cov.offset_rad(now_s))


@pytest.mark.parametrize(
    ("first_deg", "want_deg"),
    [
        (-40.0, 0.0),  # nose: -45..45
        (140.0, 180.0),  # rear: 135..225, +pi
        (50.0, 90.0),  # right side
        (-130.0, -90.0),  # left side
        (170.0, -150.0),  # wraps: 170, 180, ..., 250 (= -110) -> 165..255, centre 210 = -150
    ],
)
def test_the_offset_is_the_centre_of_the_covered_arc(first_deg: float, want_deg: float) -> None:
    cov = LookCoverage(max_age_s=1.0)
    bearings, hw = _arc(first_deg, 9)
    cov.note(bearings, hw, 0.0)
    assert _offset_deg(cov) == pytest.approx(want_deg, abs=1.0)
    assert wrap_pi_upper(math.radians(first_deg + 40.0)) == pytest.approx(math.radians(want_deg))  # middle element


def test_a_rear_arc_is_plus_pi_and_an_arc_across_plus_minus_170_too() -> None:
    cov = LookCoverage(max_age_s=1.0)
    cov.note(np.deg2rad([170.0, 175.0, 180.0, -175.0, -170.0]), math.radians(2.5), 0.0)  # 167.5..192.5
    assert cov.offset_rad(0.0) == pytest.approx(math.pi, abs=math.radians(1.0))
    assert cov.offset_rad(0.0) > 0.0  # (-pi, pi]
    cov = LookCoverage(max_age_s=1.0)
    cov.note(np.deg2rad([-170.0, 170.0]), math.radians(10.0), 0.0)  # given out of order: 160..200
    assert cov.offset_rad(0.0) == pytest.approx(math.pi, abs=math.radians(1.0))


def test_full_coverage_or_none_is_the_nose() -> None:
    cov = LookCoverage(max_age_s=1.0)
    assert cov.offset_rad(0.0) == 0.0  # no readings yet
    bearings, hw = _arc(0.0, 72, 5.0)
    cov.note(bearings, hw, 0.0)
    assert cov.offset_rad(0.0) == 0.0
    # All round but for a gap (unknown or too-close sectors at the side): still all round, no turn.
    cov = LookCoverage(max_age_s=1.0)
    keep = np.ones(72, dtype=bool)
    keep[14:22] = False  # 70..110 deg unread: 320 deg covered
    cov.note(bearings[keep], hw, 0.0)
    assert cov.offset_rad(0.0) == 0.0
    cov = LookCoverage(max_age_s=1.0)
    cov.note_all(0.0)
    assert cov.offset_rad(0.0) == 0.0


def test_readings_age_out_with_the_sectors_limit() -> None:
    cov = LookCoverage(max_age_s=1.0)
    cov.note(*_arc(140.0, 9), 10.0)
    assert _offset_deg(cov, 11.0) == pytest.approx(180.0, abs=1.0)
    assert cov.offset_rad(11.01) == 0.0  # stale: the nose, as without readings
    cov.note(*_arc(-130.0, 9), 11.5)  # the sensor now reads on the left only
    assert _offset_deg(cov, 12.0) == pytest.approx(-90.0, abs=1.0)


def test_two_equal_arcs_the_one_nearest_the_nose_wins_a_wider_one_wins_outright() -> None:
    cov = LookCoverage(max_age_s=1.0)
    cov.note(*_arc(140.0, 9), 0.0)  # rear 135..225
    cov.note(*_arc(-40.0, 9), 0.0)  # front -45..45
    assert cov.offset_rad(0.0) == 0.0
    cov = LookCoverage(max_age_s=1.0)
    cov.note(*_arc(120.0, 13), 0.0)  # rear 115..245: 40 deg wider
    cov.note(*_arc(-40.0, 9), 0.0)
    assert _offset_deg(cov) == pytest.approx(180.0, abs=1.0)


def test_single_beams_cover_their_own_bin() -> None:
    cov = LookCoverage(max_age_s=1.0)
    cov.note([math.pi], 0.0, 0.0)
    assert _offset_deg(cov) == pytest.approx(180.0, abs=1.0)


def test_bad_input_is_ignored_and_never_gives_a_non_finite_offset() -> None:
    cov = LookCoverage(max_age_s=1.0)
    cov.note([math.nan, math.inf, -math.inf], 0.1, 0.0)
    cov.note([], 0.1, 0.0)
    cov.note([1.0], 0.1, math.nan)
    assert cov.offset_rad(0.0) == 0.0
    cov.note([math.pi / 2, math.nan], math.nan, 0.0)  # a non-finite width: a single beam
    assert _offset_deg(cov) == pytest.approx(90.0, abs=1.0)
    cov.note([1e12], -3.0, 0.0)  # far outside (-pi, pi]: wrapped; a negative width: a single beam
    assert math.isfinite(cov.offset_rad(0.0))
    assert math.isfinite(cov.offset_rad(math.nan)) and math.isfinite(cov.offset_rad(math.inf))


@given(
    bearings=st.lists(st.floats(allow_nan=True, allow_infinity=True, width=64), max_size=80),
    hw=st.floats(allow_nan=True, allow_infinity=True),
    t=st.floats(allow_nan=True, allow_infinity=True),
)
def test_the_offset_is_always_finite_and_wrapped(bearings: list[float], hw: float, t: float) -> None:
    cov = LookCoverage(max_age_s=1.0)
    cov.note(bearings, hw, t)
    off = cov.offset_rad(t if math.isfinite(t) else 0.0)
    assert math.isfinite(off) and -math.pi < off <= math.pi


def test_look_yaw_turns_the_sensor_centre_onto_the_bearing() -> None:
    assert look_yaw(math.pi / 2, 0.0) == pytest.approx(math.pi / 2)  # nose sensor: the bearing
    assert look_yaw(math.pi / 2, math.pi) == pytest.approx(-math.pi / 2)  # rear sensor: tail first
    assert look_yaw(0.0, math.pi / 2) == pytest.approx(-math.pi / 2)  # right-side sensor
    assert look_yaw(0.0, math.pi) == pytest.approx(math.pi)  # (-pi, pi]
    assert look_yaw(1.0, math.nan) == 1.0  # a non-finite offset counts as the nose


def test_heading_applies_the_look_offset_to_steps_and_keeps_it_on_holds() -> None:
    h = Heading()
    pos = np.array([0.0, 0.0, -5.0])
    sp = h.apply(navigate(pos, [0.0, 1.0, -5.0], cruise_speed_m_s=1.0, dim=2), pos, math.pi)  # east, rear sensor
    assert sp is not None and sp.yaw_rad == pytest.approx(-math.pi / 2)  # facing west
    held = h.apply(hold(pos), pos, math.pi)
    assert held is not None and held.yaw_rad == pytest.approx(-math.pi / 2)
    sp = h.apply(navigate(pos, [0.0, 1.0, -5.0], cruise_speed_m_s=1.0, dim=2), pos, math.nan)
    assert sp is not None and sp.yaw_rad == pytest.approx(math.pi / 2)


# Through the front end: the body bearings after the mount yaw, from OBSTACLE_DISTANCE and DISTANCE_SENSOR.


def _front(**kw: float) -> PerceptionFrontEnd:
    p = PerceptionFrontEnd(PerceptionParams(sectors=16, **kw))  # type: ignore[arg-type]
    p.on_attitude(0.3)  # any heading: body-frame readings do not depend on it
    p.on_local_position(1000, (0.0, 0.0, -5.0), 10.0)
    return p


def _od(
    first_deg: float,
    sectors: int = 9,
    *,
    increment: float = 10.0,
    frame: int = mavlink.MAV_FRAME_BODY_FRD,
) -> ObstacleDistance:
    """``sectors`` readings of 5 m from ``first_deg`` (body or north) at ``increment`` [deg], the rest unknown."""
    return ObstacleDistance(
        src=SRC,
        time_usec=1_000_000,
        distances=(500,) * sectors + (U16,) * (72 - sectors),
        increment=0,
        min_distance=20,
        max_distance=800,
        increment_f=increment,
        angle_offset=first_deg,
        frame=frame,
    )


@pytest.mark.parametrize(
    ("first_deg", "mount_deg", "want_deg"), [(-40.0, 0.0, 0.0), (140.0, 0.0, 180.0), (-40.0, 90.0, 90.0)]
)
def test_obstacle_distance_angle_offset_and_mount_yaw_set_the_offset(
    first_deg: float, mount_deg: float, want_deg: float
) -> None:
    p = _front(obstacle_distance_mount_yaw_rad=math.radians(mount_deg))
    assert p.look_offset_rad(10.0) == 0.0
    p.on_obstacle_distance(_od(first_deg), 10.0)
    assert math.degrees(p.look_offset_rad(10.0)) == pytest.approx(want_deg, abs=1.0)
    assert p.look_offset_rad(11.5) == 0.0  # stale after sector_max_age_s


def test_a_north_aligned_scan_is_turned_into_the_body_frame_with_the_yaw_at_its_time() -> None:
    p = _front()  # heading 0.3 rad
    p.on_obstacle_distance(_od(140.0 + math.degrees(0.3), frame=mavlink.MAV_FRAME_LOCAL_NED), 10.0)
    assert math.degrees(p.look_offset_rad(10.0)) == pytest.approx(180.0, abs=1.5)


def test_a_rear_distance_sensor_beam_is_a_rear_offset() -> None:
    p = _front()
    msg = DistanceSensor(
        src=SRC,
        time_boot_ms=1000,
        min_distance=20,
        max_distance=800,
        current_distance=300,
        orientation=mavlink.MAV_SENSOR_ROTATION_YAW_180,
        quaternion=(0.0, 0.0, 0.0, 0.0),
    )
    p.on_distance_sensor(msg, 10.0)
    assert math.degrees(p.look_offset_rad(10.0)) == pytest.approx(180.0, abs=1.0)


def test_bad_scans_are_counted_and_leave_the_offset_alone() -> None:
    p = _front()
    p.on_obstacle_distance(_od(140.0), 10.0)
    bad = p.counters.bad_scans
    p.on_obstacle_distance(_od(math.nan), 10.0)  # NaN angle_offset
    p.on_obstacle_distance(_od(math.inf), 10.0)
    p.on_obstacle_distance(_od(0.0, increment=math.nan), 10.0)
    p.on_obstacle_distance(_od(0.0, increment=0.0), 10.0)  # increment 0: no sectors
    assert p.counters.bad_scans == bad + 4
    p.on_obstacle_distance(_od(0.0, sectors=0), 10.0)  # every sector unknown: no news
    assert math.degrees(p.look_offset_rad(10.0)) == pytest.approx(180.0, abs=1.0)
    p.on_obstacle_distance(_od(1e9 + 140.0), 10.0)  # an angle offset far out of range is wrapped
    assert math.isfinite(p.look_offset_rad(10.0))
