"""Setpoints for the autopilot: SET_POSITION_TARGET_LOCAL_NED built from named type-mask constants.

Every setpoint is in MAV_FRAME_LOCAL_NED (1): absolute north/east/down from the EKF origin, the one frame both
ArduCopter (GUIDED) and PX4 (OFFBOARD) treat the same way. Navigation setpoints carry the planned point and a
velocity feed-forward along the step (``MASK_POS_VEL`` 0x0DC0: position and velocity used; acceleration, yaw and
yaw rate ignored). A hold is the same mask with zero velocity, so the vehicle brakes onto the point.

With a commanded heading (``[autopilot] yaw = "travel"``, the PX4 default: docs/service.md "Heading") a
navigation or hold setpoint also carries a yaw (``with_yaw``: ``MASK_POS_VEL_YAW``, the yaw bit cleared, yaw rate
still ignored): PX4 holds its present heading when the yaw is ignored, so a range sensor covering less than 360
degrees would only ever look where the nose pointed at the takeover.
"""

from __future__ import annotations

import dataclasses
import enum
import math
from dataclasses import dataclass
from typing import Any

import numpy as np
import numpy.typing as npt
from pymavlink.dialects.v20 import ardupilotmega as mavlink

from apf_companion.autopilot import MASK_POS_VEL, MASK_POS_VEL_YAW, MASK_POSITION, MASK_VELOCITY, TypeMask
from apf_companion.perception.coverage import wrap_pi_upper

__all__ = [
    "MAV_FRAME_LOCAL_NED",
    "Setpoint",
    "SetpointKind",
    "brake",
    "encode_setpoint",
    "hold",
    "look_yaw",
    "navigate",
    "silent_safe_velocity",
    "step_bearing",
    "with_yaw",
]

MAV_FRAME_LOCAL_NED: int = mavlink.MAV_FRAME_LOCAL_NED
_VALID_MASKS = frozenset({MASK_POS_VEL, MASK_POSITION, MASK_VELOCITY, MASK_POS_VEL_YAW})


class SetpointKind(enum.Enum):
    """Why a setpoint was sent (logs and status only; the autopilot sees the same message)."""

    NAVIGATE = "navigate"
    """The planner's next point with velocity feed-forward."""
    HOLD = "hold"
    """Stay at a point with zero velocity (HOLDING, ARRIVED, STUCK, local minimum)."""
    PRESTREAM = "prestream"
    """Hold at the current position while taking over or waiting for the pilot's switch (PX4 wants setpoints
    before OFFBOARD; ArduCopter ignores them outside GUIDED). Never a planner step, not flight time."""
    BRAKE = "brake"
    """Zero velocity, position ignored (``MASK_VELOCITY``): stop wherever the vehicle is, while the pose is not
    confirmed (docs/hardening.md): no position in it, so no spoofed position can pull the vehicle anywhere."""


@dataclass(frozen=True, slots=True, kw_only=True)
class Setpoint:
    """One SET_POSITION_TARGET_LOCAL_NED's content.

    Attributes:
        pos_ned_m: Target position, local NED [m].
        vel_ned_m_s: Velocity feed-forward, local NED [m/s].
        type_mask: POSITION_TARGET_TYPEMASK ignore bits (one of the named constants).
        kind: Why it is sent.
        yaw_rad: Heading to turn to, local NED (0 = north, clockwise) [rad]; None = ignored (the yaw bit set: the
            autopilot's own heading). Given exactly when ``type_mask`` uses the yaw (``MASK_POS_VEL_YAW``).
    """

    pos_ned_m: tuple[float, float, float]
    vel_ned_m_s: tuple[float, float, float]
    type_mask: int
    kind: SetpointKind
    yaw_rad: float | None = None

    def __post_init__(self) -> None:
        # Internal invariant: a setpoint with a NaN never reaches the wire.
        if not all(math.isfinite(v) for v in (*self.pos_ned_m, *self.vel_ned_m_s)):
            msg = f"setpoint must be finite: {self.pos_ned_m} {self.vel_ned_m_s}"
            raise ValueError(msg)
        if self.type_mask not in _VALID_MASKS:
            msg = f"type_mask {self.type_mask:#06x} is not one of the named masks"
            raise ValueError(msg)
        if (self.yaw_rad is None) != bool(self.type_mask & TypeMask.YAW_IGNORE):
            msg = f"yaw {self.yaw_rad} does not match type_mask {self.type_mask:#06x}"
            raise ValueError(msg)
        if self.yaw_rad is not None and not math.isfinite(self.yaw_rad):
            msg = f"setpoint yaw must be finite: {self.yaw_rad}"
            raise ValueError(msg)


