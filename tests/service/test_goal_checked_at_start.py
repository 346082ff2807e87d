"""A goal whose check needs the vehicle's position (``goal.max_distance_m``) is held, not flown, until the first
pose, then flown or refused; a refused goal at start ends an ``exit_when_done`` run with an error (no sockets:
records go straight to the handlers, the service clock is injected)."""

from __future__ import annotations

from typing import Any

from pymavlink.dialects.v20 import ardupilotmega as m

from apf_companion.config import config_from_mapping
from apf_companion.goal import FenceBounds, Route, route_check_waits
from apf_companion.links.messages import Attitude, Heartbeat, LocalPositionNed, Source
from apf_companion.navigator import State
from apf_companion.service import CompanionService
from tests.conftest import ManualClock

AP = Source(1, 1)
HELD = "goal waits for a position to check goal.max_distance_m"


def _service(route: Route, **extra: Any) -> tuple[CompanionService, ManualClock]:
    clock = ManualClock()
    cfg = config_from_mapping({"link": {"connect": "udpin:127.0.0.1:0"}, **extra})
    return CompanionService(cfg, route=route, clock=clock), clock


def _heartbeat(svc: CompanionService, clock: ManualClock) -> None:
    hb = Heartbeat(src=AP, type=m.MAV_TYPE_QUADROTOR, autopilot=3, base_mode=1, custom_mode=4, system_status=3)
    svc.handlers.handle(hb, clock.t)


def _pose(svc: CompanionService, clock: ManualClock, north_m: float = 0.0) -> None:
    clock.t += 0.1
    svc.handlers.handle(Attitude(src=AP, time_boot_ms=int(clock.t * 1000), roll=0.0, pitch=0.0, yaw=0.0), clock.t)
    pose = LocalPositionNed(src=AP, time_boot_ms=int(clock.t * 1000), x=north_m, y=0.0, z=-5.0, vx=0, vy=0, vz=0)
    svc.handlers.handle(pose, clock.t)


def test_route_check_waits_for_a_position_only_when_the_distance_limit_needs_one() -> None:
    assert route_check_waits(None, max_distance_m=2000.0) == HELD
    assert route_check_waits((0.0, 0.0, -5.0), max_distance_m=2000.0) is None
    assert route_check_waits(None, max_distance_m=0.0) is None  # 0 = no limit: nothing to wait for


def test_a_far_goal_at_start_is_held_until_the_first_pose_then_refused() -> None:
    """The bug: the goal at start is set at the first HEARTBEAT, before any pose; the distance check was skipped
    and a goal 3 km away was flown."""
    route = Route.point(3000.0, 0.0, -5.0, source="cli")
    svc, clock = _service(route)
    _heartbeat(svc, clock)
    assert svc.navigator.route is None  # not flown: nothing to check it with
    assert svc.navigator.held is route and svc.counters.goals == 0 and svc.counters.bad_goals == 0
    out = svc.run_cycle(clock.t)
    assert out.state is State.HOLDING and out.setpoint is None  # holding, silent, saying why
    _pose(svc, clock)
    assert svc.counters.bad_goals == 1 and svc.counters.goals == 0
    assert svc.navigator.held is None and svc.navigator.route is None and svc.navigator.state is State.IDLE
    out = svc.run_cycle(clock.t)
    assert out.setpoint is None and any("goal refused" in c.reason for c in out.changes)
    _pose(svc, clock)
    assert svc.counters.bad_goals == 1  # refused once


def test_a_near_goal_at_start_is_flown_at_the_first_pose() -> None:
    route = Route.point(30.0, 0.0, -5.0, source="cli")
    svc, clock = _service(route)
    _heartbeat(svc, clock)
    assert svc.navigator.held is route and svc.navigator.route is None
    _pose(svc, clock)
    assert svc.navigator.route is route and svc.navigator.state is State.NAVIGATING
    assert svc.counters.goals == 1 and svc.counters.bad_goals == 0 and svc.navigator.held is None


