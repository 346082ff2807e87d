"""ArduCopter's position controller shape: a jerk- and acceleration-limited desired trajectory that the vehicle
tracks with a position P / velocity PI loop and a lagging attitude (thrust-vector) response.

Re-derived from the maths ArduPilot documents (this project is MIT; ArduPilot is GPL, no code is copied):

- ``libraries/AP_Math/control.cpp``: ``sqrt_controller`` (linear near the error, sqrt(2*a*d) far away),
  ``shape_pos_vel_accel[_xy]`` (velocity from the position error with gain 0.5*jerk/accel and half the
  acceleration limit, plus the target's velocity), ``shape_vel_accel[_xy]`` (acceleration from the velocity error
  with gain jerk/accel, limited), ``shape_accel`` (the acceleration moves towards that at most jerk*dt per step),
  ``update_pos_vel_accel`` (the desired position and velocity integrate the shaped acceleration);
- ``libraries/AC_AttitudeControl/AC_PosControl.cpp``: ``input_pos_vel_accel_NE_cm`` / ``_U_cm`` shape the desired
  state towards the input, ``update_NE_controller`` / ``update_U_controller`` track it (PSC_POSXY_P 1,
  PSC_VELXY_P 2, PSC_VELXY_I 1, PSC_POSZ_P 1, PSC_VELZ_P 5), limits from WPNAV_SPEED, WPNAV_ACCEL,
  WPNAV_SPEED_UP/DN, WPNAV_ACCEL_Z and PSC_JERK_XY / PSC_JERK_Z (5 m/s^3);
- ``ArduCopter/mode.cpp`` ``auto_takeoff_run``: the motors spool up (MOT_SPOOL_TIME), then the throttle slews
  over TKOFF_SLEW_TIME and the vehicle is declared off the ground at 90 % throttle; only then does the vertical
  controller (re-initialised at the vehicle's state) fly the climb.

The vehicle's lean (horizontal acceleration) follows the command with a first-order lag of ATC_INPUT_TC (0.15 s,
the attitude input shaping), and air drag (``SIM_DRAG``, fitted to the SITL step) slows it; the velocity I term
makes up for the drag during a move and unwinds after it, which gives the real vehicle's overshoot at a stop
(0.2 m after 5 m) and its slow creep back.
Frames: local NED [m]; "up" limits are negative z velocities.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from sim.vehicle.dynamics import ControlTarget, Limits, TargetKind, VehicleState
from sim.vehicle.params import ParamTable
from sim.world.model import FloatArray

__all__ = ["ArduCopterPosControl", "PscParams", "shape_accel", "sqrt_controller"]

GRAVITY_M_S2 = 9.80665
LIFTOFF_THROTTLE = 0.9  # mode.cpp auto_takeoff_run: land_complete clears at 90 % throttle
THRUST_TC_S = 0.1  # the vertical response (collective thrust) is faster than the lean-angle response


@dataclass(frozen=True, slots=True)
class PscParams:
    """The controller's parameters (ArduCopter names and units converted to SI)."""

    jerk_h_m_s3: float
    jerk_z_m_s3: float
    accel_z_m_s2: float
    kp_pos_h: float
    kp_vel_h: float
    ki_vel_h: float
    kp_pos_z: float
    kp_vel_z: float
    tilt_max_rad: float
    att_tc_s: float
    drag_1_s: float
    liftoff_delay_s: float

    @classmethod
    def from_params(cls, p: ParamTable) -> PscParams:
        return cls(
            jerk_h_m_s3=p["PSC_JERK_XY"],
            jerk_z_m_s3=p["PSC_JERK_Z"],
            accel_z_m_s2=p["WPNAV_ACCEL_Z"] / 100.0,
            kp_pos_h=p["PSC_POSXY_P"],
            kp_vel_h=p["PSC_VELXY_P"],
            ki_vel_h=p["PSC_VELXY_I"],
            kp_pos_z=p["PSC_POSZ_P"],
            kp_vel_z=p["PSC_VELZ_P"],
            tilt_max_rad=math.radians(p["ANGLE_MAX"] / 100.0),
            att_tc_s=max(p["ATC_INPUT_TC"], 0.01),
            drag_1_s=p["SIM_DRAG"],
            liftoff_delay_s=p["MOT_SPOOL_TIME"] + LIFTOFF_THROTTLE * p["TKOFF_SLEW_TIME"],
        )


def sqrt_controller(err: FloatArray, kp: float, accel: float) -> FloatArray:
    """The correction for an error vector: kp*err near it, sqrt(2*accel*(d - d_lin/2)) beyond d_lin = accel/kp^2
    (AP_Math/control.cpp sqrt_controller: the rate that can still be stopped at ``accel``)."""
    d = float(np.sqrt(np.dot(err, err)))
    if d < 1e-12:
        return np.zeros_like(err)
    if kp <= 0.0:
        return err * (math.sqrt(2.0 * accel * d) / d)
    linear = accel / (kp * kp)
    out = kp * d if d <= linear else math.sqrt(2.0 * accel * (d - 0.5 * linear))
    return err * (out / d)


