"""The pose plausibility gate: a LOCAL_POSITION_NED becomes a pose only if the vehicle could be there.

A pose is rejected (and counted by the front end) when

- a coordinate is non-finite or beyond ``max_abs_position_m`` of the EKF origin (``NON_FINITE``,
  ``OUT_OF_BOUNDS``);
- its ``time_boot_ms`` is not newer than the last accepted one (``STALE``: frozen or reordered datagrams), or goes
  further forward than the receive clock allows (``TIME_JUMP``: more than ``time_jump_s`` beyond the receive-time
  gap), or far back (``TIME_JUMP``: an autopilot reboot is accepted at once only with reboot evidence, see
  ``note_reboot``);
- it lies further from the last accepted pose than the vehicle can move in the time between them: the smaller of
  ``max_speed_m_s * dt`` and ``|v| dt + a_max dt^2 / 2`` (v estimated from the last two accepted poses), plus
  ``noise_m`` (``JUMP``).

A rejected pose that is finite and in bounds is a candidate for a real EKF reset or an unannounced reboot: after
``reset_samples`` candidates that continue each other (each a plausible move in plausible time from the previous
one in its track; up to ``MAX_TRACKS`` tracks are kept, so junk in between does not break one) and with no accepted
pose in between, the gate re-anchors on them (``RESET``): the caller
must hold and announce it before motion resumes. Interleaved genuine poses restart the count, so a spoofed stream
beside the real one never takes over. Where the autopilot streams ODOMETRY, a change of its ``reset_counter`` is
direct evidence: a jump within the next ``reset_samples`` poses re-anchors at once (``note_reset_counter``).

An anchor taken on evidence alone (the first pose, a reboot, an announced reset: one pose) is not ``confirmed``
until ``reset_samples`` poses in all, each a plausible successor of the last, agree with it: a single spoofed pose
that rides on forged evidence (a HEARTBEAT in MAV_STATE_BOOT, an ODOMETRY reset counter change) must not become a
hold point or a planning origin. A re-anchor on a consistent candidate track is confirmed at once.
"""

from __future__ import annotations

import enum
from dataclasses import dataclass

import numpy as np
import numpy.typing as npt

__all__ = ["PoseGate", "PoseLimits", "Verdict"]

FloatArray = npt.NDArray[np.float64]
MAX_TRACKS = 4  # candidate tracks kept at once (see ``PoseGate._candidate``)
REBOOT_JUMP_MS = 10_000  # time_boot_ms this far back is not a reordered datagram: a reboot (with evidence)


class Verdict(enum.Enum):
    ACCEPT = "accept"
    RESET = "reset"  # re-anchored: a sustained new position / time base (EKF reset, reboot)
    NON_FINITE = "non_finite"
    OUT_OF_BOUNDS = "out_of_bounds"
    STALE = "stale"
    TIME_JUMP = "time_jump"
    JUMP = "jump"


@dataclass(frozen=True, slots=True, kw_only=True)
class PoseLimits:
    """What the vehicle can do (``[safety]``; docs/hardening.md)."""

    max_speed_m_s: float = 15.0
    max_accel_m_s2: float = 10.0
    noise_m: float = 0.3
    max_abs_position_m: float = 10_000.0
    time_jump_s: float = 1.0
    reset_samples: int = 10


@dataclass(slots=True)
class _Fix:
    boot_ms: int
    pos: FloatArray
    rx_s: float


