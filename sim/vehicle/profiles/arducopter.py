"""ArduCopter: modes (``mode.h``), command rules (``GCS_MAVLink_Copter.cpp``), GUIDED setpoints (``mode_guided.cpp``).

HEARTBEAT autopilot ARDUPILOTMEGA, custom_mode = the ArduCopter mode number. GUIDED uses SET_POSITION_TARGET_*
only when flying (not on the ground); a target that arrives while a NAV_TAKEOFF climbs ends the takeoff and is
flown (``ModeGuided::set_pos_NED_m`` switches the submode from TakeOff to Pos); a velocity or acceleration target is
zeroed after GUID_TIMEOUT (3 s) without an update; a position target is held indefinitely.
"""

from __future__ import annotations

import math
from typing import TYPE_CHECKING

from pymavlink.dialects.v20 import ardupilotmega as mavlink

from apf_companion.autopilot import (
    MASK_ACCELERATION,
    MASK_POS_VEL_ACCEL,
    MASK_POSITION,
    POS_IGNORE,
    Autopilot,
    CopterMode,
    TypeMask,
)
from sim.vehicle.dynamics import Limits, TargetKind, wrap_pi
from sim.vehicle.fencebreach import arming_refusal, check_fence
from sim.vehicle.geo import LOCAL_FRAMES
from sim.vehicle.guided import Setpoint, classify_mask_arducopter, position_setpoint, stop_setpoint
from sim.vehicle.params import ParamTable
from sim.vehicle.profiles.base import Behaviour, ProfileTexts, SetpointRule, param_int
from sim.world.model import FloatArray

if TYPE_CHECKING:
    from sim.vehicle.engine import VehicleEngine

__all__ = ["ArduCopterProfile"]

# The modes the simulator flies; the rest are refused like a mode whose checks fail.
MODES_OK = frozenset(
    int(m)
    for m in (
        CopterMode.STABILIZE,
        CopterMode.ALT_HOLD,
        CopterMode.LOITER,
        CopterMode.POSHOLD,
        CopterMode.BRAKE,
        CopterMode.GUIDED,
        CopterMode.LAND,
        CopterMode.RTL,
    )
)
MODES_NO_ARM = frozenset(int(m) for m in (CopterMode.LAND, CopterMode.RTL, CopterMode.BRAKE))
# Mode::requires_GPS (mode.h): refused before the EKF has a position (mode.cpp set_mode, "requires position")
MODES_NEED_POSITION = frozenset(
    int(m) for m in (CopterMode.GUIDED, CopterMode.LOITER, CopterMode.POSHOLD, CopterMode.BRAKE, CopterMode.RTL)
)
_BEHAVIOUR = {int(CopterMode.GUIDED): Behaviour.GUIDED, int(CopterMode.LAND): Behaviour.LAND}
_BEHAVIOUR[int(CopterMode.RTL)] = Behaviour.RTL
# POSITION_TARGET_LOCAL_NED's type_mask per GUIDED submode (GCS_MAVLink_Copter.cpp send_position_target_local_ned)
LAND_ALT_LOW_M = 10.0  # LAND_ALT_LOW default (1000 cm)
ECHO_VEL_ACCEL = int(POS_IGNORE | TypeMask.YAW_IGNORE | TypeMask.YAW_RATE_IGNORE)  # 0x0C07


