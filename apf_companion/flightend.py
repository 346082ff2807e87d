"""How and when a run ends: the outcome rules and the one owner of the flight's times.

``CompanionService`` asks ``FlightEnd`` each cycle whether the flight is over (with ``exit_when_done`` that ends
the run), and at the end for the outcome and the flight time of its ``ServiceResult``.
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


def outcome_now(
    navigator: Navigator,
    *,
    goals: int,
    flown_s: float | None,
    max_s: float,
    lost_s: float | None = None,
    max_lost_s: float = 0.0,
    never_heard: bool = False,
) -> Outcome | None:
    """How the flight ended, if it has: a final state, a dropped goal, ``max_s`` of flight, or ``max_lost_s`` with
    no autopilot HEARTBEAT (``lost_s``: since the last one, or since the start when it was ``never_heard``) in
    LINK_LOST with the goal kept, or before the autopilot was ever heard (0 = no limit)."""
    state = navigator.state
    if never_heard and _over(lost_s, max_lost_s):
        return Outcome.LINK_LOST  # no autopilot at all (a wrong address, a cable): nothing else will happen
    outcome = _OUTCOME_OF_STATE.get(state)
    if outcome is Outcome.LINK_LOST and navigator.has_goal and not _over(lost_s, max_lost_s):
        outcome = None  # the goal (flown or held) is kept: the flight goes on when the heartbeat returns
    if outcome is None and state is State.IDLE and goals > 0 and navigator.route is None:
        outcome = Outcome.ERROR  # the goal was dropped: takeover failed or the pilot took over
    if outcome is None and _over(flown_s, max_s):
        # Out of time with the autopilot unheard: the lost link, not the flight, is why it did not arrive.
        outcome = Outcome.LINK_LOST if state is State.LINK_LOST else Outcome.TIMEOUT
    return outcome


def _over(elapsed_s: float | None, limit_s: float) -> bool:
    """``elapsed_s`` is known and beyond ``limit_s`` (0 = no limit)."""
    return limit_s > 0 and elapsed_s is not None and elapsed_s > limit_s


class FlightEnd:
    """When the current flight began navigating and when and how it ended, and the run's outcome (service seconds).

    A flight is one goal flown to its end: from its first navigation setpoint to the state that ended it (arrived,
    stuck, link lost with the goal dropped, the goal dropped, or ``max_s`` of flight). A goal that replaces the goal
    of a flight still under way continues that flight; a goal after a flight has ended starts a new one.
    """

    def __init__(self, start_s: float = 0.0) -> None:
        self._start_s = start_s  # the run's start: an autopilot never heard is lost since then
        self._first_nav_s: float | None = None
        self._goal_s: float | None = None
        self._end_s: float | None = None
        self.ended: Outcome | None = None  # how the current flight ended; None while under way (or none yet)
        self.outcome: Outcome | None = None  # the run's outcome, once something decided it

    def goal_set(self, now: float) -> None:
        """A new goal: the flight goes on, or a new one begins if the last one had ended (not once the run's
        outcome is decided: the run is ending and its last flight stands)."""
        if self.outcome is not None:
            return
        if self._end_s is not None:
            self._first_nav_s = None  # the ended flight's time is not the new one's
        self.ended = None
        self._end_s = None
        self._goal_s = now

    def navigating(self, now: float) -> None:
        """A navigation setpoint went out: the flight time counts from the flight's first one."""
        if self._first_nav_s is None:
            self._first_nav_s = now

    def flown_s(self, now: float) -> float | None:
        return None if self._first_nav_s is None else now - self._first_nav_s

    def check(
        self,
        now: float,
        navigator: Navigator,
        *,
        goals: int,
        max_s: float,
        max_lost_s: float = 0.0,
        ends_run: bool = True,
    ) -> bool:
        """Whether the flight ended just now (``outcome_now``); an ended flight stays ended until a new goal. Its
        end stops the flight time; with ``ends_run`` (``exit_when_done``) its outcome is also the run's."""
        if self.ended is not None:
            return False
        flown = self.flown_s(now)
        if flown is None and self._goal_s is not None:
            flown = now - self._goal_s  # never navigated (no position, no ranges, no takeover): time since the goal
        lost = navigator.heartbeat_age_s(now)
        never = lost is None
        lost = now - self._start_s if lost is None else lost
        outcome = outcome_now(
            navigator, goals=goals, flown_s=flown, max_s=max_s, lost_s=lost, max_lost_s=max_lost_s, never_heard=never
        )
        if outcome is None:
            return False
        self.ended, self._end_s = outcome, now
        if ends_run:
            self.outcome = outcome
        return True

    def final(self, now: float) -> tuple[Outcome, float]:
        """The run's outcome (STOPPED if nothing decided it) and the last flight's time [s]: to its end, or to
        ``now`` (the run's end) if it had none; 0 if it never navigated."""
        end = self._end_s if self._end_s is not None else now
        return self.outcome or Outcome.STOPPED, max(0.0, self.flown_s(end) or 0.0)
