"""Taking control of the autopilot for a goal: GUIDED (ArduCopter) / OFFBOARD (PX4), and arm / take off on request.

A pure state machine: no clock, no sockets. The service steps it with the time and a snapshot of what it knows
(``TakeoverInputs``) on a tick (``poll_interval_s``) and gets back the ``Action``s to carry out: commands to send,
the navigator to suspend or resume, and how it went. Each phase waits for its condition, resends its command every
``COMMAND_RETRY_S`` and fails after its timeout, or at once when the goal it works for is replaced.

Order (ArduPilot's ``mode_guided.cpp`` takes off only in GUIDED; PX4's commander accepts OFFBOARD only after
setpoints have streamed for a while, ``offboard_prestream_s``):

- [no position yet: READY, waiting (at most ``ready_timeout_s``) for fresh inputs and an EKF with a horizontal
  position: ArduCopter refuses GUIDED and arming before its EKF origin (``mode.cpp`` "requires position",
  ``AP_Arming_Copter.cpp`` "Need Position Estimate")], then
- arm requested and disarmed: [ArduPilot: GUIDED] -> ARMING -> [takeoff_alt_m > 0: [PX4: GLOBAL_POSITION] ->
  TAKEOFF] with the navigator suspended (no setpoints), then
- [PX4: PRESTREAM] -> MODE (GUIDED / OFFBOARD confirmed by HEARTBEAT.custom_mode) -> done.

NAV_TAKEOFF is resent only while it has not been ACCEPTED since the phase began and the vehicle is not climbing
(a takeoff climbs for seconds; a second NAV_TAKEOFF while it climbs fails on ArduCopter: not landed).
"""

from __future__ import annotations

import enum
import math
from collections.abc import Mapping
from dataclasses import dataclass, field

from pymavlink.dialects.v20 import ardupilotmega as mavlink

from apf_companion.autopilot import Autopilot, guided_mode_name

__all__ = [
    "COMMAND_RETRY_S",
    "HARD_TIMEOUT_FACTOR",
    "HEARTBEATS_TO_FAIL",
    "TAKEOFF_CLIMBING_M",
    "Action",
    "ActionKind",
    "Phase",
    "PhaseEvidence",
    "Prestream",
    "TakeoverController",
    "TakeoverInputs",
    "TakeoverParams",
]

COMMAND_RETRY_S = 1.0  # resend an unconfirmed mode/arm/takeoff command after this long (vehicle seconds)
TAKEOFF_REACHED_FRACTION = 0.9  # takeoff counts as done at this fraction of the target height
PRESTREAM_GAP_S = 0.5  # setpoints further apart than this restart the pre-stream
IDLE_POLL_S = 0.05  # tick while waiting for a goal to take over for
ACTIVE_POLL_S = 0.02  # tick while a phase waits for its condition
TAKEOFF_S_PER_M = 4.0  # the takeoff phase's timeout grows by this much per metre of height
TAKEOFF_CLIMBING_M = 0.1  # above the start: the takeoff is under way, NAV_TAKEOFF is not resent
PRESTREAM_EXTRA_S = 5.0  # the pre-stream phase may take this much longer than a mode change
# GUIDED / OFFBOARD and arming are confirmed only by the autopilot's HEARTBEAT (1 Hz). Past its deadline such a
# phase fails only once the autopilot has answered its command (COMMAND_ACK) and this many HEARTBEATs since then
# said "not yet" (since the phase began, for a refusal). On a lossy link the commands, their answers or the
# HEARTBEATs may all have been lost so far, and it waits on, resending, up to HARD_TIMEOUT_FACTOR times its timeout.
HEARTBEATS_TO_FAIL = 3
HARD_TIMEOUT_FACTOR = 2.0


class Phase(enum.Enum):
    IDLE = "idle"
    READY = "position estimate"
    MODE_BEFORE_ARM = "mode before arming"
    ARMING = "arming"
    GLOBAL_POSITION = "global position"
    TAKEOFF = "takeoff"
    PRESTREAM = "setpoint pre-stream"
    MODE = "mode"