class PoseGate:
    """Decides on each LOCAL_POSITION_NED (see the module docstring). Owns the last accepted fix."""

    def __init__(self, limits: PoseLimits) -> None:
        self.limits = limits
        self.last: _Fix | None = None
        self.vel_m_s = np.zeros(3)
        self._tracks: list[list[_Fix]] = []  # candidate tracks: rejected fixes that agree with each other
        self._reboot_evidence = False
        self._reset_counter: int | None = None
        self._reset_window = 0  # poses left in which a jump is the announced estimator reset
        self._agreeing = 0  # poses that agree with the current anchor (the anchor included)

    @property
    def confirmed(self) -> bool:
        """The current anchor is backed by ``reset_samples`` consistent poses (see the module docstring)."""
        return self._agreeing >= self.limits.reset_samples

    def note_reset_counter(self, counter: int) -> None:
        """The estimator's reset counter (ODOMETRY.reset_counter): a change is reset evidence, and the next
        ``reset_samples`` poses may re-anchor at once (a jump then is the reset, not a spoof)."""
        if self._reset_counter is not None and counter != self._reset_counter:
            self._reset_window = self.limits.reset_samples
        self._reset_counter = counter

    def note_reboot(self) -> None:
        """The autopilot rebooted (HEARTBEAT after a silence longer than the link timeout, or MAV_STATE_BOOT):
        the next pose may start a new time base."""
        self._reboot_evidence = True

    def check(self, boot_ms: int, pos: tuple[float, float, float], now_s: float) -> Verdict:
        lim = self.limits
        p = np.asarray(pos, dtype=np.float64)
        if not np.all(np.isfinite(p)):
            return Verdict.NON_FINITE
        if float(np.max(np.abs(p))) > lim.max_abs_position_m:
            return Verdict.OUT_OF_BOUNDS
        fix = _Fix(boot_ms, p, now_s)
        last = self.last
        if last is None or (self._reboot_evidence and boot_ms < last.boot_ms):
            return self._anchor(fix, Verdict.ACCEPT if last is None else Verdict.RESET)
        verdict = self._versus(last, fix, self.vel_m_s)
        self._reset_window = max(0, self._reset_window - 1)
        if verdict is Verdict.JUMP and self._reset_window > 0:
            return self._anchor(fix, Verdict.RESET)
        if verdict is Verdict.ACCEPT:
            dt = (boot_ms - last.boot_ms) / 1000.0
            self.vel_m_s = (p - last.pos) / dt
            self.last = fix
            self._tracks.clear()
            self._reboot_evidence = False  # the stream went on: no reboot after all
            self._agreeing += 1
            return verdict
        if verdict is Verdict.STALE:
            if last.boot_ms - boot_ms < REBOOT_JUMP_MS:
                return verdict  # reordered or frozen: normal on a lossy link, never a reset candidate
            verdict = Verdict.TIME_JUMP  # far back without boot evidence
        return self._candidate(fix, verdict)

    def _versus(self, ref: _Fix, fix: _Fix, vel_m_s: FloatArray) -> Verdict:
        """Is ``fix`` a plausible successor of ``ref``?"""
        lim = self.limits
        dt = (fix.boot_ms - ref.boot_ms) / 1000.0
        if dt <= 0.0:
            return Verdict.STALE
        if dt > (fix.rx_s - ref.rx_s) + lim.time_jump_s:
            return Verdict.TIME_JUMP
        speed = float(np.linalg.norm(vel_m_s))
        reach = min(lim.max_speed_m_s * dt, speed * dt + 0.5 * lim.max_accel_m_s2 * dt * dt) + lim.noise_m
        if float(np.linalg.norm(fix.pos - ref.pos)) > reach:
            return Verdict.JUMP
        return Verdict.ACCEPT

    def _candidate(self, fix: _Fix, verdict: Verdict) -> Verdict:
        """Add a rejected fix to the first candidate track it plausibly continues, else start a track (beyond
        ``MAX_TRACKS`` the shortest older one goes): junk interleaved with a genuine stream that the anchor rejects
        (a forged anchor) does not keep the genuine stream from re-anchoring, while a second consistent stream
        (a track of two or more fixes) blocks every re-anchor."""
        # A track whose last fix is older than the time-jump tolerance is no stream any more (its reach would grow
        # with the gap): dropped.
        self._tracks = [t for t in self._tracks if fix.rx_s - t[-1].rx_s <= self.limits.time_jump_s]
        track = next((t for t in self._tracks if self._versus(t[-1], fix, _track_vel(t)) is Verdict.ACCEPT), None)
        if track is None:
            if len(self._tracks) >= MAX_TRACKS:
                del self._tracks[min(range(len(self._tracks)), key=lambda i: len(self._tracks[i]))]
            track = []
            self._tracks.append(track)
        track.append(fix)
        rivals = [t for t in self._tracks if t is not track and len(t) >= 2]
        if len(track) >= self.limits.reset_samples and not rivals:
            # Two consistent streams (a spoof beside the real one) are conflicting evidence: neither re-anchors.
            return self._anchor(fix, Verdict.RESET, agreeing=len(track))
        return verdict

    def _anchor(self, fix: _Fix, verdict: Verdict, *, agreeing: int = 1) -> Verdict:
        self.last = fix
        self._agreeing = agreeing
        self.vel_m_s = np.zeros(3)
        self._tracks.clear()
        self._reboot_evidence = False
        self._reset_window = 0
        return verdict


def _track_vel(track: list[_Fix]) -> FloatArray:
    """The velocity between a track's last two fixes (zero with fewer)."""
    if len(track) < 2:
        return np.zeros(3)
    a, b = track[-2], track[-1]
    dt = (b.boot_ms - a.boot_ms) / 1000.0
    return (b.pos - a.pos) / dt if dt > 0 else np.zeros(3)
