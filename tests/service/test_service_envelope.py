"""The braking envelope: where the vehicle can be (its reported velocity, the autopilot's braking), not where the
setpoint is (apf_companion.envelope, docs/hardening.md "Tracking margin")."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from apf_companion.config import CycleConfig, PlannerConfig, SafetyConfig, ServiceConfig
from apf_companion.envelope import (
    BrakingEnvelope,
    free_distance_m,
    polyline_distance_m,
    stoppable_speed_m_s,
    stopping_distance_m,
)
from apf_companion.errors import ConfigError
from apf_companion.goal import Route
from apf_companion.navigator import Navigator, State
from apf_companion.perception import PerceptionFrontEnd, PerceptionParams, Pose
from apf_companion.service import build_navigator, build_planner
from apf_companion.setpoint import SetpointKind

ENV = BrakingEnvelope(accel_m_s2=2.5, latency_s=0.5, clearance_m=0.35)


@given(st.floats(0.0, 50.0), st.floats(0.1, 10.0), st.floats(0.0, 2.0))
@settings(max_examples=200, deadline=None)
def test_stoppable_speed_is_the_inverse_of_the_stopping_distance(free_m: float, a: float, t: float) -> None:
    v = stoppable_speed_m_s(free_m, a, t)
    assert v >= 0.0
    assert stopping_distance_m(v, a, t) == pytest.approx(free_m, abs=1e-9)


def test_stoppable_speed_numbers() -> None:
    # 2.5 m/s^2 after 0.5 s: 0.55 m of room allows -1.25 + sqrt(1.5625 + 2.75) = 0.827 m/s.
    assert stoppable_speed_m_s(0.55, 2.5, 0.5) == pytest.approx(-1.25 + math.sqrt(1.5625 + 2.75))
    assert stoppable_speed_m_s(0.0, 2.5, 0.5) == 0.0
    assert stoppable_speed_m_s(-1.0, 2.5, 0.5) == 0.0


def test_free_distance_of_a_disc_along_a_ray() -> None:
    o = np.zeros(2)
    east = np.array([0.0, 1.0])
    assert free_distance_m(o, east, np.array([[0.0, 2.0]]), 0.35) == pytest.approx(2.0 - 0.35)
    off = free_distance_m(o, east, np.array([[0.2, 2.0]]), 0.35)
    assert off == pytest.approx(2.0 - math.sqrt(0.35**2 - 0.2**2))
    assert math.isinf(free_distance_m(o, east, np.array([[0.0, -2.0]]), 0.35))  # behind
    assert math.isinf(free_distance_m(o, east, np.array([[0.5, 2.0]]), 0.35))  # passes wide
    assert math.isinf(free_distance_m(o, east, np.zeros((0, 2)), 0.35))


def test_polyline_distance() -> None:
    line = np.array([[0.0, 0.0], [0.0, 2.0], [2.0, 2.0]])
    assert polyline_distance_m(line, np.array([[0.3, 1.0]])) == pytest.approx(0.3)
    assert polyline_distance_m(line, np.array([[1.0, 2.4]])) == pytest.approx(0.4)
    assert polyline_distance_m(line, np.array([[-1.0, -1.0], [5.0, 5.0]])) == pytest.approx(math.sqrt(2.0))


def test_speed_cap_falls_towards_an_obstacle_on_the_line_and_is_off_without_one() -> None:
    pos = np.array([0.0, 0.0, -5.0])
    wall = np.array([[0.0, y, -5.0] for y in (1.0, 2.0, 4.0)])
    near = ENV.speed_cap_m_s(pos, np.array([0.0, 1.0, 0.0]), wall)
    assert near == pytest.approx(stoppable_speed_m_s(1.0 - 0.35, 2.5, 0.5))
    far = ENV.speed_cap_m_s(pos - np.array([0.0, 2.0, 0.0]), np.array([0.0, 1.0, 0.0]), wall)
    assert far > near
    assert math.isinf(ENV.speed_cap_m_s(pos, np.array([1.0, 0.0, 0.0]), wall))  # along, not towards
    off = BrakingEnvelope(accel_m_s2=0.0, latency_s=0.5, clearance_m=0.35)
    assert math.isinf(off.speed_cap_m_s(pos, np.array([0.0, 1.0, 0.0]), wall))


def test_breach_follows_the_command_and_the_reported_velocity() -> None:
    pos = np.array([0.0, 0.0, -5.0])
    wall = np.array([[n, 2.0, -5.0] for n in np.arange(-3.0, 3.01, 0.2)])  # a wall 2.0 m east
    fast_east = np.array([0.0, 2.0, 0.0])
    # 1.0 m in the 0.5 s latency, then on east: inside the clearance before it can stop.
    assert ENV.breaches(pos, fast_east, np.array([0.0, 1.0, 0.0]), wall)
    # Even turning west at once it comes to 2.0 - 1.0 - 0.8 = 0.2 m (braking 2 m/s at 2.5 m/s^2 takes 0.8 m).
    assert ENV.breaches(pos, fast_east, np.array([0.0, -1.0, 0.0]), wall)
    # Slower, the same turn keeps the clearance: 0.25 + 0.05 m, 1.7 m from the wall.
    assert not ENV.breaches(pos, np.array([0.0, 0.5, 0.0]), np.array([0.0, -0.5, 0.0]), wall)
    # No reported velocity, or moving along the wall: nothing to count.
    assert not ENV.breaches(pos, None, np.array([0.0, 1.0, 0.0]), wall)
    assert not ENV.breaches(pos, np.array([1.0, 0.0, 0.0]), np.array([1.0, 0.0, 0.0]), wall)


def test_inside_the_clearance_already_moving_along_the_wall_is_free() -> None:
    """Noise pushed the vehicle to 0.3 m of a wall: moving along it (not closer) is not braked or capped."""
    pos = np.array([0.0, 0.0, -5.0])
    wall = np.array([[n, 0.3, -5.0] for n in np.arange(-3.0, 3.01, 0.1)])
    north = np.array([1.0, 0.0, 0.0])
    assert not ENV.breaches(pos, north, north, wall)
    assert math.isinf(ENV.speed_cap_m_s(pos, north, wall))


def navigator(brake_accel_m_s2: float = 2.5) -> tuple[Navigator, PerceptionFrontEnd]:
    cfg = ServiceConfig(safety=SafetyConfig(brake_accel_m_s2=brake_accel_m_s2))
    perception = PerceptionFrontEnd(PerceptionParams(memory_expiry_s=30.0, merge_radius_m=0.1))
    nav = build_navigator(cfg, build_planner(cfg), perception)
    nav.rng = np.random.default_rng(1)
    return nav, perception


def test_service_config_builds_the_envelope_from_radius_and_margin() -> None:
    nav, _ = navigator()
    assert nav.params.brake_accel_m_s2 == 2.5 and nav.params.brake_latency_s == 0.5
    assert nav.params.tracking_clearance_m == pytest.approx(0.25 + 0.1)  # vehicle radius + safety margin
    with pytest.raises(ConfigError, match=r"safety\.brake_accel_m_s2"):
        SafetyConfig(brake_accel_m_s2=-1.0)


def cycle_with_velocity(brake_accel_m_s2: float) -> tuple[Navigator, SetpointKind]:
    """Flying north along a wall 1.5 m to the east, while the vehicle is carried east at 1.5 m/s (a gust, or an
    autopilot that overshot): it reaches 0.3 m of the wall even braking now (0.75 m in the 0.5 s latency, 0.45 m
    braking at 2.5 m/s^2); the planned step north only adds to that."""
    nav, perception = navigator(brake_accel_m_s2)
    t = 1.0
    wall = np.array([[n, 1.5, -5.0] for n in np.arange(-4.0, 12.0, 0.2)])
    nav.autopilot_heartbeat(t, mode_ok=True)
    nav.update_pose(
        Pose(t_s=t, pos_ned_m=np.array([0.0, 0.0, -5.0]), yaw_rad=0.0, vel_ned_m_s=np.array([0.0, 1.5, 0.0]))
    )
    perception.remember(wall, t)
    assert nav.set_route(Route.point(10.0, 0.0, -5.0, source="test"), t)
    out = nav.cycle(t)
    assert out.state is State.NAVIGATING and out.setpoint is not None
    return nav, out.setpoint.kind


def test_navigator_counts_a_reported_velocity_that_could_breach_the_clearance() -> None:
    nav, kind = cycle_with_velocity(2.5)
    assert kind is SetpointKind.NAVIGATE  # counted, the plan is flown
    assert nav.counts()["envelope_warnings"] == 1


def test_navigator_without_the_envelope_counts_nothing() -> None:
    nav, kind = cycle_with_velocity(0.0)
    assert kind is SetpointKind.NAVIGATE
    assert nav.counts()["envelope_warnings"] == 0


@pytest.mark.parametrize("sight_m", [0.0, 8.0])
def test_feed_forward_never_exceeds_the_stoppable_speed(sight_m: float) -> None:
    """A fast cruise (3 m/s) along a line towards a wall: every feed-forward can still stop 0.35 m short.

    With the escape by sight (``nav_sight_m`` 8, the default) bapf-nav turns for the wall's end from 8 m away;
    without it (a wall seen late, or one that is not a surface) it drives at the wall and the cap must act."""
    planner = PlannerConfig(name="bapf-nav", params={"nav_sight_m": sight_m})
    cfg = ServiceConfig(cycle=CycleConfig(cruise_speed_m_s=3.0), planner=planner)
    perception = PerceptionFrontEnd(PerceptionParams(memory_expiry_s=30.0, merge_radius_m=0.1))
    nav = build_navigator(cfg, build_planner(cfg), perception)
    nav.rng = np.random.default_rng(1)
    wall = np.array([[6.0, e, -5.0] for e in np.arange(-6.0, 6.01, 0.2)])  # across the way, 6 m north
    env = BrakingEnvelope(accel_m_s2=2.5, latency_s=0.5, clearance_m=0.35)
    pos, t, capped = np.array([0.0, 0.0, -5.0]), 0.0, 0
    nav.autopilot_heartbeat(t, mode_ok=True)
    nav.update_pose(Pose(t_s=t, pos_ned_m=pos, yaw_rad=0.0))
    assert nav.set_route(Route.point(10.0, 0.0, -5.0, source="test"), t)
    for _ in range(60):
        t += 0.1
        nav.autopilot_heartbeat(t, mode_ok=True)
        nav.update_pose(Pose(t_s=t, pos_ned_m=pos, yaw_rad=0.0))
        perception.remember(wall, t)
        out = nav.cycle(t)
        sp = out.setpoint
        if sp is None or sp.kind is not SetpointKind.NAVIGATE:
            continue
        vel = np.array(sp.vel_ned_m_s)
        cap = env.speed_cap_m_s(pos, np.array(sp.pos_ned_m) - pos, wall)
        assert float(np.linalg.norm(vel[:2])) <= cap + 1e-9
        capped += int(cap < 3.0)
        pos = np.array(sp.pos_ned_m)
    if sight_m == 0.0:
        assert nav.counts()["envelope_caps"] > 0 and capped > 0


def test_reported_velocity_reaches_the_pose_and_bad_ones_are_counted() -> None:
    fe = PerceptionFrontEnd(PerceptionParams())
    fe.on_attitude(0.0)
    pose = fe.on_local_position(1000, (0.0, 0.0, -5.0), 1.0, vel_ned_m_s=(0.5, -0.2, 0.0))
    assert pose is not None and pose.vel_ned_m_s is not None
    assert pose.vel_ned_m_s.tolist() == [0.5, -0.2, 0.0]
    nan = fe.on_local_position(1100, (0.05, 0.0, -5.0), 1.1, vel_ned_m_s=(math.nan, 0.0, 0.0))
    fast = fe.on_local_position(1200, (0.1, 0.0, -5.0), 1.2, vel_ned_m_s=(300.0, 0.0, 0.0))
    assert nan is not None and nan.vel_ned_m_s is None  # the pose is kept, without a velocity
    assert fast is not None and fast.vel_ned_m_s is None
    assert fe.counters.bad_velocities == 2
