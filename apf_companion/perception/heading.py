"""The vehicle's heading at a position report's own time, from ATTITUDE samples on the autopilot's clock.

A pose pairs LOCAL_POSITION_NED with a yaw. The two messages are separate streams: taking the latest ATTITUDE
at the moment a position arrives gives a yaw up to one ATTITUDE period old (100 ms at the usual 10 Hz). In a
30 deg/s turn that is 3 degrees, 0.5 m sideways at 10 m range, and range returns placed with that pose land in
front of the surfaces they saw. So each ATTITUDE is kept with its ``time_boot_ms`` (the same clock as
LOCAL_POSITION_NED's), and the yaw at the position's time is interpolated between the two latest samples, or
carried forward by the yaw rate when the position is newer than both.

ATTITUDE's rates are body rates (ArduPilot ``GCS_Common.cpp`` ``send_attitude`` sends ``ahrs.get_gyro()``;
PX4's ATTITUDE stream sends ``vehicle_angular_velocity``), so the yaw (heading) rate is the Euler kinematics
``psi_dot = (q sin(phi) + r cos(phi)) / cos(theta)``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

__all__ = ["CLOCK_RESTART_S", "MAX_EXTRAPOLATION_S", "MAX_RATE_RAD_S", "HeadingTrack", "euler_yaw_rate_rad_s"]

MAX_EXTRAPOLATION_S = 0.25
"""Longest time [s] a yaw is carried by its rate. A position further from the nearest ATTITUDE (the stream
stalled) gets the yaw carried this far and no further: the rate is no longer evidence of the heading."""

MAX_RATE_RAD_S = 2.0 * math.tau
"""A heading rate beyond this (720 deg/s, past any multicopter's yaw) is a corrupt field: it is taken as 0."""

CLOCK_RESTART_S = 1.0
"""An ATTITUDE this much older than the newest is from a restarted clock (a reboot, or time_boot_ms wrapping
after 49.7 days): the track starts over from it. Less is a reordered datagram, ignored."""

_MIN_COS_PITCH = 0.1  # |pitch| > 84 deg: the Euler rate is ill-defined; the body yaw rate is used instead


def euler_yaw_rate_rad_s(roll_rad: float, pitch_rad: float, q_rad_s: float, r_rad_s: float) -> float:
    """The heading rate [rad/s] from body rates ``q`` (pitch axis) and ``r`` (yaw axis), FRD, ZYX Euler angles;
    NaN when an input is not finite (a corrupt ATTITUDE: ``HeadingTrack`` takes that as no rate)."""
    if not all(map(math.isfinite, (roll_rad, pitch_rad, q_rad_s, r_rad_s))):
        return math.nan
    c = math.cos(pitch_rad)
    rate = q_rad_s * math.sin(roll_rad) + r_rad_s * math.cos(roll_rad)
    return rate / c if abs(c) >= _MIN_COS_PITCH else r_rad_s


@dataclass(frozen=True, slots=True)
class _Sample:
    t_s: float  # autopilot time since boot [s]
    yaw_rad: float
    rate_rad_s: float  # heading rate [rad/s], 0 when not finite


class HeadingTrack:
    """The two latest ATTITUDE samples; ``at`` answers the yaw at a time on the autopilot's boot clock.

    Counted: ``stale`` (a reordered or duplicate ATTITUDE, ignored), ``bad_rates`` (a rate not finite or beyond
    ``MAX_RATE_RAD_S``, taken as 0)."""

    __slots__ = ("_last", "_prev", "_untimed", "bad_rates", "stale")

    def __init__(self) -> None:
        self._prev: _Sample | None = None
        self._last: _Sample | None = None
        self._untimed = False  # the latest yaw came without a time: it is used as is
        self.stale = 0
        self.bad_rates = 0

    @property
    def latest_rad(self) -> float | None:
        """The newest yaw received [rad], None before the first."""
        return None if self._last is None else self._last.yaw_rad

    def update(self, yaw_rad: float, time_boot_ms: int | None = None, rate_rad_s: float = 0.0) -> None:
        """An ATTITUDE yaw [rad] at ``time_boot_ms`` (None: unknown time, taken as current). A non-finite yaw is
        ignored (the caller counts it); a non-finite or implausible rate counts as no rate."""
        if not math.isfinite(yaw_rad):
            return
        yaw_rad = math.remainder(yaw_rad, math.tau)
        rate = rate_rad_s
        if not (math.isfinite(rate) and abs(rate) <= MAX_RATE_RAD_S):
            self.bad_rates += 1
            rate = 0.0
        if time_boot_ms is None:
            self._prev, self._last, self._untimed = None, _Sample(0.0, yaw_rad, 0.0), True
            return
        sample = _Sample(time_boot_ms / 1000.0, yaw_rad, rate)
        last = self._last
        if last is not None and not self._untimed and sample.t_s <= last.t_s:
            if sample.t_s < last.t_s - CLOCK_RESTART_S:
                self._prev, self._last = None, sample
            else:
                self.stale += 1  # the newer sample stays
            return
        self._prev = None if self._untimed else last
        self._last, self._untimed = sample, False

    def age_s(self, time_boot_ms: int) -> float:
        """How far [s] ``time_boot_ms`` lies outside the samples' span (0 within it, or for a yaw without a time;
        inf before the first ATTITUDE)."""
        last, prev = self._last, self._prev
        if last is None:
            return math.inf
        if self._untimed:
            return 0.0
        t = time_boot_ms / 1000.0
        first = last.t_s if prev is None else prev.t_s
        return max(t - last.t_s, first - t, 0.0)

    def at(self, time_boot_ms: int) -> float | None:
        """The yaw [rad] at ``time_boot_ms`` (autopilot boot clock), None before the first ATTITUDE."""
        last, prev = self._last, self._prev
        if last is None:
            return None
        if self._untimed:
            return last.yaw_rad
        t = time_boot_ms / 1000.0
        if prev is not None and prev.t_s <= t <= last.t_s:
            w = (t - prev.t_s) / (last.t_s - prev.t_s)
            return math.remainder(prev.yaw_rad + w * math.remainder(last.yaw_rad - prev.yaw_rad, math.tau), math.tau)
        near = prev if prev is not None and t < prev.t_s else last
        dt = min(max(t - near.t_s, -MAX_EXTRAPOLATION_S), MAX_EXTRAPOLATION_S)
        return math.remainder(near.yaw_rad + near.rate_rad_s * dt, math.tau)