class ActionKind(enum.Enum):
    SET_MODE = "set_mode"  # send DO_SET_MODE for GUIDED / OFFBOARD
    ARM = "arm"  # send COMPONENT_ARM_DISARM(1)
    TAKEOFF = "takeoff"  # send NAV_TAKEOFF with param7 = ``value`` (ArduCopter: above home; PX4: AMSL) [m]
    SUSPEND = "suspend"  # navigator: no setpoints (arming, taking off)
    RESUME = "resume"  # navigator: setpoints again
    STARTED = "started"
    AIRBORNE = "airborne"  # ``value``: the target down [m]
    DONE = "done"
    FAILED = "failed"  # ``reason``: the goal it worked for is dropped
    ABANDONED = "abandoned"  # ``reason``: the goal it worked for was replaced or dropped; the next goal starts anew


@dataclass(frozen=True, slots=True)
class Action:
    kind: ActionKind
    value: float = math.nan
    reason: str = ""


@dataclass(frozen=True, slots=True, kw_only=True)
class TakeoverParams:
    enabled: bool = True  # autopilot.takeover and not dry_run
    profile: Autopilot = Autopilot.ARDUPILOT
    arm: bool = False
    takeoff_alt_m: float = 0.0
    mode_timeout_s: float = 5.0
    offboard_prestream_s: float = 1.3
    ready_timeout_s: float = 90.0


@dataclass(frozen=True, slots=True, kw_only=True)
class TakeoverInputs:
    """What the controller sees at a tick.

    Attributes:
        navigating: The navigator is NAVIGATING.
        engaged: The autopilot has been seen in GUIDED/OFFBOARD for the current goal.
        route: The current goal (compared by identity), or None.
        mode_ok: The latest autopilot HEARTBEAT's custom_mode is GUIDED (ArduPilot) / OFFBOARD (PX4).
        armed: The latest autopilot HEARTBEAT has MAV_MODE_FLAG_SAFETY_ARMED.
        down_m: The vehicle's down (local NED) [m], None without a pose.
        home_amsl_m: Home altitude AMSL from GLOBAL_POSITION_INT (alt - relative_alt) [m], None until heard.
        waiting: The navigator holds for a goal it has not taken over for yet because its inputs are missing (no
            pose yet: the takeover starts and waits in READY).
        ekf_ready: The autopilot's EKF has a horizontal position (True when it does not report one).
        heartbeats: Autopilot HEARTBEATs heard so far, or None (not counted: the deadline alone decides).
        acks: The latest COMMAND_ACK to us per command: (MAV_RESULT, service time).
            - A mode or arm phase whose command has had no answer since it began does not fail before its hard
              limit (the commands or the answers were lost). ArduCopter ACKs DO_SET_MODE ACCEPTED only when the
              mode was set (GCS_Common.cpp ``_set_mode_common``), PX4 only when the transition was not denied
              (Commander.cpp).
            - COMPONENT_ARM_DISARM ACCEPTED since the arming phase began is proof of arming. The takeover only
              ever sends arm (param1 = 1), and both autopilots ACK that ACCEPTED only when the vehicle is armed
              (ArduCopter/GCS_Mavlink.cpp: when arming succeeded or it already was; PX4
              src/modules/commander/Commander.cpp: when the arming transition was not denied).
            - NAV_TAKEOFF ACCEPTED since the takeoff phase began: the takeoff is under way, not resent.
    """

    navigating: bool
    engaged: bool
    route: object | None
    mode_ok: bool
    armed: bool
    down_m: float | None = None
    home_amsl_m: float | None = None
    waiting: bool = False
    ekf_ready: bool = True
    heartbeats: int | None = None
    acks: Mapping[int, tuple[int, float]] = field(default_factory=dict)


# The phases confirmed only by HEARTBEAT, and the command each sends.
_HEARTBEAT_PHASES = {
    Phase.MODE: mavlink.MAV_CMD_DO_SET_MODE,
    Phase.MODE_BEFORE_ARM: mavlink.MAV_CMD_DO_SET_MODE,
    Phase.ARMING: mavlink.MAV_CMD_COMPONENT_ARM_DISARM,
}


