"""The external (GUIDED / OFFBOARD) setpoint: decoding SET_POSITION_TARGET_* into local NED, and its state.

ArduCopter: ``GCS_MAVLink_Copter.cpp`` (handle_message_set_position_target_*) turns the message into a
position / velocity / acceleration target for ``mode_guided.cpp``; the frame decides whether the position is
absolute (LOCAL_NED), relative to the vehicle (LOCAL_OFFSET_NED) or relative and rotated by its heading
(BODY_NED / BODY_OFFSET_NED, which also rotate velocity, acceleration and yaw).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from pymavlink.dialects.v20 import ardupilotmega as mavlink

from apf_companion.autopilot import ACC_IGNORE, MASK_POSITION, POS_IGNORE, VEL_IGNORE, TypeMask
from sim.vehicle.dynamics import TargetKind, wrap_pi
from sim.vehicle.geo import BODY_FRAMES
from sim.world.model import FloatArray

__all__ = [
    "GuidedState",
    "Setpoint",
    "classify_mask_arducopter",
    "decode_setpoint",
    "position_setpoint",
    "stop_setpoint",
]

MAX_SETPOINT_TIMES = 200  # arrival times kept (PX4's proof of life needs only the last second or so)


@dataclass(slots=True)
class Setpoint:
    """A target in local NED; fields the type_mask ignores are None."""

    kind: TargetKind
    type_mask: int
    t_rx: float
    pos: FloatArray | None
    vel: FloatArray | None
    acc: FloatArray | None
    yaw: float | None
    yaw_rate: float | None


def position_setpoint(t_s: float, pos_ned_m: FloatArray) -> Setpoint:
    """A plain position target (as after a takeoff or a DO_REPOSITION)."""
    return Setpoint(TargetKind.POSITION, MASK_POSITION, t_s, pos_ned_m, None, None, None, None)


@dataclass(slots=True)
class GuidedState:
    """The setpoint in force and when setpoints arrived (one owner: the engine's setpoint input)."""

    sp: Setpoint | None = None
    times: list[float] = field(default_factory=list)  # recent arrival times (PX4's proof of life)
    timed_out: bool = False  # GUID_TIMEOUT already logged for this setpoint
    fixed_yaw_rad: float | None = None  # MAV_CMD_CONDITION_YAW's heading, until the next setpoint

    def received(self, t_s: float) -> None:
        self.times.append(t_s)
        if len(self.times) > MAX_SETPOINT_TIMES:
            del self.times[: MAX_SETPOINT_TIMES // 2]

    @property
    def last_t_s(self) -> float | None:
        return self.times[-1] if self.times else None

    def set(self, sp: Setpoint | None) -> None:
        self.sp = sp
        self.timed_out = False
        self.fixed_yaw_rad = None  # ArduCopter: a new target resets auto_yaw to its default (mode_guided.cpp)


def classify_mask_arducopter(mask: int) -> TargetKind | None:
    """ArduCopter's reading of a type_mask (GCS_MAVLink_Copter.cpp handle_message_set_position_target_local_ned):
    a group (position, velocity, acceleration) is ignored when any of its bits is set; position+velocity(+accel),
    velocity(+accel), acceleration alone or position alone are flown; FORCE with an acceleration and every other
    combination is "input is not valid so stop" (None: the caller commands a stop)."""
    use_pos, use_vel, use_acc = (not mask & bits for bits in (POS_IGNORE, VEL_IGNORE, ACC_IGNORE))
    if mask & TypeMask.FORCE_SET and use_acc:
        return None
    if use_pos and (use_vel or not use_acc):
        return TargetKind.POSITION
    if use_vel:
        return TargetKind.VELOCITY
    if use_acc and not use_pos:
        return TargetKind.ACCELERATION
    return None


def stop_setpoint(t_s: float, type_mask: int) -> Setpoint:
    """ArduCopter's answer to an invalid setpoint: ``ModeGuided::init`` starts the velocity controller at zero
    velocity, so the vehicle decelerates and holds where it stops."""
    return Setpoint(TargetKind.VELOCITY, type_mask, t_s, None, np.zeros(3), None, None, None)


def decode_setpoint(
    msg: Any,
    frame: int,
    pos_in: FloatArray,
    kind: TargetKind,
    *,
    mask: int,
    t_s: float,
    pos_now_ned_m: FloatArray,
    yaw_now_rad: float,
    body_yaw_relative: bool = True,
) -> Setpoint | None:
    """The message's fields under ``mask`` in local NED (``pos_in`` decoded by the caller); None if not finite."""
    c, s = math.cos(yaw_now_rad), math.sin(yaw_now_rad)
    body = frame in BODY_FRAMES

    def rot(v: FloatArray) -> FloatArray:
        return np.array([c * v[0] - s * v[1], s * v[0] + c * v[1], v[2]]) if body else v

    pos = vel = acc = None
    if not mask & POS_IGNORE:
        pos = rot(pos_in)
        if frame != mavlink.MAV_FRAME_LOCAL_NED:
            pos = pos + pos_now_ned_m
    if not mask & VEL_IGNORE:
        vel = rot(np.array([msg.vx, msg.vy, msg.vz], dtype=np.float64))
    if not mask & ACC_IGNORE:
        acc = rot(np.array([msg.afx, msg.afy, msg.afz], dtype=np.float64))
    yaw_offset = yaw_now_rad if body and body_yaw_relative else 0.0
    yaw = None if mask & TypeMask.YAW_IGNORE else wrap_pi(msg.yaw + yaw_offset)
    yaw_rate = None if mask & TypeMask.YAW_RATE_IGNORE else float(msg.yaw_rate)
    values = [v for v in (pos, vel, acc) if v is not None]
    if not all(np.all(np.isfinite(v)) for v in values) or (yaw is not None and not math.isfinite(yaw)):
        return None
    return Setpoint(kind, mask, t_s, pos, vel, acc, yaw, yaw_rate)