def _limit(v: FloatArray, cap: float) -> FloatArray:
    n = float(np.sqrt(np.dot(v, v)))
    return v * (cap / n) if n > cap > 0.0 else v


def shape_accel(acc_goal: FloatArray, acc: FloatArray, jerk: float, dt: float) -> FloatArray:
    """Move ``acc`` towards ``acc_goal`` by at most jerk*dt (control.cpp shape_accel_xy)."""
    return acc + _limit(acc_goal - acc, jerk * dt)


def shape_vel_accel(
    vel_in: FloatArray, acc_in: FloatArray, vel: FloatArray, acc: FloatArray, a_max: float, jerk: float, dt: float
) -> FloatArray:
    """Jerk-limited acceleration towards a velocity (control.cpp shape_vel_accel_xy): gain jerk/accel."""
    a_goal = _limit(sqrt_controller(vel_in - vel, jerk / a_max, jerk), a_max) + acc_in
    return shape_accel(_limit(a_goal, a_max), acc, jerk, dt)


def shape_pos_vel_accel(
    pos_in: FloatArray,
    vel_in: FloatArray,
    acc_in: FloatArray,
    state: tuple[FloatArray, FloatArray, FloatArray],
    v_max: float,
    a_max: float,
    jerk: float,
    dt: float,
) -> FloatArray:
    """Jerk-limited acceleration towards a position and velocity (control.cpp shape_pos_vel_accel_xy): the
    position loop has gain 0.5*jerk/accel and uses half the acceleration, so the stop is always reachable."""
    pos, vel, acc = state
    vel_goal = _limit(sqrt_controller(pos_in - pos, 0.5 * jerk / a_max, 0.5 * a_max), v_max) + vel_in
    return shape_vel_accel(_limit(vel_goal, v_max), acc_in, vel, acc, a_max, jerk, dt)


class _Axis:
    """The desired trajectory of one group of axes (horizontal pair, or vertical)."""

    def __init__(self, n: int) -> None:
        self.pos = np.zeros(n)
        self.vel = np.zeros(n)
        self.acc = np.zeros(n)

    def reset(self, pos: FloatArray, vel: FloatArray) -> None:
        self.pos[:] = pos
        self.vel[:] = vel
        self.acc[:] = 0.0

    def advance(self, acc: FloatArray, dt: float) -> None:
        """control.cpp update_pos_vel_accel: integrate the shaped acceleration."""
        self.pos += self.vel * dt + 0.5 * acc * dt * dt
        self.vel += acc * dt
        self.acc[:] = acc


