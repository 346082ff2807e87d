"""How and when a run ends: the outcome rules and the one owner of the flight's times.

``CompanionService`` asks ``FlightEnd`` each cycle (with ``exit_when_done``) whether the flight is over, and at
the end for the outcome and the flight time of its ``ServiceResult``.
"""

from __future__ import annotations

import enum

from apf_companion.navigator import Navigator, State

__all__ = ["FlightEnd", "Outcome", "outcome_now"]


class Outcome(enum.StrEnum):
    """How a run ended (``ServiceResult.outcome``)."""

    ARRIVED = "arrived"
    STUCK = "stuck"
    TIMEOUT = "timeout"
    LINK_LOST = "link_lost"
    STOPPED = "stopped"
    ERROR = "error"


_OUTCOME_OF_STATE = {State.ARRIVED: Outcome.ARRIVED, State.STUCK: Outcome.STUCK, State.LINK_LOST: Outcome.LINK_LOST}


def outcome_now(navigator: Navigator, *, goals: int, flown_s: float | None, max_s: float) -> Outcome | None:
    """How the flight ended, if it has: a final state, a dropped goal, or ``max_s`` of flight (0 = no limit)."""
    outcome = _OUTCOME_OF_STATE.get(navigator.state)
    if outcome is Outcome.LINK_LOST and navigator.route is not None:
        outcome = None  # the goal is kept: the flight goes on when the heartbeat returns
    if outcome is None and navigator.state is State.IDLE and goals > 0 and navigator.route is None:
        outcome = Outcome.ERROR  # the goal was dropped: takeover failed or the pilot took over
    if outcome is None and max_s > 0 and flown_s is not None and flown_s > max_s:
        outcome = Outcome.TIMEOUT
    return outcome


class FlightEnd:
    """When the current goal was set and navigation began, and how and when the run ended (service seconds)."""

    def __init__(self) -> None:
        self._first_nav_s: float | None = None
        self._goal_s: float | None = None
        self._end_s: float | None = None
        self.outcome: Outcome | None = None

    def goal_set(self, now: float) -> None:
        """A new goal: the flight is not over (whatever ended the last one)."""
        self.outcome = None
        self._end_s = None
        self._goal_s = now

    def navigating(self, now: float) -> None:
        """A navigation setpoint went out: the flight time counts from the first one."""
        if self._first_nav_s is None:
            self._first_nav_s = now

    def flown_s(self, now: float) -> float | None:
        return None if self._first_nav_s is None else now - self._first_nav_s

    def check(self, now: float, navigator: Navigator, *, goals: int, max_s: float) -> bool:
        """Whether the flight ended just now (``outcome_now``); an ended flight stays ended until a new goal."""
        if self.outcome is not None:
            return False
        flown = self.flown_s(now)
        if flown is None and self._goal_s is not None:
            flown = now - self._goal_s  # never navigated (no position, no ranges, no takeover): time since the goal
        outcome = outcome_now(navigator, goals=goals, flown_s=flown, max_s=max_s)
        if outcome is None:
            return False
        self.outcome, self._end_s = outcome, now
        return True

    def final(self, now: float) -> tuple[Outcome, float]:
        """The run's outcome (STOPPED if nothing ended it) and its flight time [s] at ``now`` or at its end."""
        end = self._end_s if self._end_s is not None else now
        return self.outcome or Outcome.STOPPED, max(0.0, self.flown_s(end) or 0.0)
