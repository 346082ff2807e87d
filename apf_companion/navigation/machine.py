"""The navigator's state and its transitions, each with a reason (a STATUSTEXT)."""

from __future__ import annotations

import math

from apf_companion.navigation.goalslot import GoalSlot
from apf_companion.navigation.legs import Legs
from apf_companion.navigation.model import ENGAGED_STATES, HOLD_STATES, NavigatorParams, State, StateChange
from apf_companion.navigation.tracking import HoldPoint, StepTracker
from apf_companion.navigation.vehicle import VehicleLink

__all__ = ["REASON_REPEAT_S", "StateMachine"]

REASON_REPEAT_S = 1.0  # a changed HOLDING reason is announced at most this often (a flapping cause cannot flood)
SAYS_WHY_NOW = frozenset({State.HOLDING, State.WAITING_FOR_PILOT})  # states whose changed reason is announced
# WAITING_FOR_PILOT on PX4 while a failsafe is active: no holds (they would end it into OFFBOARD); fits a STATUSTEXT
FAILSAFE_WAIT_REASON = "failsafe: switch mode first"


class StateMachine:
    """The state, the changes not yet reported, and the transitions that change more than the state: dropping the
    goal, entering a holding state (a new hold point), going for a goal (or waiting for the pilot)."""

    def __init__(
        self,
        params: NavigatorParams,
        *,
        goal: GoalSlot,
        vehicle: VehicleLink,
        steps: StepTracker,
        hold: HoldPoint,
        legs: Legs,
    ) -> None:
        self.p = params
        self.goal = goal
        self.vehicle = vehicle
        self.steps = steps
        self.hold = hold
        self.legs = legs
        self.state = State.IDLE
        self._said: tuple[str, float] = ("", -math.inf)  # the last reason announced, and when
        self._pending: list[StateChange] = []

    def change(self, now_s: float, new: State, reason: str) -> None:
        if new is self.state and (new not in SAYS_WHY_NOW or _repeats(self._said, reason, now_s)):
            return  # SAYS_WHY_NOW: a new cause is announced (at most every REASON_REPEAT_S)
        self._pending.append(StateChange(t_s=now_s, old=self.state, new=new, reason=reason))
        self.state = new
        self._said = (reason, now_s)

    def drain(self) -> list[StateChange]:
        """The changes since the last drain, oldest first; clears them."""
        changes, self._pending = self._pending, []
        return changes

    def go(self, now_s: float, reason: str) -> None:
        """NAVIGATING for the goal (``reason``), or WAITING_FOR_PILOT when the pilot has to switch the mode first
        (HOLDING without a pose yet: PX4 would refuse OFFBOARD without the hold stream, and nothing can be flown)."""
        if self.pilot_must_switch() and self.vehicle.pose is None:
            self.change(now_s, State.HOLDING, self.vehicle.no_pose_reason())
        elif self.pilot_must_switch():
            self.change(now_s, State.WAITING_FOR_PILOT, self.switch_reason())
        else:
            self.change(now_s, State.NAVIGATING, reason)

    def mode_seen(self, now_s: float, *, mode_ok: bool) -> None:
        """A HEARTBEAT's mode: out of GUIDED / OFFBOARD while engaged drops the goal; in it engages the route."""
        if self.goal.engaged and not mode_ok and (self.state in ENGAGED_STATES or self.state is State.LINK_LOST):
            # The pilot (or a failsafe) took the vehicle: never fight it; wait for a new goal.
            self.drop_goal(now_s, State.IDLE, "autopilot left guided control: goal dropped")
        if mode_ok and self.goal.route is not None:
            self.goal.engaged = True
            if self.state is State.WAITING_FOR_PILOT:
                self.change(now_s, State.NAVIGATING, f"in {self.p.guided_mode}, flying to the goal")

    def drop_goal(self, now_s: float, new: State, reason: str) -> None:
        self.goal.drop()
        self.legs.leg = None
        self.hold.reset()
        self.change(now_s, new, reason)

    def enter_hold(self, now_s: float, new: State, reason: str) -> None:
        """Enter a holding state (``HOLD_STATES``): the step is dropped, the hold point fixed anew unless the state
        stays the same."""
        self.steps.target = None
        if self.state not in HOLD_STATES or new is not self.state:
            self.hold.reset()
        self.change(now_s, new, reason)

    def pilot_must_switch(self) -> bool:
        return self.goal.pilot_must_switch(takeover=self.p.takeover)

    def switch_reason(self) -> str:
        return f"switch to {self.p.guided_mode} to fly"  # "APF WAITING_FOR_PILOT: ..." fits one STATUSTEXT


def _repeats(said: tuple[str, float], reason: str, now_s: float) -> bool:
    return reason == said[0] or now_s - said[1] < REASON_REPEAT_S
