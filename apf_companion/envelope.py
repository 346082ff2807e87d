"""Where the vehicle can be, not where the setpoint is: a braking envelope from its reported velocity.

A multicopter does not stop at its setpoint. ArduCopter's position controller shapes the path with an acceleration
limit (WPNAV_ACCEL, 2.5 m/s^2 by default) and a jerk limit (PSC_JERK_XY, 5 m/s^3), and the lean follows with a lag
(ATC_INPUT_TC, 0.15 s): at a turn it overshoots along its old heading by 0.16-0.20 m at 0.5-0.9 m/s (real SITL,
tests/data/arducopter_sitl_responses.toml). A companion that checks only its setpoints against its clearance
therefore grazes obstacles on the real vehicle. Two rules bound that, from the vehicle's side:

- **Stoppable speed.** The feed-forward along a step is capped so that the vehicle can still stop before coming
  within the tracking clearance of anything remembered along that direction, even past the step's end (the
  overshoot goes on along the same line): ``v <= -a t + sqrt((a t)^2 + 2 a D)``, the largest speed whose stopping
  distance ``v t + v^2 / (2 a)`` fits in the free distance ``D``. It is the rule of ArduPilot's own simple
  avoidance (libraries/AC_Avoidance/AC_Avoid.cpp ``get_max_speed``: ``sqrt_controller`` of the distance to the
  fence or obstacle at the avoidance acceleration), with the reaction time ``t`` made explicit.
- **Watch.** From the reported velocity (LOCAL_POSITION_NED vx/vy/vz): if following the setpoint, then stopping,
  could take the vehicle inside the tracking clearance, the cycle is counted (``envelope_warnings``), so a
  vehicle that overshoots more than the plan allows shows in the status. It does not override the plan: holding
  instead (at the vehicle's position or at its stopping point) made CR-BAPF* pass closer, not further, on the
  simulator's model of ArduCopter's position controller (docs/hardening.md, "Tracking margin").

Pure numpy; local NED; 2D uses north/east only (the altitude is held).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import numpy.typing as npt

__all__ = [
    "BrakingEnvelope",
    "free_distance_m",
    "polyline_distance_m",
    "stoppable_speed_m_s",
    "stopping_distance_m",
]

FloatArray = npt.NDArray[np.float64]
_EPS = 1e-9
TRANSITION_SAMPLES = 9  # points on the parabola of a velocity change (chords of <= 1/8 of it)
INSIDE_TOLERANCE_M = 0.02  # inside the clearance already: the disc is this much smaller than the distance now


def stopping_distance_m(speed_m_s: float, accel_m_s2: float, latency_s: float) -> float:
    """Distance covered while reacting for ``latency_s`` at ``speed_m_s``, then braking at ``accel_m_s2`` [m]."""
    return speed_m_s * latency_s + speed_m_s * speed_m_s / (2.0 * accel_m_s2)


def stoppable_speed_m_s(free_m: float, accel_m_s2: float, latency_s: float) -> float:
    """The largest speed whose ``stopping_distance_m`` fits in ``free_m`` (0 when there is no room) [m/s]."""
    if free_m <= 0.0:
        return 0.0
    at = accel_m_s2 * latency_s
    room = 2.0 * accel_m_s2 * free_m
    if room <= 0.0:
        return 0.0  # underflow: no room
    return room / (at + math.sqrt(at * at + room))  # = -at + sqrt(at^2 + room), without the cancellation


def free_distance_m(origin: FloatArray, direction: FloatArray, points: FloatArray, radius_m: float) -> float:
    """How far a disc (sphere) of ``radius_m`` can move from ``origin`` along unit ``direction`` before it touches a
    point of ``points`` (N, dim) [m]; ``inf`` when nothing lies in its way. A point already inside the disc
    gives 0 if it lies ahead (the disc cannot move towards it), and is ignored if it lies behind."""
    if points.shape[0] == 0:
        return math.inf
    rel = points - origin
    along = rel @ direction
    lateral2 = np.einsum("ij,ij->i", rel, rel) - along * along
    r2 = max(radius_m, 0.0) ** 2
    hit = (lateral2 < r2) & (along > 0.0)
    if not np.any(hit):
        return math.inf
    # Entry of the ray into each point's disc: along - sqrt(r^2 - lateral^2), clipped at 0 (already inside).
    entry = along[hit] - np.sqrt(np.maximum(r2 - lateral2[hit], 0.0))
    return float(max(0.0, np.min(entry)))


@dataclass(frozen=True, slots=True, kw_only=True)
class BrakingEnvelope:
    """The vehicle's braking envelope (``[safety] tracking_*``; docs/hardening.md, "Tracking margin").

    Attributes:
        accel_m_s2: The autopilot's horizontal braking acceleration (ArduCopter WPNAV_ACCEL / 100; PX4
            MPC_ACC_HOR); 0 = off [m/s^2].
        latency_s: Reaction time before that braking is reached: a cycle, the link, the jerk-limited build-up
            of the acceleration (accel / jerk / 2) and the attitude lag [s].
        clearance_m: Never closer than this to a remembered point, where the vehicle can be [m].
        dim: 2 (north, east) or 3.
    """

    accel_m_s2: float
    latency_s: float
    clearance_m: float
    dim: int = 2

    @property
    def enabled(self) -> bool:
        return self.accel_m_s2 > 0.0 and self.clearance_m > 0.0

    def _radius_m(self, pos: FloatArray, points: FloatArray) -> float:
        """The clearance to keep from here: ``clearance_m``, or, once noise has pushed the vehicle inside it, a
        little less than the distance it has now (never closer than now; moving along or away stays free)."""
        rel = points - pos
        nearest = float(np.sqrt(np.min(np.einsum("ij,ij->i", rel, rel))))
        return min(self.clearance_m, nearest - INSIDE_TOLERANCE_M)

    def speed_cap_m_s(self, pos: FloatArray, direction: FloatArray, points: FloatArray) -> float:
        """The highest feed-forward along ``direction`` (any length; local NED) from ``pos`` that can still stop
        ``clearance_m`` short of every point in ``points`` (N, 3) on that line [m/s]; ``inf`` when off or free."""
        d = np.asarray(direction, dtype=np.float64)[: self.dim]
        norm = float(np.sqrt(d @ d))
        if not self.enabled or norm < _EPS or points.shape[0] == 0:
            return math.inf
        here, pts = pos[: self.dim], points[:, : self.dim]
        free = free_distance_m(here, d / norm, pts, self._radius_m(here, pts))
        return math.inf if math.isinf(free) else stoppable_speed_m_s(free, self.accel_m_s2, self.latency_s)

    def transition_m(self, pos: FloatArray, vel: FloatArray, vel_cmd: FloatArray, points: FloatArray) -> float:
        """The closest the vehicle comes to ``points`` if it follows ``vel_cmd`` and nothing newer arrives: it
        keeps ``vel`` for ``latency_s``, changes it to ``vel_cmd`` at ``accel_m_s2`` (a parabola, sampled), flies
        ``vel_cmd`` for another ``latency_s`` (the next cycle's decision), then stops at ``accel_m_s2``; local
        NED [m]."""
        v0 = np.asarray(vel, dtype=np.float64)[: self.dim]
        v1 = np.asarray(vel_cmd, dtype=np.float64)[: self.dim]
        dv = v1 - v0
        dv_norm = float(np.sqrt(dv @ dv))
        p1 = pos[: self.dim] + v0 * self.latency_s
        t = np.linspace(0.0, dv_norm / self.accel_m_s2, TRANSITION_SAMPLES)[:, None]
        acc = dv * (self.accel_m_s2 / dv_norm) if dv_norm > _EPS else np.zeros_like(dv)
        change = p1 + v0 * t + 0.5 * acc * t * t
        p3 = change[-1] + v1 * self.latency_s
        speed1 = float(np.sqrt(v1 @ v1))
        p4 = p3 + v1 * (speed1 / (2.0 * self.accel_m_s2))
        path = np.vstack([pos[None, : self.dim], change, p3[None], p4[None]])
        return polyline_distance_m(path, points[:, : self.dim])

    def breaches(self, pos: FloatArray, vel: FloatArray | None, vel_cmd: FloatArray, points: FloatArray) -> bool:
        """Following the command ``vel_cmd`` from the reported velocity ``vel`` (local NED), with nothing newer
        arriving, could take the vehicle closer than ``clearance_m`` to a point (or closer than it is now, when
        already inside)."""
        if vel is None or not self.enabled or points.shape[0] == 0:
            return False
        radius = self._radius_m(pos[: self.dim], points[:, : self.dim])
        return self.transition_m(pos, vel, vel_cmd, points) < radius


def polyline_distance_m(vertices: FloatArray, points: FloatArray) -> float:
    """The smallest distance from the polyline through ``vertices`` (K, dim) to ``points`` (N, dim) [m]."""
    a = vertices[:-1, None, :]  # (K-1, 1, dim)
    ab = (vertices[1:] - vertices[:-1])[:, None, :]
    ap = points[None, :, :] - a  # (K-1, N, dim)
    ab2 = np.einsum("kij,kij->ki", ab, ab)
    t = np.clip(np.einsum("knj,kij->kn", ap, ab) / np.maximum(ab2, _EPS), 0.0, 1.0)
    d = ap - t[:, :, None] * ab
    return float(np.sqrt(np.min(np.einsum("knj,knj->kn", d, d))))