class ArduCopterProfile:
    """ArduCopter 4.5 as the simulator models it."""

    autopilot = Autopilot.ARDUPILOT
    mav_autopilot = int(mavlink.MAV_AUTOPILOT_ARDUPILOTMEGA)
    flight_sw_version = 4 << 24 | 5 << 16 | 0 << 8 | 255  # 4.5.0 official
    texts = ProfileTexts(
        armed="Arming motors",
        disarmed="Disarming motors",
        land_complete="Land complete, disarmed",
        auto_disarm="Auto disarm: landed",
    )
    land_mode = int(CopterMode.LAND)
    rtl_mode = int(CopterMode.RTL)
    fail_result = int(mavlink.MAV_RESULT_FAILED)
    no_custom_mode_result = int(mavlink.MAV_RESULT_UNSUPPORTED)
    # ArduPilot answers SET_MODE with a COMMAND_ACK for the message id
    set_mode_ack_command = int(mavlink.MAVLINK_MSG_ID_SET_MODE)
    takeoff_in_guided = True
    keeps_setpoint_on_mode_change = False  # GUIDED is re-initialised on entry: no stale target
    # GCS_Common.cpp set_message_interval: no ap_message for the id -> DENIED
    unknown_message_result = int(mavlink.MAV_RESULT_DENIED)
    reports_prearm_check = True  # GCS.cpp update_sensor_status_flags
    body_yaw_relative = True
    echoes_target_yaw = False  # GCS_MAVLink_Copter.cpp send_position_target_local_ned sends yaw 0
    # AC_PosControl.cpp input_pos_vel_accel_NE_cm integrates the target; mode_guided.cpp zeroes vel at GUID_TIMEOUT
    advances_position_target = True
    supports_reboot = True  # GCS_Common.cpp handle_preflight_reboot
    # MAVLink_routing.cpp check_and_forward: "loopback of our own messages" -> not processed locally
    drops_own_ids = True
    # a fresh ArduCopter sends HEARTBEAT only (SITL, issue 8): SRn_* stream rates default to 0 until a GCS asks
    unasked_streams = False

    # -- modes
    def initial_mode(self, airborne: bool) -> int:
        return int(CopterMode.GUIDED if airborne else CopterMode.STABILIZE)

    def parse_mode(self, name: str) -> int | None:
        try:
            return int(CopterMode[name])
        except KeyError:
            return None

    def mode_name(self, custom_mode: int) -> str:
        try:
            return CopterMode(custom_mode).name
        except ValueError:
            return f"MODE{custom_mode}"

    def behaviour(self, custom_mode: int) -> Behaviour:
        return _BEHAVIOUR.get(custom_mode, Behaviour.HOLD)

    def mode_from_command(self, p: tuple[float, ...]) -> int:
        return param_int(p[1], -1)

    def request_mode(self, v: VehicleEngine, custom_mode: int) -> int:
        if custom_mode not in MODES_OK:
            v.statustext(mavlink.MAV_SEVERITY_WARNING, f"Flight mode change failed {self.mode_name(custom_mode)}")
            return self.fail_result
        if v.crashed:
            return self.fail_result
        if custom_mode in MODES_NEED_POSITION and not v.startup.origin_set:
            # mode.cpp set_mode -> mode_change_failed: "Mode change to %s failed: %s", MAV_SEVERITY_WARNING
            text = f"Mode change to {self.mode_name(custom_mode)} failed: requires position"
            v.statustext(mavlink.MAV_SEVERITY_WARNING, text)
            return self.fail_result
        v.set_mode(custom_mode, "command")
        return int(mavlink.MAV_RESULT_ACCEPTED)

    # -- limits and speeds
    def limits(self, params: ParamTable) -> Limits:
        return Limits(
            speed_h_m_s=params["WPNAV_SPEED"] / 100.0,
            speed_up_m_s=params["WPNAV_SPEED_UP"] / 100.0,
            speed_down_m_s=params["WPNAV_SPEED_DN"] / 100.0,
            accel_h_m_s2=params["WPNAV_ACCEL"] / 100.0,
        )

    def cruise_m_s(self, params: ParamTable) -> float:
        return params["WPNAV_SPEED"] / 100.0

    def land_speed_m_s(self, params: ParamTable, alt_m: float, limits: Limits) -> float:
        """mode_land.cpp: LAND_SPEED below LAND_ALT_LOW (10 m), the descent speed above it."""
        return params["LAND_SPEED"] / 100.0 if alt_m < LAND_ALT_LOW_M else limits.speed_down_m_s

    def rtl_alt_m(self, params: ParamTable) -> float:
        return params["RTL_ALT"] / 100.0

    def takeoff_speed_up_m_s(self, v: VehicleEngine, limits: Limits) -> float:
        return limits.speed_up_m_s  # spool-up and the throttle slew are the arducopter dynamics' (poscontrol.py)

    def disarm_delay_s(self, params: ParamTable) -> float:
        return params["DISARM_DELAY"]

    def disarm_timer_held(self, v: VehicleEngine) -> bool:
        """An accepted takeoff spools the motors up, and ArduCopter's auto_disarm_check (ArduCopter/motors.cpp)
        restarts its timer while the spool state is above GROUND_IDLE: a vehicle taking off is not disarmed as
        landed, however late in DISARM_DELAY the takeoff came."""
        return v.takeoff_alt_m is not None

    def face_travel(self, params: ParamTable) -> bool:
        return params["WP_YAW_BEHAVIOR"] > 0

    def guided_timeout_s(self, params: ParamTable) -> float | None:
        return params["GUID_TIMEOUT"]

    def ekf_origin_delay_s(self, params: ParamTable) -> float:
        return params["SIM_EKF_ORIGIN_S"]

    # -- command rules
    def arm_refusal(self, v: VehicleEngine, *, force: bool) -> str | None:
        if v.custom_mode in MODES_NO_ARM and not force:
            return "Arm: Mode not armable"
        if v.custom_mode in MODES_NEED_POSITION and not v.startup.origin_set:
            # AP_Arming_Copter.cpp mandatory_position_checks (run even when forced): no position_ok() yet
            return "PreArm: Need Position Estimate"
        return None if force else arming_refusal(v)

    def takeoff(self, v: VehicleEngine, p: tuple[float, ...]) -> int:
        """NAV_TAKEOFF: only armed, in GUIDED and landed; param7 = altitude above home [m]."""
        if v.custom_mode != CopterMode.GUIDED or not v.armed or not v.state.on_ground or not p[6] > 0:
            return int(mavlink.MAV_RESULT_FAILED)
        v.takeoff_alt_m = float(p[6])
        v.hold_pos_ned_m = v.state.pos_ned_m.copy()
        v.guided.sp = None
        return int(mavlink.MAV_RESULT_ACCEPTED)

    def reposition(self, v: VehicleEngine, p: tuple[float, ...], target_ned_m: FloatArray) -> int:
        """DO_REPOSITION: flies there in GUIDED; from another mode only with the CHANGE_MODE flag, else DENIED
        (GCS_MAVLink_Copter.cpp handle_command_int_do_reposition); like any GUIDED target it ends a takeoff."""
        if v.custom_mode != CopterMode.GUIDED:
            if not param_int(p[1]) & mavlink.MAV_DO_REPOSITION_FLAGS_CHANGE_MODE:
                return int(mavlink.MAV_RESULT_DENIED)
            v.set_mode(int(CopterMode.GUIDED), "reposition")
        v.guided.set(position_setpoint(v.t_s, target_ned_m))
        self.after_external_target(v)
        return int(mavlink.MAV_RESULT_ACCEPTED)

    def change_speed(self, params: ParamTable, speed_m_s: float) -> str | None:
        return params.set("WPNAV_SPEED", speed_m_s * 100.0)

    def condition_yaw(self, v: VehicleEngine, p: tuple[float, ...]) -> int:
        """MAV_CMD_CONDITION_YAW (GCS_MAVLink_Copter.cpp handle_MAV_CMD_CONDITION_YAW): param1 angle [0, 360] deg,
        param3 direction (-1 ccw, +1 cw), param4 0 absolute / 1 relative; else FAILED. The heading holds in
        GUIDED until the next target (auto_yaw.set_fixed_yaw_rad); the turn rate (param2) is not modelled."""
        angle_deg, direction, relative = p[0], p[2], p[3]
        if not (0.0 <= angle_deg <= 360.0 and relative in (0.0, 1.0)):
            return int(mavlink.MAV_RESULT_FAILED)
        if relative == 1.0:
            sign = -1.0 if direction < 0 else 1.0
            yaw = v.state.yaw_rad + sign * math.radians(angle_deg)
        else:
            yaw = math.radians(angle_deg)
        v.guided.fixed_yaw_rad = wrap_pi(yaw)
        return int(mavlink.MAV_RESULT_ACCEPTED)

    # -- setpoint rules
    def setpoint_rule(self, mask: int, frame: int) -> SetpointRule:
        """An unsupported frame or type_mask is not ignored: GCS_MAVLink_Copter.cpp answers it with
        ``mode_guided.init(true)`` ("input is not valid so stop"), silently (kind None, no text)."""
        if frame not in LOCAL_FRAMES:
            return SetpointRule(None, mask)
        return SetpointRule(classify_mask_arducopter(mask), mask)

    def invalid_setpoint(self, v: VehicleEngine) -> bool:
        """Stop, silently: decelerate and hold (ModeGuided::init runs the velocity controller at zero), which ends
        a takeoff. Only in GUIDED and flying, like any setpoint."""
        if self.accepts_setpoint(v):
            v.guided.set(stop_setpoint(v.t_s, ECHO_VEL_ACCEL))
            self.after_external_target(v)
        return True

    def accepts_setpoint(self, v: VehicleEngine) -> bool:
        # setpoints are used only in GUIDED and not on the ground (GCS_MAVLink_Copter.cpp: in_guided_mode;
        # mode_guided.cpp runs the controllers only when not landed)
        return v.custom_mode == CopterMode.GUIDED and not v.state.on_ground

    def after_external_target(self, v: VehicleEngine) -> None:
        v.takeoff_alt_m = None  # a new GUIDED target ends the takeoff submode (mode_guided.cpp set_pos_NED_m)

    def echo_type_mask(self, sp: Setpoint) -> int:
        """The submode's fixed mask (GCS_MAVLink_Copter.cpp send_position_target_local_ned), not the one sent."""
        if sp.kind is TargetKind.POSITION:
            return MASK_POSITION if sp.vel is None else MASK_POS_VEL_ACCEL
        if sp.kind is TargetKind.VELOCITY:
            return ECHO_VEL_ACCEL
        return MASK_ACCELERATION

    def stays_on_ground(self, sp: Setpoint) -> bool:
        return False

    def takeoff_complete(self, v: VehicleEngine, target_ned_m: FloatArray) -> None:
        v.guided.sp = position_setpoint(v.t_s, target_ned_m)  # GUIDED holds the takeoff altitude

    def check_failsafes(self, v: VehicleEngine) -> None:
        check_fence(v)

    def spawn_in_air(self, v: VehicleEngine) -> None:
        return None
