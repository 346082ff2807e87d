"""A multicopter as a point mass: a cascaded position -> velocity -> acceleration controller with speed and
acceleration limits, a yaw loop, ground contact, free fall when disarmed in the air, and actuation noise.

Frames: local NED (x north, y east, z down) [m]; yaw 0 = north, clockwise positive [rad]. The ground is z = 0
(home altitude); the vehicle cannot go below it.

The position loop is a square-root controller (as ArduPilot's AC_PosControl): linear near the target, and
limited to the speed from which the vehicle can still stop with half its acceleration limit, so it does not
overshoot. Actuation noise (the paper's N(0, 0.1^2) per move) is drawn once per period per horizontal axis and
spread evenly over that period as a velocity disturbance, so the vehicle ends each period displaced by the draw
from where its controller would have put it; the controller then corrects.
"""

from __future__ import annotations

import enum
import math
from dataclasses import dataclass, field
from typing import Protocol

import numpy as np

from sim.world.model import FloatArray

__all__ = ["ControlTarget", "Controller", "Limits", "TargetKind", "VehicleState", "step_dynamics", "wrap_pi"]

GRAVITY_M_S2 = 9.80665
KP_POS = 1.0  # position loop gain [1/s]
KV_VEL = 3.0  # velocity loop gain [1/s]
KP_YAW = 2.0  # yaw loop gain [1/s]
MAX_YAW_RATE_RAD_S = math.radians(90.0)
ACC_Z_MAX_M_S2 = 4.0
CRASH_IMPACT_M_S = 4.0  # vertical speed at ground contact above which a fall is a crash


def wrap_pi(a: float) -> float:
    return (a + math.pi) % (2 * math.pi) - math.pi


class TargetKind(enum.Enum):
    HOLD = "hold"  # stop and hold the position where the target was set
    POSITION = "position"  # pos (optionally with vel / acc feed-forward)
    VELOCITY = "velocity"  # vel (optionally with acc feed-forward)
    ACCELERATION = "acceleration"
    GROUND = "ground"  # stay on the ground (motors idle or off)


@dataclass(slots=True)
class ControlTarget:
    """What the controller tracks. Fields unused by ``kind`` are None."""

    kind: TargetKind = TargetKind.GROUND
    pos_ned_m: FloatArray | None = None
    vel_ned_m_s: FloatArray | None = None
    acc_ned_m_s2: FloatArray | None = None
    yaw_rad: float | None = None
    yaw_rate_rad_s: float | None = None
    face_travel: bool = False  # no yaw given: turn to face the horizontal velocity command
    speed_h_m_s: float | None = None  # cap for position targets (cruise); None = the hard limit


@dataclass(frozen=True, slots=True, kw_only=True)
class Limits:
    speed_h_m_s: float = 5.0
    speed_up_m_s: float = 2.5
    speed_down_m_s: float = 1.5
    accel_h_m_s2: float = 2.5
    yaw_rate_rad_s: float = MAX_YAW_RATE_RAD_S  # the most the heading turns towards a target yaw [rad/s]


@dataclass(slots=True)
class VehicleState:
    pos_ned_m: FloatArray = field(default_factory=lambda: np.zeros(3))
    vel_ned_m_s: FloatArray = field(default_factory=lambda: np.zeros(3))
    acc_ned_m_s2: FloatArray = field(default_factory=lambda: np.zeros(3))
    yaw_rad: float = 0.0
    yaw_rate_rad_s: float = 0.0
    on_ground: bool = True

    @property
    def alt_m(self) -> float:
        """Height above home/ground [m]."""
        return -float(self.pos_ned_m[2])

    def attitude_rad(self) -> tuple[float, float]:
        """(roll, pitch) that produce the current horizontal acceleration (small-angle multicopter)."""
        a = self.acc_ned_m_s2
        c, s = math.cos(self.yaw_rad), math.sin(self.yaw_rad)
        a_fwd = c * a[0] + s * a[1]
        a_right = -s * a[0] + c * a[1]
        return math.atan2(a_right, GRAVITY_M_S2), -math.atan2(a_fwd, GRAVITY_M_S2)


class Controller(Protocol):
    """A position controller other than the built-in cascade (sim/vehicle/poscontrol.py): it keeps state."""

    def accel(
        self, state: VehicleState, target: ControlTarget, limits: Limits, dt: float
    ) -> tuple[FloatArray, float | None]: ...

    def relax(self, state: VehicleState) -> None: ...


def _sqrt_controller(err: FloatArray, kp: float, accel: float) -> FloatArray:
    """Velocity towards an error vector: kp*err near it, sqrt(2*a*d) far away (ArduPilot's sqrt_controller)."""
    d = float(np.hypot.reduce(err)) if err.size > 1 else abs(float(err[0]))
    if d < 1e-9:
        return np.zeros_like(err)
    linear = accel / (kp * kp)
    speed = kp * d if d <= linear else math.sqrt(2.0 * accel * (d - 0.5 * linear))
    return err * (speed / d)


def _limit_norm(v: FloatArray, cap: float) -> FloatArray:
    n = float(np.hypot.reduce(v))
    return v * (cap / n) if n > cap else v


