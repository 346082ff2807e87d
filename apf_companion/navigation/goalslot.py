"""The navigator's goal: none, ``held`` (taken, not flown until the service can check it) or ``route`` (flown);
never both."""

from __future__ import annotations

from apf_companion.goal import Route

__all__ = ["GoalSlot"]


class GoalSlot:
    """The goal, and whether the autopilot has been seen in GUIDED / OFFBOARD for it (``engaged``)."""

    def __init__(self) -> None:
        self.route: Route | None = None  # the goal flown
        self.held: Route | None = None  # a goal taken but not flown until it can be checked (``hold``)
        self.engaged = False  # the autopilot has been seen in GUIDED/OFFBOARD for this route

    @property
    def has_goal(self) -> bool:
        """A goal is flown (``route``) or held for its check (``held``)."""
        return self.taken is not None

    @property
    def taken(self) -> Route | None:
        """The goal taken: the one flown, or the one held for its check (never both)."""
        return self.route if self.route is not None else self.held

    def fly(self, route: Route, *, engaged: bool) -> None:
        """Fly ``route`` (replacing a flown or held goal); ``engaged``: the autopilot is in its mode already."""
        self.route, self.held = route, None
        self.engaged = engaged

    def hold(self, route: Route) -> None:
        """Hold ``route`` for its check (one goal: a flown one has a pose, so it is not held, in practice)."""
        self.route, self.held = None, route

    def drop(self) -> None:
        self.route, self.held = None, None
        self.engaged = False

    def pilot_must_switch(self, *, takeover: bool) -> bool:
        """A goal the service may not take over for (``takeover`` off) and the autopilot not seen in its mode."""
        return not takeover and self.route is not None and not self.engaged