def _vec3(v: npt.ArrayLike) -> tuple[float, float, float]:
    a = np.asarray(v, dtype=np.float64).reshape(3)
    return (float(a[0]), float(a[1]), float(a[2]))


def hold(pos_ned_m: npt.ArrayLike, kind: SetpointKind = SetpointKind.HOLD) -> Setpoint:
    """Hold at ``pos_ned_m`` (3,) with zero velocity."""
    return Setpoint(pos_ned_m=_vec3(pos_ned_m), vel_ned_m_s=(0.0, 0.0, 0.0), type_mask=MASK_POS_VEL, kind=kind)


def with_yaw(sp: Setpoint, yaw_rad: float) -> Setpoint:
    """``sp`` (a position + velocity setpoint: navigate or hold) also turning the vehicle to ``yaw_rad`` (local
    NED, wrapped to [-pi, pi)); the yaw bit of the mask cleared, the yaw rate still ignored."""
    if sp.type_mask not in (MASK_POS_VEL, MASK_POS_VEL_YAW):
        msg = f"internal: a yaw on a {sp.kind.value} setpoint (type_mask {sp.type_mask:#06x})"
        raise AssertionError(msg)
    yaw = (yaw_rad + math.pi) % (2.0 * math.pi) - math.pi
    return dataclasses.replace(sp, type_mask=MASK_POS_VEL_YAW, yaw_rad=yaw)


def look_yaw(bearing_ned_rad: float, look_offset_rad: float) -> float:
    """The heading (local NED [rad], wrapped to (-pi, pi]) that points a sensor centred ``look_offset_rad`` off the
    nose (body FRD, clockwise) along ``bearing_ned_rad``; a non-finite offset counts as 0 (the nose), so no NaN
    ever reaches a setpoint's yaw."""
    offset = look_offset_rad if math.isfinite(look_offset_rad) else 0.0
    return wrap_pi_upper(bearing_ned_rad - offset)


def step_bearing(sp: Setpoint | None, pos_ned_m: npt.ArrayLike, min_m: float) -> float | None:
    """The horizontal bearing (local NED, ``atan2(east, north)`` [rad]) from ``pos_ned_m`` to a navigation
    setpoint's point, or None: not a navigation setpoint, or a step shorter than ``min_m``."""
    if sp is None or sp.kind is not SetpointKind.NAVIGATE:
        return None
    pos = np.asarray(pos_ned_m, dtype=np.float64)
    dn, de = sp.pos_ned_m[0] - float(pos[0]), sp.pos_ned_m[1] - float(pos[1])
    return math.atan2(de, dn) if math.hypot(dn, de) >= min_m else None


def brake() -> Setpoint:
    """Stop where the vehicle is: zero velocity; the position fields are ignored (``MASK_VELOCITY``) and zero, so
    not even a consumer that misreads the mask is sent towards an unconfirmed position."""
    zero = (0.0, 0.0, 0.0)
    return Setpoint(pos_ned_m=zero, vel_ned_m_s=zero, type_mask=MASK_VELOCITY, kind=SetpointKind.BRAKE)


