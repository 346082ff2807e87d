"""How and when a run ends (apf_companion/flightend.py), on a real navigator that has no goal."""

from __future__ import annotations

from apf_companion.builders import build_navigator, build_planner, perception_params
from apf_companion.config import ServiceConfig
from apf_companion.flightend import FlightEnd, Outcome
from apf_companion.navigator import Navigator, State
from apf_companion.perception import PerceptionFrontEnd


def _idle_navigator() -> Navigator:
    cfg = ServiceConfig()
    nav = build_navigator(cfg, build_planner(cfg), PerceptionFrontEnd(perception_params(cfg)))
    assert nav.state is State.IDLE and nav.route is None
    return nav


def test_a_dropped_goal_ends_the_flight_once_and_a_new_goal_reopens_it() -> None:
    nav, end = _idle_navigator(), FlightEnd()
    assert not end.check(5.0, nav, goals=0, max_s=0.0, ends_run=False)  # idle before any goal: not over
    assert end.check(6.0, nav, goals=1, max_s=0.0, ends_run=False)  # a goal came and is gone: takeover failed
    assert end.ended is Outcome.ERROR and end.outcome is None  # the flight ended, the run goes on
    assert not end.check(7.0, nav, goals=1, max_s=0.0, ends_run=False)  # ended stays ended
    end.goal_set(8.0)
    assert end.ended is None
    assert end.final(9.0) == (Outcome.STOPPED, 0.0)  # never navigated: no flight time


def test_flight_time_counts_from_the_first_navigation_setpoint_to_the_end() -> None:
    nav, end = _idle_navigator(), FlightEnd()
    end.goal_set(1.0)
    end.navigating(3.0)
    end.navigating(4.0)  # later setpoints do not move the start
    assert end.flown_s(10.0) == 7.0
    assert end.final(10.0) == (Outcome.STOPPED, 7.0)  # stopped before an outcome: to the stop
    assert end.check(12.0, nav, goals=1, max_s=0.0)  # ends_run: the flight's outcome is the run's
    assert end.final(50.0) == (Outcome.ERROR, 9.0)  # the flight time stops where the flight ended
    end.goal_set(60.0)  # the run is ending: its last flight stands
    assert end.final(70.0) == (Outcome.ERROR, 9.0)


def test_a_new_flight_counts_from_its_own_first_setpoint_and_a_replaced_goal_does_not_restart_it() -> None:
    nav, end = _idle_navigator(), FlightEnd()
    end.goal_set(1.0)
    end.navigating(2.0)
    end.goal_set(5.0)  # a new goal while flying: the same flight
    end.navigating(5.1)
    assert end.flown_s(6.0) == 4.0
    assert end.check(8.0, nav, goals=1, max_s=0.0, ends_run=False)  # ended (the goal dropped) at 8 s
    assert end.final(30.0) == (Outcome.STOPPED, 6.0)  # not until the stop at 30 s
    end.goal_set(40.0)  # a goal after the end: a new flight
    assert end.final(41.0) == (Outcome.STOPPED, 0.0)  # not navigated yet
    end.navigating(42.0)
    assert end.final(45.0) == (Outcome.STOPPED, 3.0)


def test_max_flight_counts_from_the_goal_while_navigation_never_started() -> None:
    nav, end = _idle_navigator(), FlightEnd()
    end.goal_set(1.0)
    assert not end.check(5.0, nav, goals=0, max_s=10.0)
    assert end.check(12.0, nav, goals=0, max_s=10.0) and end.outcome is Outcome.TIMEOUT
    assert end.final(20.0) == (Outcome.TIMEOUT, 0.0)
