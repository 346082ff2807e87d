"""What the autopilot says about itself: its mode and arming (HEARTBEAT), whether and how often it has been heard,
its EKF's position flags (EKF_STATUS_REPORT) and its answers to our commands (COMMAND_ACK).

A HEARTBEAT also tells the others what it means: boot evidence for the pose gate, the stream requests to restart
or send, the navigator's link and mode, and at the first one (this process's, or the first after a lost link) the
route given at start is flown, unless the vehicle is already flying in guided control (restarted mid-flight: it
holds, docs/hardening.md).
"""

from __future__ import annotations

from collections.abc import Callable

from pymavlink.dialects.v20 import ardupilotmega as mavlink

from apf_companion.autopilot import Autopilot, CopterMode, Px4MainMode, Px4Mode
from apf_companion.goal import Route
from apf_companion.handling.params import HandlerParams
from apf_companion.handling.streams import StreamRequests
from apf_companion.links.messages import CommandAck, EkfStatusReport, Heartbeat
from apf_companion.navigator import Navigator
from apf_companion.perception import PoseGate

__all__ = ["EKF_POSITION_FLAGS", "AutopilotState", "mode_is_ours"]

NOT_A_VEHICLE = frozenset({mavlink.MAV_TYPE_ONBOARD_CONTROLLER, mavlink.MAV_TYPE_GCS})  # their HEARTBEATs
REBOOTING = frozenset({mavlink.MAV_STATE_UNINIT, mavlink.MAV_STATE_BOOT})  # HEARTBEAT.system_status
# ArduCopter position_ok() (system.cpp ekf_has_absolute_position / _relative_position): a horizontal position, not
# the constant-position mode the EKF is in before it has one
EKF_POSITION_FLAGS = mavlink.EKF_POS_HORIZ_ABS | mavlink.EKF_PRED_POS_HORIZ_ABS | mavlink.EKF_POS_HORIZ_REL


def mode_is_ours(profile: Autopilot, custom_mode: int) -> bool:
    """HEARTBEAT.custom_mode is GUIDED (ArduCopter) / OFFBOARD (PX4)."""
    if profile is Autopilot.ARDUPILOT:
        return custom_mode == CopterMode.GUIDED
    return Px4Mode.from_custom_mode(custom_mode).main == Px4MainMode.OFFBOARD


class AutopilotState:
    """The autopilot's HEARTBEAT, EKF_STATUS_REPORT and COMMAND_ACK (see the module docstring).

    Args:
        gate: The pose gate, told of boot evidence (a pose may then start a new time base).
        streams: The stream requests, restarted and sent at HEARTBEATs.
        set_route: Offers a goal to goal admission (``GoalAdmission.admit``).
        route_at_start: Flown once the autopilot is first heard.
    """

    def __init__(
        self,
        params: HandlerParams,
        *,
        gate: PoseGate,
        navigator: Navigator,
        streams: StreamRequests,
        set_route: Callable[[Route, float], bool],
        route_at_start: Route | None,
    ) -> None:
        self.params = params
        self._gate = gate
        self._navigator = navigator
        self._streams = streams
        self._set_route = set_route
        self._route_at_start = route_at_start
        self.heard = False
        self.heartbeats = 0  # autopilot HEARTBEATs heard (the takeover weighs its evidence by them)
        self.custom_mode: int | None = None
        self.base_mode = 0
        self.ekf_flags: int | None = None  # latest EKF_STATUS_REPORT.flags; None: the autopilot sends none
        self.acks: dict[int, tuple[int, float]] = {}  # command -> (result, service time) of its latest ACK to us

    @property
    def armed(self) -> bool:
        return bool(self.base_mode & mavlink.MAV_MODE_FLAG_SAFETY_ARMED)

    @property
    def mode_ok(self) -> bool:
        """The autopilot's latest mode is ours (GUIDED / OFFBOARD); False before its first HEARTBEAT."""
        return self.custom_mode is not None and mode_is_ours(self.params.profile, self.custom_mode)

    @property
    def ekf_ready(self) -> bool:
        """The EKF has a horizontal position; True when the autopilot reports no EKF status (PX4)."""
        return self.ekf_flags is None or (
            bool(self.ekf_flags & EKF_POSITION_FLAGS) and not self.ekf_flags & mavlink.EKF_CONST_POS_MODE
        )

    def on_heartbeat(self, rec: Heartbeat, now_s: float) -> None:
        if rec.type in NOT_A_VEHICLE:
            return
        nav = self._navigator
        at_start = not self.heard  # this process's first HEARTBEAT
        first = at_start or not nav.link_alive(now_s)
        if (self.heard and first) or rec.system_status in REBOOTING:
            self._gate.note_reboot()  # boot evidence: a pose may start a new time base
        if first or rec.system_status in REBOOTING:
            self._streams.restart()  # a rebooted autopilot has forgotten our stream requests
        self.heard = True
        self.heartbeats += 1
        self.custom_mode = rec.custom_mode
        self.base_mode = rec.base_mode
        failsafe = rec.system_status == mavlink.MAV_STATE_CRITICAL
        nav.autopilot_heartbeat(now_s, mode_ok=self.params.dry_run or self.mode_ok, failsafe=failsafe)
        self._streams.send_due(now_s)
        if first:
            route, self._route_at_start = self._route_at_start, None
            restarted = self._restarted_mid_flight(route) if at_start else None
            if restarted is not None:
                nav.recovery.restart_hold(now_s, restarted)
            elif route is not None:
                self._set_route(route, now_s)

    def _restarted_mid_flight(self, route: Route | None) -> str | None:
        """At the first HEARTBEAT: the vehicle is already flying (armed) in GUIDED / OFFBOARD, so this process was
        (re)started mid-flight: why it holds instead of moving, or None to go on as usual (docs/hardening.md)."""
        if self.params.dry_run or not (self.armed and self.mode_ok):
            return None
        if route is not None and (self.params.fly_config_goal_after_restart or not route.source.startswith("config")):
            return None  # a goal given now (command line), or the config says its goal is fresh
        why = "started with the vehicle flying in guided control: holding, send a fresh goal"
        return why if route is None else f"{why} (goal.fly_after_restart = false)"

    def on_ekf_status(self, rec: EkfStatusReport, now_s: float) -> None:
        self.ekf_flags = rec.flags
        self._navigator.ekf_ready = self.ekf_ready  # why there is no pose yet (HOLDING reason)

    def on_command_ack(self, rec: CommandAck, now_s: float) -> None:
        if rec.target_component in (0, self.params.component_id):
            self.acks[rec.command] = (rec.result, now_s)