def navigate(pos_ned_m: npt.ArrayLike, next_ned_m: npt.ArrayLike, *, cruise_speed_m_s: float, dim: int) -> Setpoint:
    """Go to ``next_ned_m`` (3,) with a velocity feed-forward of ``cruise_speed_m_s`` along the planned step.

    In 2D the feed-forward is horizontal (the altitude is held by the position part alone).
    """
    here = np.asarray(pos_ned_m, dtype=np.float64).reshape(3)
    there = np.asarray(next_ned_m, dtype=np.float64).reshape(3)
    step = there - here
    if dim == 2:
        step[2] = 0.0
    norm = float(np.linalg.norm(step))
    vel = step * (cruise_speed_m_s / norm) if norm > 1e-9 else np.zeros(3)
    return Setpoint(pos_ned_m=_vec3(there), vel_ned_m_s=_vec3(vel), type_mask=MASK_POS_VEL, kind=SetpointKind.NAVIGATE)


def silent_safe_velocity(
    target_ned_m: npt.ArrayLike,
    vel_ned_m_s: npt.ArrayLike,
    obstacles_ned_m: npt.ArrayLike,
    *,
    horizon_s: float,
    max_drift_m: float,
    clearance_m: float,
    dim: int,
) -> tuple[float, float, float]:
    """The velocity feed-forward that stays safe if this is the last setpoint the autopilot receives.

    ArduCopter GUIDED (ArduCopter/mode_guided.cpp ``posvel_control_run`` / ``set_destination_posvel``) advances the
    position target along the velocity target every loop and zeroes the velocity only after GUID_TIMEOUT (3 s)
    without an update (AC_PosControl.cpp ``input_pos_vel_accel_xy`` -> ``update_pos_vel_accel_xy``): the vehicle
    drifts ``|v| * GUID_TIMEOUT`` past the setpoint's position. PX4 (PositionControl.cpp ``_positionControl``:
    ``vel_sp = vel_ff + K_p (pos_sp - pos)``) settles ``|v| / MPC_XY_P`` past it until the offboard-loss failsafe.
    So the speed is cut until that drift (over ``horizon_s``) is at most ``max_drift_m`` and the drift segment from
    the target stays ``clearance_m`` from every remembered obstacle point; zero when the target itself is that
    close. The direction is never changed.
    """
    v = np.asarray(vel_ned_m_s, dtype=np.float64).reshape(3).copy()
    speed = float(np.linalg.norm(v[:dim]))
    if speed <= 0.0:
        return _vec3(v)
    u = v[:dim] / speed
    drift = min(speed * horizon_s, max_drift_m)
    obs = np.asarray(obstacles_ned_m, dtype=np.float64).reshape(-1, 3)
    if obs.shape[0] and drift > 0.0:
        rel = obs[:, :dim] - np.asarray(target_ned_m, dtype=np.float64).reshape(3)[:dim]
        along = rel @ u
        perp_sq = np.maximum(np.einsum("ij,ij->i", rel, rel) - along * along, 0.0)
        hit = perp_sq < clearance_m * clearance_m
        entry = along[hit] - np.sqrt(clearance_m * clearance_m - perp_sq[hit])  # where the segment comes too close
        exit_ = along[hit] + np.sqrt(clearance_m * clearance_m - perp_sq[hit])
        blocking = entry[exit_ > 0.0]  # the part of the segment ahead of the target only
        if blocking.size:
            drift = min(drift, max(0.0, float(np.min(blocking))))
    scale = min(1.0, drift / (speed * horizon_s))
    return _vec3(v * scale)


def encode_setpoint(mav: Any, sp: Setpoint, *, time_boot_ms: int, target_system: int, target_component: int) -> Any:
    """The SET_POSITION_TARGET_LOCAL_NED message for ``sp`` (pymavlink ``MAVLink`` object ``mav``)."""
    x, y, z = sp.pos_ned_m
    vx, vy, vz = sp.vel_ned_m_s
    return mav.set_position_target_local_ned_encode(
        time_boot_ms & 0xFFFFFFFF,
        target_system,
        target_component,
        MAV_FRAME_LOCAL_NED,
        sp.type_mask,
        x,
        y,
        z,
        vx,
        vy,
        vz,
        0.0,
        0.0,
        0.0,
        0.0 if sp.yaw_rad is None else sp.yaw_rad,
        0.0,
    )