class PhaseEvidence:
    """One phase's evidence: when it began, and for a phase confirmed only by HEARTBEAT (``command``: the command it
    sends) the HEARTBEATs heard when it began and when its command's ACCEPTED was first seen."""

    def __init__(self, command: int | None, start_s: float) -> None:
        self.command = command
        self.start_s = start_s
        self._hb_at_enter: int | None = None  # HEARTBEATs heard when the phase began
        self._accepted_s: float | None = None  # the phase's command ACCEPTED at (service time), as first seen
        self._hb_at_accepted: int | None = None  # HEARTBEATs heard when that ACK was first seen

    def accepted(self, inp: TakeoverInputs, command: int) -> bool:
        """``command``'s latest ACK since the phase began said ACCEPTED."""
        ack = inp.acks.get(command)
        return ack is not None and ack[0] == mavlink.MAV_RESULT_ACCEPTED and ack[1] >= self.start_s

    def note(self, inp: TakeoverInputs) -> None:
        """A tick: count the HEARTBEATs from the first one in the phase, and from the ACCEPTED when first seen."""
        if self._hb_at_enter is None:
            self._hb_at_enter = inp.heartbeats
        ack = self._answer(inp)
        if ack is not None and ack[0] == mavlink.MAV_RESULT_ACCEPTED and ack[1] != self._accepted_s:
            self._accepted_s, self._hb_at_accepted = ack[1], inp.heartbeats

    def _answer(self, inp: TakeoverInputs) -> tuple[int, float] | None:
        """The autopilot's latest answer to this phase's command since the phase began, or None."""
        ack = None if self.command is None else inp.acks.get(self.command)
        return ack if ack is not None and ack[1] >= self.start_s else None

    def enough(self, inp: TakeoverInputs) -> bool:
        """Past the deadline: enough to fail, unless the phase's evidence (its command's answer, then HEARTBEATs
        saying "not yet") has been lost so far."""
        if inp.heartbeats is None or self._hb_at_enter is None or self.command is None:
            return True
        ack = self._answer(inp)
        if ack is None:
            return False  # every command or every answer lost so far: the HEARTBEATs' "not yet" says nothing
        accepted = ack[0] == mavlink.MAV_RESULT_ACCEPTED
        since = self._hb_at_accepted if accepted and self._hb_at_accepted is not None else self._hb_at_enter
        return inp.heartbeats - since >= HEARTBEATS_TO_FAIL


class Prestream:
    """PX4's setpoint pre-stream before OFFBOARD: when the unbroken stream of setpoints began, and its latest."""

    def __init__(self) -> None:
        self._since_s: float | None = None
        self._last_s: float | None = None

    def note(self, now_s: float) -> None:
        """A setpoint at ``now_s``; one more than ``PRESTREAM_GAP_S`` after the last restarts the stream."""
        if self._last_s is None or now_s - self._last_s > PRESTREAM_GAP_S:
            self._since_s = now_s
        self._last_s = now_s

    def streamed(self, now_s: float, need_s: float) -> bool:
        """The stream is unbroken at ``now_s`` and has lasted ``need_s``."""
        since, last = self._since_s, self._last_s
        return since is not None and last is not None and now_s - last < PRESTREAM_GAP_S and last - since >= need_s


