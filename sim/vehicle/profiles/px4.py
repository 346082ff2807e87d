"""PX4 multicopter: modes (``px4_custom_mode.h``), commander's command rules, OFFBOARD (``offboardCheck.cpp``).

HEARTBEAT autopilot PX4, custom_mode = main mode << 16 | sub mode << 24. Switching to OFFBOARD (or arming in it)
is refused (TEMPORARILY_REJECTED) unless the last setpoint is newer than COM_OF_LOSS_T (``offboardCheck.cpp``); in
OFFBOARD, no setpoint for COM_OF_LOSS_T (1 s) triggers the failsafe (COM_OBL_RC_ACT; without RC: Hold =
AUTO.LOITER) and a STATUSTEXT; a setpoint after that, with the mode not changed meanwhile, returns to OFFBOARD
(``failsafe.cpp``: the fallback clears with its condition). OFFBOARD can take off from the ground when armed and
the setpoint climbs.
SET_POSITION_TARGET_LOCAL_NED follows ``mavlink_receiver.cpp``: LOCAL_NED or BODY_NED only (BODY_NED ignores the
position), any combination of position / velocity / acceleration, no FORCE with an acceleration.
"""

from __future__ import annotations

import math
from typing import TYPE_CHECKING

from pymavlink.dialects.v20 import ardupilotmega as mavlink

from apf_companion.autopilot import (
    ACC_IGNORE,
    POS_IGNORE,
    PX4_HOLD,
    PX4_LAND,
    PX4_OFFBOARD,
    PX4_TAKEOFF,
    VEL_IGNORE,
    Autopilot,
    Px4AutoSubMode,
    Px4MainMode,
    Px4Mode,
    TypeMask,
)
from sim.vehicle.dynamics import Limits, TargetKind
from sim.vehicle.fencebreach import arming_refusal, check_fence
from sim.vehicle.guided import Setpoint
from sim.vehicle.params import ParamTable
from sim.vehicle.profiles.base import Behaviour, ProfileTexts, SetpointRule, param_int
from sim.world.model import FloatArray

if TYPE_CHECKING:
    from sim.vehicle.engine import VehicleEngine

__all__ = ["PX4_RTL", "Px4Profile"]

PX4_RTL = Px4Mode(Px4MainMode.AUTO, Px4AutoSubMode.RTL)
PX4_POSCTL = Px4Mode(Px4MainMode.POSCTL)
MODES_OK = frozenset({PX4_HOLD, PX4_TAKEOFF, PX4_LAND, PX4_RTL, PX4_OFFBOARD})
_NAMES = {
    PX4_HOLD: "AUTO.LOITER",
    PX4_TAKEOFF: "AUTO.TAKEOFF",
    PX4_LAND: "AUTO.LAND",
    PX4_RTL: "AUTO.RTL",
    PX4_OFFBOARD: "OFFBOARD",
    PX4_POSCTL: "POSCTL",
}
_ALIASES = {"HOLD": PX4_HOLD, "LOITER": PX4_HOLD, "TAKEOFF": PX4_TAKEOFF, "LAND": PX4_LAND, "RTL": PX4_RTL}
_BEHAVIOUR = {
    PX4_OFFBOARD: Behaviour.GUIDED,
    PX4_LAND: Behaviour.LAND,
    PX4_RTL: Behaviour.RTL,
    PX4_TAKEOFF: Behaviour.TAKEOFF,
}
# COM_OBL_RC_ACT -> the failsafe mode and its name in the STATUSTEXT (no RC: the RC-only actions mean Hold)
_OFFBOARD_LOSS_ACTIONS = {3: (PX4_RTL, "Return"), 4: (PX4_LAND, "Land"), 6: (PX4_LAND, "Land"), 7: (PX4_LAND, "Land")}
_SP = "SET_POSITION_TARGET_LOCAL_NED"


