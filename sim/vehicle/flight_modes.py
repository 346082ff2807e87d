"""What each mode asks of the position controller, per step (ArduCopter's ``mode_guided.cpp``, ``mode_land.cpp``,
``mode_rtl.cpp``, ``mode_loiter.cpp`` handing targets to ``AC_PosControl``; PX4's FlightTasks).

``choose_target`` looks the mode's behaviour up in ``MODE_TARGETS``; each function returns the controller
target and the limits it flies with, and advances its mode's own phase (RTL climb/return/land, takeoff).
"""

from __future__ import annotations

import logging
from collections.abc import Callable
from typing import TYPE_CHECKING

import numpy as np

from sim.vehicle.dynamics import ControlTarget, Limits, TargetKind
from sim.vehicle.profiles import Behaviour, replace_limits
from sim.world.model import FloatArray

if TYPE_CHECKING:
    from sim.vehicle.engine import VehicleEngine

__all__ = ["MODE_TARGETS", "choose_target"]

log = logging.getLogger(__name__)

ModeTarget = Callable[["VehicleEngine", Limits], tuple[ControlTarget, Limits]]
RTL_CLIMB_TOLERANCE_M = 0.5  # RTL climbs to its altitude before it returns ...
RTL_ARRIVED_M = 0.5  # ... and lands when this close (horizontally) to home
TAKEOFF_DONE_M = 0.1  # a takeoff is complete this close below its altitude
GROUND = TargetKind.GROUND


def choose_target(v: VehicleEngine, limits: Limits) -> tuple[ControlTarget, Limits]:
    if not v.armed:
        return ControlTarget(kind=GROUND), limits
    behaviour = v.behaviour()
    climbing = v.takeoff_alt_m is not None and v.profile_rules.takeoff_in_guided
    if climbing and behaviour in (Behaviour.GUIDED, Behaviour.HOLD):
        behaviour = Behaviour.TAKEOFF  # ArduCopter climbs to a NAV_TAKEOFF's altitude inside GUIDED
    return MODE_TARGETS[behaviour](v, limits)


def _land(v: VehicleEngine, limits: Limits) -> tuple[ControlTarget, Limits]:
    st = v.state
    if st.on_ground:
        return ControlTarget(kind=GROUND), limits
    speed_down = v.profile_rules.land_speed_m_s(v.params, st.alt_m, limits)
    hold = v.hold_pos_ned_m.copy()
    hold[2] = 1.0  # below the ground: keep descending until touchdown
    return ControlTarget(kind=TargetKind.POSITION, pos_ned_m=hold), replace_limits(limits, speed_down_m_s=speed_down)


def _rtl(v: VehicleEngine, limits: Limits) -> tuple[ControlTarget, Limits]:
    """Climb to max(return altitude, current), fly home, then land (phase 2)."""
    if v.rtl_phase >= 2:
        return _land(v, limits)
    st = v.state
    rules = v.profile_rules
    alt = max(rules.rtl_alt_m(v.params), st.alt_m)
    if v.rtl_phase == 0:
        v.rtl_alt_m = alt
        v.rtl_phase = 1
    goal = np.array([0.0, 0.0, -v.rtl_alt_m])
    if v.rtl_phase == 1 and st.alt_m < v.rtl_alt_m - RTL_CLIMB_TOLERANCE_M:
        climb = st.pos_ned_m.copy()
        climb[2] = -v.rtl_alt_m
        return ControlTarget(kind=TargetKind.POSITION, pos_ned_m=climb), limits
    if float(np.hypot(*st.pos_ned_m[:2])) < RTL_ARRIVED_M:
        v.rtl_phase = 2
        v.hold_pos_ned_m = np.array([0.0, 0.0, 0.0])
    face = rules.face_travel(v.params)
    cruise = rules.cruise_m_s(v.params)
    return ControlTarget(kind=TargetKind.POSITION, pos_ned_m=goal, face_travel=face, speed_h_m_s=cruise), limits