def test_without_a_distance_limit_the_goal_at_start_is_flown_at_once() -> None:
    route = Route.point(3000.0, 0.0, -5.0, source="cli")
    svc, clock = _service(route, goal={"max_distance_m": 0.0})
    _heartbeat(svc, clock)
    assert svc.navigator.route is route and svc.navigator.held is None


def test_a_refused_goal_at_start_ends_an_exit_when_done_run_with_an_error() -> None:
    route = Route.point(10.0, 10.0, -300.0, source="cli")  # above goal.max_altitude_m (120 m)
    svc, clock = _service(route, exit_when_done=True)
    _heartbeat(svc, clock)  # refused at once: the altitude needs no position
    assert svc.counters.bad_goals == 1
    result = svc.result()
    assert result.outcome == "error"
    assert svc._stop.is_set()


def test_a_goal_held_then_refused_ends_an_exit_when_done_run_with_an_error() -> None:
    svc, clock = _service(Route.point(3000.0, 0.0, -5.0, source="cli"), exit_when_done=True)
    _heartbeat(svc, clock)
    assert not svc._stop.is_set()
    _pose(svc, clock)
    assert svc._stop.is_set() and svc.result().outcome == "error"


def test_a_refused_goal_at_start_without_exit_when_done_leaves_the_service_idle() -> None:
    svc, clock = _service(Route.point(10.0, 10.0, -300.0, source="cli"))
    _heartbeat(svc, clock)
    assert svc.counters.bad_goals == 1 and not svc._stop.is_set()
    assert svc.result().outcome == "stopped"


class _ReadFence:
    """A fence reader whose first read has ended (only what ``GoalAdmission.recheck`` reads)."""

    def __init__(self, bounds: FenceBounds) -> None:
        self.bounds = bounds


def test_a_goal_taken_before_the_fence_was_read_is_dropped_when_it_lies_above_the_fences_ceiling() -> None:
    route = Route.point(10.0, 0.0, -40.0, source="cli")  # 40 m up: under goal.max_altitude_m
    svc, clock = _service(route)
    _heartbeat(svc, clock)
    _pose(svc, clock)
    assert svc.navigator.route is route  # flown: no fence known yet
    svc.fence = _ReadFence(FenceBounds(ceiling_m=30.0))  # type: ignore[assignment]
    svc.admission.recheck(clock.t)
    assert svc.navigator.route is None and svc.counters.bad_goals == 1
    assert any(c.new is State.IDLE and "fence's ceiling" in c.reason for c in svc.navigator.drain_changes())
    svc.admission.recheck(clock.t)  # nothing left to refuse
    assert svc.counters.bad_goals == 1


def test_a_goal_that_would_wait_is_refused_while_no_autopilot_is_heard() -> None:
    """As the navigator refuses a goal with the link lost: counted, not held (zenoh goals before any HEARTBEAT)."""
    svc, clock = _service(Route.point(1.0, 0.0, -5.0, source="cli"))
    assert not svc.admission.admit(Route.point(5.0, 5.0, -5.0, source="zenoh"), clock.t)
    assert svc.counters.bad_goals == 1 and svc.navigator.held is None and svc.navigator.state is State.IDLE


def _lose_link(svc: CompanionService, clock: ManualClock) -> list[str]:
    """No HEARTBEAT for longer than link.heartbeat_timeout_s (3 s): the cycle enters LINK_LOST. Its reasons."""
    clock.t += 4.0
    out = svc.run_cycle(clock.t)
    assert out.state is State.LINK_LOST and out.setpoint is None
    return [c.reason for c in out.changes]


