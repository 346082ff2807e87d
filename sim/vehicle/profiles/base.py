"""What an autopilot profile decides: its modes, its command rules and its setpoint rules.

The engine owns the vehicle and asks its profile (looked up once in ``PROFILES`` by ``Autopilot``) wherever
ArduCopter and PX4 differ, the way ArduCopter's ``Mode`` subclasses and PX4's ``Commander`` own those rules.
"""

from __future__ import annotations

import enum
import math
from dataclasses import dataclass
from typing import TYPE_CHECKING, Protocol

from apf_companion.autopilot import Autopilot
from sim.vehicle.dynamics import Limits, TargetKind
from sim.vehicle.guided import Setpoint
from sim.vehicle.params import ParamTable
from sim.world.model import FloatArray

if TYPE_CHECKING:
    from sim.vehicle.engine import VehicleEngine

__all__ = ["AutopilotProfile", "Behaviour", "ProfileTexts", "SetpointRule", "param_int", "replace_limits"]


class Behaviour(enum.Enum):
    """What the current mode makes the vehicle do (many modes share one)."""

    GUIDED = "guided"  # fly the external setpoint (ArduCopter GUIDED, PX4 OFFBOARD)
    HOLD = "hold"  # hold position (LOITER, BRAKE, POSHOLD, STABILIZE without RC, PX4 Hold, ...)
    LAND = "land"
    RTL = "rtl"
    TAKEOFF = "takeoff"  # PX4 AUTO.TAKEOFF (ArduCopter climbs inside GUIDED)


@dataclass(frozen=True, slots=True)
class ProfileTexts:
    """STATUSTEXTs the autopilot sends for these events."""

    armed: str
    disarmed: str
    land_complete: str
    auto_disarm: str


@dataclass(frozen=True, slots=True)
class SetpointRule:
    """How the autopilot takes a SET_POSITION_TARGET_*: the kind of target and the type_mask in force, or None
    with the STATUSTEXT it answers (severity, text); then the profile's ``invalid_setpoint`` says what it does
    (ArduCopter stops, PX4 ignores)."""

    kind: TargetKind | None
    type_mask: int
    severity: int = 0
    text: str = ""


def param_int(value: float, default: int = 0) -> int:
    """An integer command param; NaN (or inf) means "unused" (common.xml COMMAND_LONG) and gives ``default``.

    MAVSDK sends NaN for unused params (``action.arm()`` param2): ``round(nan)`` would raise.
    """
    return round(value) if math.isfinite(value) else default


def replace_limits(limits: Limits, **changes: float) -> Limits:
    return Limits(**{**{k: getattr(limits, k) for k in Limits.__slots__}, **changes})


class AutopilotProfile(Protocol):
    """One autopilot's rules. Methods taking ``v`` read or change the engine's vehicle."""

    autopilot: Autopilot
    mav_autopilot: int  # HEARTBEAT.autopilot
    flight_sw_version: int  # AUTOPILOT_VERSION
    texts: ProfileTexts
    land_mode: int  # custom_mode for MAV_CMD_NAV_LAND
    rtl_mode: int  # custom_mode for MAV_CMD_NAV_RETURN_TO_LAUNCH
    fail_result: int  # a command understood but not possible now
    no_custom_mode_result: int  # a mode request without MAV_MODE_FLAG_CUSTOM_MODE_ENABLED
    set_mode_ack_command: int  # the COMMAND_ACK.command answering a SET_MODE message
    takeoff_in_guided: bool  # a takeoff climbs inside the guided mode (ArduCopter), not in a mode of its own
    keeps_setpoint_on_mode_change: bool  # the last external setpoint survives a mode change
    unknown_message_result: int  # SET_MESSAGE_INTERVAL for a message id the autopilot cannot send
    reports_prearm_check: bool  # SYS_STATUS carries MAV_SYS_STATUS_PREARM_CHECK
    body_yaw_relative: bool  # in BODY_* frames the setpoint's yaw is relative to the heading
    echoes_target_yaw: bool  # POSITION_TARGET_LOCAL_NED carries the target's yaw (else 0)
    advances_position_target: bool  # a position+velocity target moves along its velocity until GUID_TIMEOUT
    supports_reboot: bool  # MAV_CMD_PREFLIGHT_REBOOT_SHUTDOWN is modelled (sim/vehicle/reboot.py)
    drops_own_ids: bool  # messages from the autopilot's own sysid/compid are dropped (MAVLink_routing.cpp)
    unasked_streams: bool  # telemetry streams without being asked (PX4); else only HEARTBEAT until requested

    # -- modes
    def initial_mode(self, airborne: bool) -> int: ...
    def parse_mode(self, name: str) -> int | None: ...
    def mode_name(self, custom_mode: int) -> str: ...
    def behaviour(self, custom_mode: int) -> Behaviour: ...
    def mode_from_command(self, p: tuple[float, ...]) -> int: ...
    def request_mode(self, v: VehicleEngine, custom_mode: int) -> int: ...

    # -- limits and speeds from the parameters
    def limits(self, params: ParamTable) -> Limits: ...
    def cruise_m_s(self, params: ParamTable) -> float: ...
    def land_speed_m_s(self, params: ParamTable, alt_m: float, limits: Limits) -> float: ...
    def rtl_alt_m(self, params: ParamTable) -> float: ...
    def takeoff_speed_up_m_s(self, v: VehicleEngine, limits: Limits) -> float: ...
    def disarm_delay_s(self, params: ParamTable) -> float: ...
    def disarm_timer_held(self, v: VehicleEngine) -> bool: ...  # True: the landed disarm timer restarts
    def face_travel(self, params: ParamTable) -> bool: ...
    def guided_timeout_s(self, params: ParamTable) -> float | None: ...
    def ekf_origin_delay_s(self, params: ParamTable) -> float: ...  # simulated s from boot to the EKF origin

    # -- command rules
    def arm_refusal(self, v: VehicleEngine, *, force: bool) -> str | None: ...
    def takeoff(self, v: VehicleEngine, p: tuple[float, ...]) -> int: ...
    def reposition(self, v: VehicleEngine, p: tuple[float, ...], target_ned_m: FloatArray) -> int: ...
    def change_speed(self, params: ParamTable, speed_m_s: float) -> str | None: ...
    def condition_yaw(self, v: VehicleEngine, p: tuple[float, ...]) -> int: ...

    # -- setpoint rules
    def setpoint_rule(self, mask: int, frame: int) -> SetpointRule: ...
    def invalid_setpoint(self, v: VehicleEngine) -> bool: ...  # True: acted on it silently; False: ignore, warn
    def accepts_setpoint(self, v: VehicleEngine) -> bool: ...
    def after_external_target(self, v: VehicleEngine) -> None: ...
    def echo_type_mask(self, sp: Setpoint) -> int: ...
    def stays_on_ground(self, sp: Setpoint) -> bool: ...
    def takeoff_complete(self, v: VehicleEngine, target_ned_m: FloatArray) -> None: ...
    def check_failsafes(self, v: VehicleEngine) -> None: ...
    def spawn_in_air(self, v: VehicleEngine) -> None: ...
