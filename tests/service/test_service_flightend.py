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
    assert not end.check(5.0, nav, goals=0, max_s=0.0)  # idle before any goal: not over
    assert end.check(6.0, nav, goals=1, max_s=0.0)  # a goal came and is gone: takeover failed
    assert end.outcome is Outcome.ERROR
    assert not end.check(7.0, nav, goals=1, max_s=0.0)  # ended stays ended
    end.goal_set(8.0)
    assert end.outcome is None
    assert end.final(9.0) == (Outcome.STOPPED, 0.0)  # never navigated: no flight time


def test_flight_time_counts_from_the_first_navigation_setpoint_to_the_end() -> None:
    nav, end = _idle_navigator(), FlightEnd()
    end.goal_set(1.0)
    end.navigating(3.0)
    end.navigating(4.0)  # later setpoints do not move the start
    assert end.flown_s(10.0) == 7.0
    assert end.final(10.0) == (Outcome.STOPPED, 7.0)
    assert end.check(12.0, nav, goals=1, max_s=0.0)
    assert end.final(50.0) == (Outcome.ERROR, 9.0)  # the flight time stops where the flight ended