class Px4Profile:
    """PX4 1.15 multicopter as the simulator models it."""

    autopilot = Autopilot.PX4
    mav_autopilot = int(mavlink.MAV_AUTOPILOT_PX4)
    flight_sw_version = 1 << 24 | 15 << 16 | 0 << 8 | 255  # 1.15.0 release
    texts = ProfileTexts(
        armed="Armed by external command",
        disarmed="Disarmed by external command",
        land_complete="Landing detected, disarmed",
        auto_disarm="Disarmed: preflight timeout",
    )
    land_mode = PX4_LAND.to_custom_mode()
    rtl_mode = PX4_RTL.to_custom_mode()
    fail_result = int(mavlink.MAV_RESULT_TEMPORARILY_REJECTED)
    no_custom_mode_result = int(mavlink.MAV_RESULT_DENIED)
    set_mode_ack_command = int(mavlink.MAV_CMD_DO_SET_MODE)  # PX4 turns SET_MODE into DO_SET_MODE
    takeoff_in_guided = False
    keeps_setpoint_on_mode_change = True  # the latest setpoint waits for OFFBOARD to engage
    unknown_message_result = int(mavlink.MAV_RESULT_FAILED)  # mavlink_receiver.cpp: no stream -> PX4_ERROR
    reports_prearm_check = False
    body_yaw_relative = False  # mavlink_receiver.cpp passes BODY_NED yaw through unrotated
    echoes_target_yaw = True
    advances_position_target = False  # the position is flown as sent; the velocity is a feed-forward
    supports_reboot = False  # not modelled: UNSUPPORTED
    drops_own_ids = False  # not checked in PX4's source
    unasked_streams = True  # mavlink_main.cpp configure_streams_to_default: the mode's streams from boot

    # -- modes
    def initial_mode(self, airborne: bool) -> int:
        return PX4_HOLD.to_custom_mode()

    def parse_mode(self, name: str) -> int | None:
        if name in _ALIASES:
            return _ALIASES[name].to_custom_mode()
        for mode, mode_name in _NAMES.items():
            if mode_name == name:
                return mode.to_custom_mode()
        return None

    def mode_name(self, custom_mode: int) -> str:
        mode = Px4Mode.from_custom_mode(custom_mode)
        return _NAMES.get(mode, f"PX4({mode.main},{mode.sub})")

    def behaviour(self, custom_mode: int) -> Behaviour:
        return _BEHAVIOUR.get(Px4Mode.from_custom_mode(custom_mode), Behaviour.HOLD)

    def mode_from_command(self, p: tuple[float, ...]) -> int:
        return Px4Mode(param_int(p[1]), param_int(p[2])).to_custom_mode()

    def request_mode(self, v: VehicleEngine, custom_mode: int) -> int:
        mode = Px4Mode.from_custom_mode(custom_mode)
        if mode.main != Px4MainMode.AUTO:
            mode = Px4Mode(mode.main, 0)
        if mode not in MODES_OK:
            text = f"Switching to {self.mode_name(custom_mode)} is currently not available"
            v.statustext(mavlink.MAV_SEVERITY_CRITICAL, text)
            return self.fail_result
        if mode == PX4_OFFBOARD and not self.offboard_ready(v):
            v.statustext(mavlink.MAV_SEVERITY_CRITICAL, "Switching to Offboard is currently not available")
            return self.fail_result
        if v.crashed:
            return self.fail_result
        # The user's intended mode changes, even to the failsafe's own Hold: a takeover, which ends the failsafe
        # (failsafe/framework.cpp ``getSelectedAction``: the action becomes a warning, HEARTBEAT no longer CRITICAL)
        v.offboard_fallback = v.failsafe = False
        v.set_mode(mode.to_custom_mode(), "command")
        return int(mavlink.MAV_RESULT_ACCEPTED)

    def offboard_ready(self, v: VehicleEngine) -> bool:
        """The last setpoint is newer than COM_OF_LOSS_T (offboardCheck.cpp: ``data_is_recent``); no pre-stream."""
        last = v.guided.last_t_s
        return last is not None and v.t_s < last + v.params["COM_OF_LOSS_T"]

    # -- limits and speeds
    def limits(self, params: ParamTable) -> Limits:
        """The MPC_* limits; a commanded yaw is turned to at MPC_YAWRAUTO_MAX (the yaw setpoint's rate limit in
        autonomous modes, OFFBOARD included: src/modules/mc_pos_control/multicopter_autonomous_params.c, 45 deg/s;
        the yaw acceleration limit MPC_YAWRAUTO_ACC is not modelled)."""
        return Limits(
            speed_h_m_s=params["MPC_XY_VEL_MAX"],
            speed_up_m_s=params["MPC_Z_VEL_MAX_UP"],
            speed_down_m_s=params["MPC_Z_VEL_MAX_DN"],
            accel_h_m_s2=params["MPC_ACC_HOR"],
            yaw_rate_rad_s=math.radians(params["MPC_YAWRAUTO_MAX"]),
        )

    def cruise_m_s(self, params: ParamTable) -> float:
        return params["MPC_XY_CRUISE"]

    def land_speed_m_s(self, params: ParamTable, alt_m: float, limits: Limits) -> float:
        """FlightTaskAuto land: the descent speed above MPC_LAND_ALT1, MPC_LAND_SPEED below MPC_LAND_ALT2,
        interpolated in between."""
        alt1, alt2, slow = params["MPC_LAND_ALT1"], params["MPC_LAND_ALT2"], params["MPC_LAND_SPEED"]
        fast = max(limits.speed_down_m_s, slow)
        if alt_m <= alt2 or alt1 <= alt2:
            return slow if alt_m <= alt2 else fast
        return slow + (fast - slow) * min(1.0, (alt_m - alt2) / (alt1 - alt2))

    def rtl_alt_m(self, params: ParamTable) -> float:
        return params["RTL_RETURN_ALT"]

    def takeoff_speed_up_m_s(self, v: VehicleEngine, limits: Limits) -> float:
        """mc_pos_control Takeoff.cpp: the motors spool for COM_SPOOLUP_TIME after arming, then the upward speed
        limit ramps to MPC_TKO_SPEED over MPC_TKO_RAMP_T (0 = at once)."""
        p = v.params
        ramp_from = max(v.armed_t_s + p["COM_SPOOLUP_TIME"], v.takeoff_t_s)
        if v.t_s < ramp_from:
            return 0.0
        ramp = p["MPC_TKO_RAMP_T"]
        share = 1.0 if ramp <= 0.0 else min(1.0, (v.t_s - ramp_from) / ramp)
        return min(p["MPC_TKO_SPEED"], limits.speed_up_m_s) * share

    def disarm_delay_s(self, params: ParamTable) -> float:
        return params["COM_DISARM_PRFLT"]

    def disarm_timer_held(self, v: VehicleEngine) -> bool:
        """Commander's pre-flight disarm (COM_DISARM_PRFLT) counts from arming until the land detector has seen a
        takeoff (``_have_taken_off_since_arming``), whatever was commanded: never held here
        (src/modules/commander/Commander.cpp, the auto-disarm check)."""
        return False

    def face_travel(self, params: ParamTable) -> bool:
        return False

    def guided_timeout_s(self, params: ParamTable) -> float | None:
        return None  # OFFBOARD holds the last setpoint; the loss failsafe ends it

    def ekf_origin_delay_s(self, params: ParamTable) -> float:
        return 0.0  # not modelled for PX4: position from boot

    # -- command rules
    def arm_refusal(self, v: VehicleEngine, *, force: bool) -> str | None:
        if v.custom_mode == PX4_OFFBOARD.to_custom_mode() and not self.offboard_ready(v):
            return "Arming denied: no offboard setpoints"
        return arming_refusal(v)

    def takeoff(self, v: VehicleEngine, p: tuple[float, ...]) -> int:
        """NAV_TAKEOFF: param7 is an AMSL altitude (NaN = MIS_TAKEOFF_ALT above home)."""
        if not v.state.on_ground:
            return self.fail_result
        # like PX4's Takeoff mode, a target below home + MIS_TAKEOFF_ALT is raised to it, and it says so
        minimum = v.params["MIS_TAKEOFF_ALT"]
        alt = minimum if math.isnan(p[6]) else p[6] - v.cfg.home.alt_amsl_m
        if not alt >= minimum:
            if not math.isnan(p[6]):
                v.statustext(mavlink.MAV_SEVERITY_CRITICAL, f"Using minimum takeoff altitude: {minimum:.2f} m")
            alt = minimum
        v.set_mode(PX4_TAKEOFF.to_custom_mode(), "takeoff")
        v.takeoff_alt_m = alt
        v.takeoff_t_s = v.t_s
        return int(mavlink.MAV_RESULT_ACCEPTED)

    def reposition(self, v: VehicleEngine, p: tuple[float, ...], target_ned_m: FloatArray) -> int:
        """DO_REPOSITION: Hold mode, flying to the new hold point."""
        v.set_mode(PX4_HOLD.to_custom_mode(), "reposition")
        v.hold_pos_ned_m = target_ned_m
        return int(mavlink.MAV_RESULT_ACCEPTED)

    def change_speed(self, params: ParamTable, speed_m_s: float) -> str | None:
        return params.set("MPC_XY_CRUISE", min(speed_m_s, params["MPC_XY_VEL_MAX"]))

    def condition_yaw(self, v: VehicleEngine, p: tuple[float, ...]) -> int:
        return int(mavlink.MAV_RESULT_UNSUPPORTED)  # a mission item on PX4, not a command it takes in flight

    # -- setpoint rules
    def setpoint_rule(self, mask: int, frame: int) -> SetpointRule:
        """mavlink_receiver.cpp handle_message_set_position_target_local_ned."""
        critical = mavlink.MAV_SEVERITY_CRITICAL
        if frame not in (mavlink.MAV_FRAME_LOCAL_NED, mavlink.MAV_FRAME_BODY_NED):
            return SetpointRule(None, mask, critical, f"{_SP} coordinate frame {frame} unsupported")
        if frame == mavlink.MAV_FRAME_BODY_NED:
            mask |= POS_IGNORE  # BODY_NED: velocity and acceleration only
        given = [mask & bits != bits for bits in (POS_IGNORE, VEL_IGNORE, ACC_IGNORE)]
        if given[2] and mask & TypeMask.FORCE_SET:
            return SetpointRule(None, mask, critical, f"{_SP} force not supported")
        if not any(given):
            return SetpointRule(None, mask, critical, f"{_SP} invalid")
        if any(mask & bits not in (0, bits) for bits in (POS_IGNORE, VEL_IGNORE, ACC_IGNORE)):
            # PX4 flies single axes (NaN per axis); the simulator's controller takes whole vectors
            return SetpointRule(
                None, mask, mavlink.MAV_SEVERITY_WARNING, "Setpoint ignored: partial axes not simulated"
            )
        kind = TargetKind.POSITION if given[0] else TargetKind.VELOCITY if given[1] else TargetKind.ACCELERATION
        return SetpointRule(kind, mask)

    def invalid_setpoint(self, v: VehicleEngine) -> bool:
        return False  # mavlink_receiver.cpp: an unusable setpoint is dropped (with its STATUSTEXT)

    def accepts_setpoint(self, v: VehicleEngine) -> bool:
        return True  # kept for when OFFBOARD engages

    def after_external_target(self, v: VehicleEngine) -> None:
        return None

    def echo_type_mask(self, sp: Setpoint) -> int:
        return sp.type_mask

    def stays_on_ground(self, sp: Setpoint) -> bool:
        # OFFBOARD lifts off only for a setpoint that climbs
        climbing = (sp.pos is not None and sp.pos[2] < -0.3) or (sp.vel is not None and sp.vel[2] < -0.1)
        return not climbing

    def takeoff_complete(self, v: VehicleEngine, target_ned_m: FloatArray) -> None:
        v.set_mode(PX4_HOLD.to_custom_mode(), "takeoff complete")
        v.hold_pos_ned_m = target_ned_m

    def check_failsafes(self, v: VehicleEngine) -> None:
        """The geofence (sim.vehicle.fencebreach); OFFBOARD without a setpoint for COM_OF_LOSS_T: the COM_OBL_RC_ACT
        failsafe, which ends when setpoints come back: PX4 then returns to OFFBOARD by itself unless the mode was
        changed meanwhile. The offboard loss is a mode fallback (src/modules/commander/failsafe/failsafe.cpp
        ``checkModeFallback``) that leaves the user's intended mode at OFFBOARD and clears when its condition
        clears (``ActionOptions`` default ``ClearCondition::WhenConditionClears``, failsafe/framework.h); a mode
        change by the user is the takeover that ends it (``set_mode`` clears ``offboard_fallback``)."""
        check_fence(v)
        if v.offboard_fallback and v.armed and self.offboard_ready(v):
            v.set_mode(PX4_OFFBOARD.to_custom_mode(), "offboard signal back")
            return
        if v.custom_mode != PX4_OFFBOARD.to_custom_mode():
            return
        last = v.guided.last_t_s
        if v.t_s - (last if last is not None else -math.inf) <= v.params["COM_OF_LOSS_T"]:
            return
        new, name = _OFFBOARD_LOSS_ACTIONS.get(round(v.params["COM_OBL_RC_ACT"]), (PX4_HOLD, "Hold"))
        v.statustext(mavlink.MAV_SEVERITY_CRITICAL, f"Failsafe: offboard signal lost, {name}")
        v.set_mode(new.to_custom_mode(), "offboard loss")
        v.failsafe = True
        v.offboard_fallback = True

    def spawn_in_air(self, v: VehicleEngine) -> None:
        if v.custom_mode == PX4_OFFBOARD.to_custom_mode():
            v.guided.times = [-1.5 + 0.1 * i for i in range(15)]  # as if a stream had been running