class TakeoverController:
    """The takeover state machine (module docstring). ``step`` it; carry out the actions it returns."""

    def __init__(self, params: TakeoverParams) -> None:
        self.params = params
        self.phase = Phase.IDLE
        self._ardupilot = params.profile is Autopilot.ARDUPILOT
        self._route: object | None = None
        self._suspended = False
        self._deadline_s = 0.0
        self._next_send_s = 0.0
        self._evidence = PhaseEvidence(None, 0.0)
        self._home_down_m = 0.0
        self._takeoff_param_m = params.takeoff_alt_m
        self._prestream = Prestream()

    @property
    def poll_interval_s(self) -> float:
        """How long to wait before the next ``step`` [vehicle s]."""
        return IDLE_POLL_S if self.phase is Phase.IDLE else ACTIVE_POLL_S

    def note_prestream(self, now_s: float) -> None:
        """A PRESTREAM setpoint was produced at ``now_s`` (PX4 wants a stream before OFFBOARD)."""
        self._prestream.note(now_s)

    def step(self, now_s: float, inp: TakeoverInputs) -> list[Action]:
        """Advance at ``now_s``: start for a new goal, move through every phase whose condition holds, resend or
        fail the phase that waits. Returns the actions in the order to carry them out."""
        acts: list[Action] = []
        if self.phase is Phase.IDLE:
            if not self.params.enabled or not (inp.navigating or inp.waiting) or inp.engaged or inp.route is None:
                return acts
            self._start(now_s, inp, acts)
        while self.phase is not Phase.IDLE:
            self._evidence.note(inp)
            if self._condition(now_s, inp):
                self._advance(now_s, inp, acts)
                continue
            if inp.route is not self._route:  # not a failure: a new goal starts its own takeover
                why = "goal replaced" if inp.route is not None else "goal dropped"
                self._stop(ActionKind.ABANDONED, f"{self._what()}: {why}", acts)
            elif now_s > self._deadline_s and self._enough_evidence(now_s, inp):
                self._stop(ActionKind.FAILED, f"{self._what()} not confirmed within {self._timeout_s():.1f} s", acts)
            else:
                resend = self._command(inp)
                if resend is not None and now_s >= self._next_send_s:
                    acts.append(resend)
                    self._next_send_s = now_s + COMMAND_RETRY_S
            break
        return acts

    def _start(self, now_s: float, inp: TakeoverInputs, acts: list[Action]) -> None:
        self._route = inp.route
        acts.append(Action(ActionKind.STARTED))
        if self._ready(inp):
            self._begin(now_s, inp, acts)
        else:
            self._enter(Phase.READY, now_s)

    @staticmethod
    def _ready(inp: TakeoverInputs) -> bool:
        # a pose, fresh inputs (NAVIGATING: a goal set a moment ago is NAVIGATING before its first cycle) and the EKF
        return inp.navigating and inp.down_m is not None and inp.ekf_ready

    def _begin(self, now_s: float, inp: TakeoverInputs, acts: list[Action]) -> None:
        if self.params.arm and not inp.armed:
            self._suspended = True
            acts.append(Action(ActionKind.SUSPEND))
            self._enter(Phase.MODE_BEFORE_ARM if self._ardupilot else Phase.ARMING, now_s)
        else:
            self._enter(self._after_arming(), now_s)

    def _enough_evidence(self, now_s: float, inp: TakeoverInputs) -> bool:
        """Past the deadline: fail unless the phase's evidence has been lost so far (``PhaseEvidence.enough``); at
        the hard limit, fail regardless."""
        hard_limit_s = self._deadline_s + (HARD_TIMEOUT_FACTOR - 1.0) * self._timeout_s()
        return now_s > hard_limit_s or self._evidence.enough(inp)

    def _after_arming(self) -> Phase:
        return Phase.MODE if self._ardupilot else Phase.PRESTREAM

    def _enter(self, phase: Phase, now_s: float) -> None:
        self.phase = phase
        self._deadline_s = now_s + self._timeout_s()
        self._next_send_s = now_s
        self._evidence = PhaseEvidence(_HEARTBEAT_PHASES.get(phase), now_s)

    def _timeout_s(self) -> float:
        p = self.params
        if self.phase is Phase.READY:
            return p.ready_timeout_s
        if self.phase is Phase.TAKEOFF:
            return p.mode_timeout_s + TAKEOFF_S_PER_M * p.takeoff_alt_m
        if self.phase is Phase.PRESTREAM:
            return p.mode_timeout_s + PRESTREAM_EXTRA_S
        return p.mode_timeout_s

    def _what(self) -> str:
        if self.phase in (Phase.MODE, Phase.MODE_BEFORE_ARM):
            return guided_mode_name(self.params.profile)
        return str(self.phase.value)

    def _condition(self, now_s: float, inp: TakeoverInputs) -> bool:
        phase = self.phase
        if phase in (Phase.MODE, Phase.MODE_BEFORE_ARM):
            return inp.mode_ok
        if phase is Phase.READY:
            return self._ready(inp)
        if phase is Phase.ARMING:
            # The ACK arrives at once, the HEARTBEAT that says armed up to a second later (more on a lossy link),
            # and ArduCopter's DISARM_DELAY (10 s) runs from arming until a takeoff spools the motors.
            return inp.armed or self._evidence.accepted(inp, mavlink.MAV_CMD_COMPONENT_ARM_DISARM)
        if phase is Phase.GLOBAL_POSITION:
            return inp.home_amsl_m is not None
        if phase is Phase.TAKEOFF:
            climbed = None if inp.down_m is None else self._home_down_m - inp.down_m
            return climbed is not None and climbed >= TAKEOFF_REACHED_FRACTION * self.params.takeoff_alt_m
        return self._prestream.streamed(now_s, self.params.offboard_prestream_s)

    def _command(self, inp: TakeoverInputs) -> Action | None:
        if self.phase in (Phase.MODE, Phase.MODE_BEFORE_ARM):
            return Action(ActionKind.SET_MODE)
        if self.phase is Phase.ARMING:
            return Action(ActionKind.ARM)
        if self.phase is Phase.TAKEOFF and not self._taking_off(inp):
            return Action(ActionKind.TAKEOFF, value=self._takeoff_param_m)
        return None  # READY, GLOBAL_POSITION and PRESTREAM only wait; a takeoff under way needs no resend

    def _taking_off(self, inp: TakeoverInputs) -> bool:
        """NAV_TAKEOFF was ACCEPTED in this phase, or the vehicle climbs."""
        acked = self._evidence.accepted(inp, mavlink.MAV_CMD_NAV_TAKEOFF)
        climbing = inp.down_m is not None and self._home_down_m - inp.down_m > TAKEOFF_CLIMBING_M
        return acked or climbing

    def _advance(self, now_s: float, inp: TakeoverInputs, acts: list[Action]) -> None:
        p = self.params
        phase = self.phase
        if phase is Phase.READY:
            self._begin(now_s, inp, acts)
        elif phase is Phase.MODE_BEFORE_ARM:
            self._enter(Phase.ARMING, now_s)
        elif phase is Phase.ARMING and p.takeoff_alt_m > 0:
            self._home_down_m = inp.down_m if inp.down_m is not None else 0.0
            self._takeoff_param_m = p.takeoff_alt_m  # ArduCopter: param7 is the height above home
            self._enter(Phase.TAKEOFF if self._ardupilot else Phase.GLOBAL_POSITION, now_s)
        elif phase is Phase.GLOBAL_POSITION:
            assert inp.home_amsl_m is not None
            self._takeoff_param_m = inp.home_amsl_m + p.takeoff_alt_m  # PX4: param7 is an AMSL altitude
            self._enter(Phase.TAKEOFF, now_s)
        elif phase in (Phase.ARMING, Phase.TAKEOFF):
            if phase is Phase.TAKEOFF:
                acts.append(Action(ActionKind.AIRBORNE, value=self._home_down_m - p.takeoff_alt_m))
            self._resume(acts)
            self._enter(self._after_arming(), now_s)
        elif phase is Phase.PRESTREAM:
            self._enter(Phase.MODE, now_s)
        else:
            self.phase = Phase.IDLE
            acts.append(Action(ActionKind.DONE))

    def _resume(self, acts: list[Action]) -> None:
        if self._suspended:
            self._suspended = False
            acts.append(Action(ActionKind.RESUME))

    def _stop(self, kind: ActionKind, reason: str, acts: list[Action]) -> None:
        """End the takeover: FAILED (the service drops the goal) or ABANDONED (its goal is gone already)."""
        self._resume(acts)
        self.phase = Phase.IDLE
        acts.append(Action(kind, reason=reason))
