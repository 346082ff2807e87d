"""ArduCopter: modes (``mode.h``), command rules (``GCS_MAVLink_Copter.cpp``), GUIDED setpoints (``mode_guided.cpp``).

HEARTBEAT autopilot ARDUPILOTMEGA, custom_mode = the ArduCopter mode number. GUIDED accepts SET_POSITION_TARGET_*
only when flying (not on the ground, not while a NAV_TAKEOFF climbs); a velocity or acceleration target is
zeroed after GUID_TIMEOUT (3 s) without an update; a position target is held indefinitely.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

from pymavlink.dialects.v20 import ardupilotmega as mavlink

from apf_companion.autopilot import Autopilot, CopterMode
from sim.vehicle.dynamics import Limits, TargetKind
from sim.vehicle.guided import Setpoint, classify_mask_arducopter, position_setpoint
from sim.vehicle.params import ParamTable
from sim.vehicle.profiles.base import Behaviour, ProfileTexts
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
_BEHAVIOUR = {int(CopterMode.GUIDED): Behaviour.GUIDED, int(CopterMode.LAND): Behaviour.LAND}
_BEHAVIOUR[int(CopterMode.RTL)] = Behaviour.RTL


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
        return round(p[1])

    def request_mode(self, v: VehicleEngine, custom_mode: int) -> int:
        if custom_mode not in MODES_OK:
            v.statustext(mavlink.MAV_SEVERITY_WARNING, f"Flight mode change failed {self.mode_name(custom_mode)}")
            return self.fail_result
        if v.crashed:
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

    def land_speed_m_s(self, params: ParamTable) -> float:
        return params["LAND_SPEED"] / 100.0

    def rtl_alt_m(self, params: ParamTable) -> float:
        return params["RTL_ALT"] / 100.0

    def takeoff_speed_up_m_s(self, params: ParamTable, limits: Limits) -> float:
        return limits.speed_up_m_s

    def disarm_delay_s(self, params: ParamTable) -> float:
        return params["DISARM_DELAY"]

    def face_travel(self, params: ParamTable) -> bool:
        return params["WP_YAW_BEHAVIOR"] > 0

    def guided_timeout_s(self, params: ParamTable) -> float | None:
        return params["GUID_TIMEOUT"]

    # -- command rules
    def arm_refusal(self, v: VehicleEngine, *, force: bool) -> str | None:
        if v.custom_mode in MODES_NO_ARM and not force:
            return "Arm: Mode not armable"
        return None

    def takeoff(self, v: VehicleEngine, p: tuple[float, ...]) -> int:
        """NAV_TAKEOFF: only armed, in GUIDED and landed; param7 = altitude above home [m]."""
        if v.custom_mode != CopterMode.GUIDED or not v.armed or not v.state.on_ground or not p[6] > 0:
            return int(mavlink.MAV_RESULT_FAILED)
        v.takeoff_alt_m = float(p[6])
        v.hold_pos_ned_m = v.state.pos_ned_m.copy()
        v.guided.sp = None
        return int(mavlink.MAV_RESULT_ACCEPTED)

    def reposition(self, v: VehicleEngine, p: tuple[float, ...], target_ned_m: FloatArray) -> int:
        """DO_REPOSITION: flies there in GUIDED; from another mode only with the CHANGE_MODE flag."""
        if v.custom_mode != CopterMode.GUIDED:
            if not round(p[1]) & mavlink.MAV_DO_REPOSITION_FLAGS_CHANGE_MODE:
                return int(mavlink.MAV_RESULT_FAILED)
            v.set_mode(int(CopterMode.GUIDED), "reposition")
        v.guided.sp = position_setpoint(v.t_s, target_ned_m)
        return int(mavlink.MAV_RESULT_ACCEPTED)

    def change_speed(self, params: ParamTable, speed_m_s: float) -> str | None:
        return params.set("WPNAV_SPEED", speed_m_s * 100.0)

    # -- setpoint rules
    def classify_mask(self, mask: int) -> tuple[TargetKind | None, str]:
        return classify_mask_arducopter(mask)

    def accepts_setpoint(self, v: VehicleEngine) -> bool:
        # setpoints are used only in GUIDED, not on the ground or during a takeoff
        return v.custom_mode == CopterMode.GUIDED and v.takeoff_alt_m is None and not v.state.on_ground

    def stays_on_ground(self, sp: Setpoint) -> bool:
        return False

    def takeoff_complete(self, v: VehicleEngine, target_ned_m: FloatArray) -> None:
        v.guided.sp = position_setpoint(v.t_s, target_ned_m)  # GUIDED holds the takeoff altitude

    def check_failsafes(self, v: VehicleEngine) -> None:
        return None

    def spawn_in_air(self, v: VehicleEngine) -> None:
        return None