class ArduCopterPosControl:
    """AC_PosControl as the simulator models it: shaped desired state, tracking loops, attitude lag."""

    def __init__(self, params: ParamTable) -> None:
        self._params = params
        self.h = _Axis(2)
        self.z = _Axis(1)
        self._vel_i = np.zeros(2)  # PSC_VELXY_I integrator [m/s^2]
        self._acc_out = np.zeros(3)  # the vehicle's acceleration response [m/s^2]
        self._ground_s = 0.0  # time spent spooling / slewing the throttle on the ground
        self._engaged = False  # the desired state follows the vehicle until the controller runs

    def relax(self, state: VehicleState) -> None:
        """Re-initialise at the vehicle's state (landed, disarmed: AC_PosControl init_*_controller)."""
        self._ground_s = 0.0
        self._engaged = False

    def _init_at(self, state: VehicleState) -> None:
        self._engaged = True
        self.h.reset(state.pos_ned_m[:2], state.vel_ned_m_s[:2])
        self.z.reset(state.pos_ned_m[2:], state.vel_ned_m_s[2:])
        self._vel_i[:] = 0.0
        self._acc_out[:] = 0.0

    def accel(
        self, state: VehicleState, target: ControlTarget, limits: Limits, dt: float
    ) -> tuple[FloatArray, float | None]:
        """The vehicle's acceleration this step, and the heading of travel when the target asks to face it."""
        psc = PscParams.from_params(self._params)
        if not self._engaged:
            self._init_at(state)
        if state.on_ground:
            self._init_at(state)
            if not self._spooled(target, psc, dt):
                return np.zeros(3), None
        else:
            self._ground_s = 0.0
        self._shape(target, limits, psc, dt)
        acc_cmd = self._track(state, psc, dt)
        self._acc_out[:2] += (acc_cmd[:2] - self._acc_out[:2]) * min(1.0, dt / psc.att_tc_s)
        self._acc_out[2] += (acc_cmd[2] - self._acc_out[2]) * min(1.0, dt / THRUST_TC_S)
        acc = self._acc_out.copy()
        acc[:2] -= psc.drag_1_s * state.vel_ned_m_s[:2]  # air drag: the velocity integrator makes up for it
        travel_yaw = None
        if target.face_travel and math.hypot(*self.h.vel) > 0.5:
            travel_yaw = math.atan2(self.h.vel[1], self.h.vel[0])
        return acc, travel_yaw

    def _spooled(self, target: ControlTarget, psc: PscParams, dt: float) -> bool:
        """On the ground: a climb starts only after spool-up and the takeoff throttle slew (mode.cpp)."""
        wants_up = target.kind is not TargetKind.GROUND and (
            (target.pos_ned_m is not None and target.pos_ned_m[2] < -0.05)
            or (target.vel_ned_m_s is not None and target.vel_ned_m_s[2] < 0.0)
        )
        if not wants_up:
            self._ground_s = 0.0
            return False
        self._ground_s += dt
        return self._ground_s >= psc.liftoff_delay_s

    def _shape(self, target: ControlTarget, limits: Limits, psc: PscParams, dt: float) -> None:
        """Shape the desired trajectory towards the target (AC_PosControl input_*), per axis group."""
        a_h, a_z = limits.accel_h_m_s2, psc.accel_z_m_s2
        cruise = limits.speed_h_m_s if target.speed_h_m_s is None else min(target.speed_h_m_s, limits.speed_h_m_s)
        vel_in = np.zeros(3) if target.vel_ned_m_s is None else target.vel_ned_m_s
        acc_in = np.zeros(3) if target.acc_ned_m_s2 is None else target.acc_ned_m_s2
        kind = target.kind
        if kind in (TargetKind.POSITION, TargetKind.HOLD) and target.pos_ned_m is not None:
            p = target.pos_ned_m
            st_h = (self.h.pos, self.h.vel, self.h.acc)
            acc_h = shape_pos_vel_accel(p[:2], vel_in[:2], acc_in[:2], st_h, cruise, a_h, psc.jerk_h_m_s3, dt)
            acc_z = self._shape_z_pos(float(p[2]), float(vel_in[2]), limits, psc, dt)
        elif kind is TargetKind.ACCELERATION:
            acc_h = shape_accel(acc_in[:2], self.h.acc, psc.jerk_h_m_s3, dt)
            acc_z = shape_accel(acc_in[2:], self.z.acc, psc.jerk_z_m_s3, dt)
        else:  # VELOCITY, or GROUND in the air (descend)
            if kind is not TargetKind.VELOCITY:
                vel_in = np.array([0.0, 0.0, limits.speed_down_m_s])
            acc_h = shape_vel_accel(vel_in[:2], acc_in[:2], self.h.vel, self.h.acc, a_h, psc.jerk_h_m_s3, dt)
            v_z = min(max(float(vel_in[2]), -limits.speed_up_m_s), limits.speed_down_m_s)
            acc_z = shape_vel_accel(np.array([v_z]), acc_in[2:], self.z.vel, self.z.acc, a_z, psc.jerk_z_m_s3, dt)
        self.h.advance(acc_h, dt)
        self.z.advance(acc_z, dt)
        self.h.vel[:] = _limit(self.h.vel, limits.speed_h_m_s)
        self.z.vel[0] = min(max(self.z.vel[0], -limits.speed_up_m_s), limits.speed_down_m_s)

    def _shape_z_pos(self, pos_d: float, vel_d: float, limits: Limits, psc: PscParams, dt: float) -> FloatArray:
        """Vertical shape_pos_vel_accel: the climb / descent speed limits differ (WPNAV_SPEED_UP / _DN)."""
        j, a = psc.jerk_z_m_s3, psc.accel_z_m_s2
        err = np.array([pos_d - self.z.pos[0]])
        v_goal = float(sqrt_controller(err, 0.5 * j / a, 0.5 * a)[0]) + vel_d
        v_goal = min(max(v_goal, -limits.speed_up_m_s), limits.speed_down_m_s)
        return shape_vel_accel(np.array([v_goal]), np.zeros(1), self.z.vel, self.z.acc, a, j, dt)

    def _track(self, state: VehicleState, psc: PscParams, dt: float) -> FloatArray:
        """update_NE_controller / update_U_controller: P on position, PI on velocity, plus the shaped acceleration."""
        p, v = state.pos_ned_m, state.vel_ned_m_s
        vel_h = self.h.vel + psc.kp_pos_h * (self.h.pos - p[:2])
        err_h = vel_h - v[:2]
        self._vel_i += psc.ki_vel_h * err_h * dt
        acc_h = self.h.acc + psc.kp_vel_h * err_h + self._vel_i
        a_tilt = GRAVITY_M_S2 * math.tan(psc.tilt_max_rad)
        if float(np.hypot(*acc_h)) > a_tilt:
            acc_h = _limit(acc_h, a_tilt)
            self._vel_i -= psc.ki_vel_h * err_h * dt  # anti-windup: hold the integrator while saturated
        vel_z = self.z.vel[0] + psc.kp_pos_z * (self.z.pos[0] - p[2])
        acc_z = self.z.acc[0] + psc.kp_vel_z * (vel_z - v[2])
        acc_z = min(max(acc_z, -GRAVITY_M_S2), GRAVITY_M_S2)
        return np.array([acc_h[0], acc_h[1], acc_z])
