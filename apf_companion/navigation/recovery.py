"""What the navigator keeps through a lost link or a position reset, and how it resumes (docs/hardening.md)."""

from __future__ import annotations

import math

from apf_companion.navigation.goalslot import GoalSlot
from apf_companion.navigation.machine import StateMachine
from apf_companion.navigation.model import Counters, CycleInputs, CycleOutput, NavigatorParams, State
from apf_companion.navigation.tracking import HoldPoint, StepTracker
from apf_companion.navigation.vehicle import VehicleLink
from apf_companion.setpoint import brake

__all__ = ["Recovery"]


class Recovery:
    """The hold after a position reset, whether the pose is confirmed, and the transitions of a lost and returned
    link and of a restart mid-flight."""

    def __init__(
        self,
        params: NavigatorParams,
        *,
        machine: StateMachine,
        goal: GoalSlot,
        vehicle: VehicleLink,
        steps: StepTracker,
        hold: HoldPoint,
        counters: Counters,
    ) -> None:
        self.p = params
        self.machine = machine
        self.goal = goal
        self.vehicle = vehicle
        self.steps = steps
        self.hold = hold
        self.counters = counters
        self.hold_until_s = -math.inf  # a position reset holds until then
        self.pose_confirmed = True  # the pose gate's anchor is confirmed (set by the handler on every pose)

    def brake(self, inp: CycleInputs) -> CycleOutput:
        """The pose is not confirmed (docs/hardening.md): while flying for a goal (engaged), stop where the vehicle
        is, with no position in the setpoint; silence before that (nothing was commanded yet) and once the pose is
        stale. No hold point, step or arrival is taken from an unconfirmed pose."""
        self.steps.target = None
        self.hold.reset()
        self.counters.unconfirmed_pose_cycles += 1
        sp = brake() if inp.pose_ok and self.goal.engaged else None
        return CycleOutput(t_s=inp.now_s, state=self.machine.state, setpoint=sp, nearest_obstacle_m=inp.nearest_m)

    def holding(self, now_s: float) -> bool:
        return now_s < self.hold_until_s

    def position_reset(self, now_s: float, reason: str) -> None:
        """The old step and hold point are in the old frame: hold at the new position (a STATUSTEXT says why)."""
        self.steps.target = None
        self.hold.reset()
        self.hold_until_s = now_s + self.p.reset_hold_s
        if self.goal.route is not None and self.machine.state in (State.NAVIGATING, State.HOLDING):
            self.machine.change(now_s, State.HOLDING, f"{reason}: holding")

    def restart_hold(self, now_s: float, reason: str) -> None:
        """The service started while the vehicle flies in GUIDED / OFFBOARD: hold where it is, without a goal, until
        a fresh goal arrives (``set_route``) or the pilot takes the vehicle (IDLE)."""
        self.goal.engaged = True  # the vehicle is in our mode: a mode change by the pilot ends the hold
        self.hold.reset()
        self.machine.change(now_s, State.HOLDING, reason)

    def goalless_hold(self, inp: CycleInputs) -> CycleOutput:
        if not self.pose_confirmed:
            return self.brake(inp)
        sp = self.hold.setpoint(self.vehicle.pose, pose_fresh=inp.pose_ok)
        return CycleOutput(t_s=inp.now_s, state=self.machine.state, setpoint=sp, nearest_obstacle_m=inp.nearest_m)

    def link_dead(self, now_s: float) -> None:
        """No heartbeat: silence. The goal (flown or held) is kept (``resume_after_link_lost``), the step and hold
        forgotten."""
        machine = self.machine
        if self.vehicle.last_hb_s is None or machine.state is State.LINK_LOST:
            return
        if self.p.resume_after_link_lost and self.goal.has_goal:
            self.steps.target = None
            self.hold.reset()
            machine.change(now_s, State.LINK_LOST, "autopilot heartbeat lost: stopped sending, goal kept")
        else:
            machine.drop_goal(now_s, State.LINK_LOST, "autopilot heartbeat lost: stopped sending")

    def link_back(self, now_s: float) -> None:
        """The heartbeat is back; its mode was checked in ``autopilot_heartbeat`` (a mode not ours while engaged
        dropped the goal). Hold first: the HOLDING handler navigates on once the inputs are fresh."""
        machine, goal, vehicle = self.machine, self.goal, self.vehicle
        if goal.held is not None:  # never flown: the service checks it at the next pose
            reason = vehicle.no_pose_reason() if vehicle.pose is None else "goal checked at the next pose"
            machine.change(now_s, State.HOLDING, f"autopilot heartbeat back: {reason}")
        elif goal.route is None:
            machine.change(now_s, State.IDLE, "autopilot heartbeat back: send a new goal to fly")
        elif goal.engaged and vehicle.mode_ok:
            machine.change(now_s, State.HOLDING, "autopilot heartbeat back, guided: resuming when inputs are fresh")
        else:
            machine.go(now_s, "autopilot heartbeat back: taking over again for the goal")