def test_a_held_goal_is_dropped_at_link_loss_without_resume_after_link_lost() -> None:
    """The bug: the goal held for its check (no pose yet) outlived a link loss in the service and was flown at the
    first pose after the link came back, although ``resume_after_link_lost = false`` drops a flown goal then."""
    route = Route.point(30.0, 0.0, -5.0, source="cli")
    svc, clock = _service(route, safety={"resume_after_link_lost": False})
    _heartbeat(svc, clock)
    assert svc.run_cycle(clock.t).state is State.HOLDING and svc.navigator.held is route
    assert _lose_link(svc, clock) == ["autopilot heartbeat lost: stopped sending"]  # as a flown goal's drop
    assert svc.navigator.held is None and not svc.navigator.has_goal
    _heartbeat(svc, clock)
    out = svc.run_cycle(clock.t)
    assert out.state is State.IDLE and [c.reason for c in out.changes] == [
        "autopilot heartbeat back: send a new goal to fly"
    ]
    _pose(svc, clock)
    _pose(svc, clock)
    assert svc.navigator.route is None and svc.navigator.state is State.IDLE  # not flown
    assert svc.counters.goals == 0 and svc.counters.bad_goals == 0


def test_a_held_goal_is_kept_through_a_link_loss_with_resume_after_link_lost() -> None:
    """As a flown goal: kept while the link is lost (a pose then does not check it), checked at the first pose
    once the link is back, and flown."""
    route = Route.point(30.0, 0.0, -5.0, source="cli")
    svc, clock = _service(route)
    _heartbeat(svc, clock)
    svc.run_cycle(clock.t)
    assert _lose_link(svc, clock) == ["autopilot heartbeat lost: stopped sending, goal kept"]
    _pose(svc, clock)  # a pose while no HEARTBEAT comes: the goal waits for the link
    assert svc.navigator.held is route and svc.navigator.route is None and svc.counters.bad_goals == 0
    _heartbeat(svc, clock)
    out = svc.run_cycle(clock.t)
    assert out.state is State.HOLDING and out.setpoint is None
    assert [c.reason for c in out.changes] == ["autopilot heartbeat back: goal checked at the next pose"]
    _pose(svc, clock)
    assert svc.navigator.route is route and svc.navigator.held is None and svc.navigator.state is State.NAVIGATING
    assert svc.counters.goals == 1 and svc.counters.bad_goals == 0


def test_a_held_goal_kept_through_a_link_loss_does_not_end_an_exit_when_done_run() -> None:
    """LINK_LOST with the goal kept is not the end of the flight (``FlightEnd``), for a held goal as a flown one;
    without ``resume_after_link_lost`` the goal is gone and the run ends with outcome link_lost."""
    for resume, ended in ((True, False), (False, True)):
        svc, clock = _service(
            Route.point(30.0, 0.0, -5.0, source="cli"),
            exit_when_done=True,
            safety={"resume_after_link_lost": resume},
        )
        _heartbeat(svc, clock)
        svc.run_cycle(clock.t)
        _lose_link(svc, clock)
        assert svc._stop.is_set() is ended
        assert svc.result().outcome == ("link_lost" if ended else "stopped")


def test_the_status_shows_a_goal_held_for_its_check_and_one_not_yet_flown() -> None:
    """The status said ``"goal": null`` while a goal was held, or taken but not flown yet (its first leg starts with a
    pose): a ground station or zenoh client could not see what the vehicle was about to fly to."""
    route = Route.point(30.0, 4.0, float("nan"), source="cli")  # NaN down: keep the altitude
    svc, clock = _service(route)
    assert svc.reporter.status_dict(clock.t)["goal"] is None
    _heartbeat(svc, clock)
    goal = svc.reporter.status_dict(clock.t)["goal"]
    assert goal == {
        "north_m": 30.0, "east_m": 4.0, "down_m": None, "leg": None, "legs": 1, "source": "cli", "held": True
    }  # fmt: skip
    _pose(svc, clock)
    svc.run_cycle(clock.t)
    assert svc.navigator.route is route and svc.navigator.leg_index is None  # the takeover first: no leg yet
    goal = svc.reporter.status_dict(clock.t)["goal"]
    assert goal == {
        "north_m": 30.0, "east_m": 4.0, "down_m": None, "leg": None, "legs": 1, "source": "cli", "held": False
    }  # fmt: skip