def _takeoff(v: VehicleEngine, limits: Limits) -> tuple[ControlTarget, Limits]:
    alt = v.takeoff_alt_m if v.takeoff_alt_m is not None else v.params["MIS_TAKEOFF_ALT"]
    speed_up = v.profile_rules.takeoff_speed_up_m_s(v, limits)
    tgt = v.hold_pos_ned_m.copy()
    tgt[2] = -alt
    if v.state.alt_m >= alt - TAKEOFF_DONE_M:
        v.takeoff_alt_m = None
        v.hold_pos_ned_m = tgt
        v.profile_rules.takeoff_complete(v, tgt)
    return ControlTarget(kind=TargetKind.POSITION, pos_ned_m=tgt), replace_limits(limits, speed_up_m_s=speed_up)


def _guided(v: VehicleEngine, limits: Limits) -> tuple[ControlTarget, Limits]:
    """The external setpoint, with ArduCopter's GUID_TIMEOUT on velocity / acceleration targets."""
    st = v.state
    rules = v.profile_rules
    sp = v.guided.sp
    if sp is None:
        if st.on_ground:
            return ControlTarget(kind=GROUND), limits
        hold = ControlTarget(kind=TargetKind.HOLD, pos_ned_m=v.hold_pos_ned_m, yaw_rad=v.guided.fixed_yaw_rad)
        return hold, limits
    if st.on_ground and rules.stays_on_ground(sp):
        return ControlTarget(kind=GROUND), limits
    timeout_s = rules.guided_timeout_s(v.params)
    expired = timeout_s is not None and v.t_s - sp.t_rx > timeout_s
    if sp.kind in (TargetKind.VELOCITY, TargetKind.ACCELERATION) and expired:
        if not v.guided.timed_out:
            v.guided.timed_out = True
            log.info("sim.guided_timeout", extra={"t_s": v.t_s})
        return ControlTarget(kind=TargetKind.VELOCITY, vel_ned_m_s=np.zeros(3)), limits
    pos, vel, acc = sp.pos, sp.vel, sp.acc
    if sp.kind is TargetKind.POSITION and rules.advances_position_target and pos is not None and vel is not None:
        pos, vel, acc = _advanced(pos, vel, acc, v.t_s - sp.t_rx, timeout_s)
    elif sp.kind is TargetKind.POSITION and expired:
        vel = acc = None  # the feed-forward expires; the position is held
    fixed_yaw = v.guided.fixed_yaw_rad  # MAV_CMD_CONDITION_YAW
    target = ControlTarget(
        kind=sp.kind,
        pos_ned_m=pos,
        vel_ned_m_s=vel,
        acc_ned_m_s2=acc,
        yaw_rad=sp.yaw if fixed_yaw is None else fixed_yaw,
        yaw_rate_rad_s=sp.yaw_rate if fixed_yaw is None else None,
        face_travel=rules.face_travel(v.params) and fixed_yaw is None,
        speed_h_m_s=rules.cruise_m_s(v.params) if vel is None else None,
    )
    return target, limits


def _advanced(
    pos: FloatArray, vel: FloatArray, acc: FloatArray | None, age_s: float, timeout_s: float | None
) -> tuple[FloatArray, FloatArray | None, FloatArray | None]:
    """ArduCopter moves a position+velocity target along its velocity (AC_PosControl input_pos_vel_accel_NE_cm
    integrates the input with update_pos_vel_accel) until GUID_TIMEOUT zeroes the velocity and acceleration
    (mode_guided.cpp posvelaccel_control_run); then the advanced point is held."""
    expired = timeout_s is not None and age_s > timeout_s
    tau = age_s if timeout_s is None else min(age_s, timeout_s)
    a = np.zeros(3) if acc is None else acc
    pos_now = pos + vel * tau + 0.5 * a * tau * tau
    if expired:
        return pos_now, None, None
    return pos_now, vel + a * tau, acc


def _hold(v: VehicleEngine, limits: Limits) -> tuple[ControlTarget, Limits]:
    """LOITER, BRAKE, POSHOLD, STABILIZE / ALT_HOLD without RC, PX4 Hold."""
    if v.state.on_ground:
        return ControlTarget(kind=GROUND), limits
    cruise = v.profile_rules.cruise_m_s(v.params)
    return ControlTarget(kind=TargetKind.HOLD, pos_ned_m=v.hold_pos_ned_m, speed_h_m_s=cruise), limits


MODE_TARGETS: dict[Behaviour, ModeTarget] = {
    Behaviour.LAND: _land,
    Behaviour.RTL: _rtl,
    Behaviour.TAKEOFF: _takeoff,
    Behaviour.GUIDED: _guided,
    Behaviour.HOLD: _hold,
}