def step_dynamics(
    state: VehicleState,
    target: ControlTarget,
    limits: Limits,
    dt: float,
    *,
    armed: bool,
    disturbance_vel_ne_m_s: FloatArray | None = None,
    controller: Controller | None = None,
) -> float:
    """Advance ``state`` by ``dt`` seconds in place. Returns the downward speed at ground contact (0 if none).

    On the ground the vehicle stays put unless it is armed and its controller asks to climb (lift-off).
    ``controller`` None = the built-in square-root cascade (``simple`` dynamics).
    """
    p, v = state.pos_ned_m, state.vel_ned_m_s
    travel_yaw: float | None = None
    if not armed:
        if controller is not None:
            controller.relax(state)
        if state.on_ground:
            _rest(state)
            return 0.0
        acc = np.array([0.0, 0.0, GRAVITY_M_S2])  # motors off in the air: free fall, no control
        state.yaw_rate_rad_s = 0.0
    else:
        if target.kind is TargetKind.GROUND and state.on_ground:
            if controller is not None:
                controller.relax(state)
            _rest(state)
            return 0.0
        if controller is None:
            acc, travel_yaw = _control_accel(state, target, limits)
        else:
            acc, travel_yaw = controller.accel(state, target, limits, dt)
        if state.on_ground and acc[2] >= -1e-6:
            _rest(state)
            return 0.0
        _yaw_step(state, target, travel_yaw, dt, limits.yaw_rate_rad_s)
        state.on_ground = False
    v += acc * dt
    v[:2] = _limit_norm(v[:2].copy(), max(limits.speed_h_m_s, 0.0) * 1.05)
    if armed:
        v[2] = min(max(v[2], -limits.speed_up_m_s * 1.05), limits.speed_down_m_s * 1.05 + 0.5)
    p += v * dt
    if disturbance_vel_ne_m_s is not None:
        p[:2] += disturbance_vel_ne_m_s * dt
    state.acc_ned_m_s2[:] = acc
    if p[2] >= 0.0 and v[2] >= 0.0:  # ground contact while not climbing: touchdown
        impact = float(v[2])
        state.on_ground = True
        _rest(state)
        return max(impact, 1e-9)
    return 0.0


def _rest(state: VehicleState) -> None:
    state.vel_ned_m_s[:] = 0.0
    state.acc_ned_m_s2[:] = 0.0
    state.yaw_rate_rad_s = 0.0
    state.pos_ned_m[2] = 0.0


def _control_accel(state: VehicleState, target: ControlTarget, limits: Limits) -> tuple[FloatArray, float | None]:
    """The acceleration command, and the heading of travel when the target asks to face it."""
    p, v = state.pos_ned_m, state.vel_ned_m_s
    travel_yaw: float | None = None
    a_h = limits.accel_h_m_s2
    acc_ff = np.zeros(3) if target.acc_ned_m_s2 is None else target.acc_ned_m_s2
    if target.kind is TargetKind.ACCELERATION:
        acc = acc_ff.copy()
        # no velocity feedback: keep within speed limits by braking at them
    else:
        if target.kind in (TargetKind.POSITION, TargetKind.HOLD) and target.pos_ned_m is not None:
            err = target.pos_ned_m - p
            cruise = limits.speed_h_m_s if target.speed_h_m_s is None else min(target.speed_h_m_s, limits.speed_h_m_s)
            v_cmd_h = _limit_norm(_sqrt_controller(err[:2], KP_POS, 0.5 * a_h), cruise)
            v_cmd_z = _sqrt_controller(err[2:], KP_POS, 0.5 * ACC_Z_MAX_M_S2)[0]
            v_cmd = np.array([v_cmd_h[0], v_cmd_h[1], v_cmd_z])
            if target.vel_ned_m_s is not None:
                v_cmd = v_cmd + target.vel_ned_m_s
        elif target.kind is TargetKind.VELOCITY and target.vel_ned_m_s is not None:
            v_cmd = target.vel_ned_m_s.copy()
        else:  # GROUND while airborne and armed: descend gently
            v_cmd = np.array([0.0, 0.0, limits.speed_down_m_s])
        v_cmd[:2] = _limit_norm(v_cmd[:2], limits.speed_h_m_s)
        v_cmd[2] = min(max(v_cmd[2], -limits.speed_up_m_s), limits.speed_down_m_s)
        acc = acc_ff + KV_VEL * (v_cmd - v)
        if target.face_travel and math.hypot(v_cmd[0], v_cmd[1]) > 0.5:
            travel_yaw = math.atan2(v_cmd[1], v_cmd[0])
    acc[:2] = _limit_norm(acc[:2], a_h)
    acc[2] = min(max(acc[2], -ACC_Z_MAX_M_S2), ACC_Z_MAX_M_S2)
    return np.asarray(acc, dtype=np.float64), travel_yaw


def _face(state: VehicleState, yaw_goal: float, max_rate: float) -> None:
    state.yaw_rate_rad_s = min(max(KP_YAW * wrap_pi(yaw_goal - state.yaw_rad), -max_rate), max_rate)


def _yaw_step(state: VehicleState, target: ControlTarget, travel_yaw: float | None, dt: float, max_rate: float) -> None:
    """Turn towards the target's yaw (or yaw rate, or the heading of travel) at most ``max_rate`` [rad/s]; with none
    of them the heading is kept."""
    if target.yaw_rate_rad_s is not None:
        state.yaw_rate_rad_s = min(max(target.yaw_rate_rad_s, -MAX_YAW_RATE_RAD_S), MAX_YAW_RATE_RAD_S)
    elif target.yaw_rad is not None:
        _face(state, target.yaw_rad, max_rate)
    elif travel_yaw is not None:
        _face(state, travel_yaw, max_rate)
    else:
        state.yaw_rate_rad_s = 0.0
    state.yaw_rad = wrap_pi(state.yaw_rad + state.yaw_rate_rad_s * dt)
