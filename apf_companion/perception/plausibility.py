"""The pose plausibility gate: a LOCAL_POSITION_NED becomes a pose only if the vehicle could be there.

A pose is rejected (and counted by the front end) when

- a coordinate is non-finite or beyond ``max_abs_position_m`` of the EKF origin (``NON_FINITE``,
  ``OUT_OF_BOUNDS``);
- its ``time_boot_ms`` is more than ``time_jump_s`` ahead of what the receive clock allows (``TIME_LEAD``: see
  "Time" below);
- its ``time_boot_ms`` is not newer than the last accepted one (``STALE``: frozen or reordered datagrams), or far
  back (``TIME_JUMP``: an autopilot reboot is accepted at once only with reboot evidence, see ``note_reboot``);
- it is not newer and contradicts the accepted poses around its time (``CONFLICT``: see "Two streams" below);
- it lies further from the last accepted pose than the vehicle can move in the time between them: the smaller of
  ``max_speed_m_s * dt`` and ``|v| dt + a_max dt^2 / 2`` (v estimated from the last two accepted poses), plus
  ``noise_m`` (``JUMP``).

Time. The stamp is the autopilot's word, the receive clock ours. Their relation (perception/clocksync.py: the
offset of the least-delayed poses, robust to forged ones, rising by at most ``time_jump_s`` in all plus a drift)
says how late a pose may be stamped: never later than its receipt. Each pose's *effective* time is its stamp, but
no later than the relation allows at its receipt; ``dt`` above is the difference of effective times, and a pose is
stale when its stamp is not newer than the last accepted pose's effective time. So a pose stamped ahead gains no
reach and does not make the genuine poses after it look stale, and the tolerance is spent once against the
relation, not again from every accepted pose (where it added up: ten poses each stamped 0.95 s after the last
walked the pose 50 m in 0.5 s). Late poses (a burst after a silent link) keep their stamps.

Two streams. A stream forged with newer stamps than the genuine one (sent faster, or stamped a little ahead) makes
the genuine poses stale, and could then walk the pose at the vehicle's limits. A stale pose is therefore checked
against the accepted poses with the nearest stamps (kept for ``HISTORY_S``): if it lies further from either than the
vehicle can move in the time between their stamps, two streams claim different positions for the same time, and
the anchor loses its confirmation (``CONFLICT``): the service brakes until ``reset_samples`` poses agree in a row.
Not checked: a pose older than every kept one (from before a reset, delivered late), and one with the last accepted
stamp again (a frozen stream: its pose ages and the navigator holds).

A rejected pose that is finite and in bounds is a candidate for a real EKF reset or an unannounced reboot: after
``reset_samples`` candidates that continue each other (each a plausible move in plausible time from the previous
one in its track; up to ``MAX_TRACKS`` tracks are kept, so junk in between does not break one) and with no accepted
pose in between, the gate re-anchors on them (``RESET``): the caller
must hold and announce it before motion resumes. Interleaved genuine poses restart the count, so a spoofed stream
beside the real one never takes over. Where the autopilot streams ODOMETRY, a change of its ``reset_counter`` is
direct evidence: a jump within the next ``reset_samples`` poses re-anchors at once (``note_reset_counter``). A reset
smaller than the gate's reach is accepted as a move, but the remembered points are then in the old frame: the first
pose accepted after the counter changed reports ``RESET`` too (the stream goes on; the caller forgets the old frame).
PX4 publishes the counter and the position of one estimator update together (EKF2.cpp ``PublishLocalPosition`` /
``PublishOdometry``), so that pose is in the new frame; a jump that arrives later in the window still re-anchors.

While the rejected poses form a track of half ``reset_samples`` (at least two) that the anchor rejects (a reset's
new frame before it re-anchors, or a second stream), the anchor is not ``confirmed`` either: the old frame's hold
point and steps are not sent into the new one (the caller brakes, frame-free).

An anchor taken on evidence alone (the first pose, a reboot, an announced reset: one pose) is not ``confirmed``
until ``reset_samples`` poses in all, each a plausible successor of the last, agree with it: a single spoofed pose
that rides on forged evidence (a HEARTBEAT in MAV_STATE_BOOT, an ODOMETRY reset counter change) must not become a
hold point or a planning origin. A re-anchor on a consistent candidate track is confirmed at once.
"""

from __future__ import annotations

import bisect
import enum
from dataclasses import dataclass

import numpy as np
import numpy.typing as npt

from apf_companion.perception.clocksync import ClockRelation

__all__ = ["PoseGate", "PoseLimits", "Verdict"]

FloatArray = npt.NDArray[np.float64]
MAX_TRACKS = 4  # candidate tracks kept at once (see ``PoseGate._candidate``)
REBOOT_JUMP_S = 10.0  # time_boot_ms this far back is not a reordered datagram: a reboot (with evidence)
HISTORY_S = REBOOT_JUMP_S  # accepted poses kept for the stale-pose check, by stamp [s]
HISTORY_MAX = 4096  # ... and at most this many
MIN_VEL_DT_S = 0.01  # below this effective time between two poses no velocity is estimated from them [s]


class Verdict(enum.Enum):
    ACCEPT = "accept"
    RESET = "reset"  # re-anchored: a sustained new position / time base (EKF reset, reboot)
    NON_FINITE = "non_finite"
    OUT_OF_BOUNDS = "out_of_bounds"
    STALE = "stale"
    CONFLICT = "conflict"  # stale, and contradicts the accepted poses of its time: a second stream
    TIME_LEAD = "time_lead"  # stamped more than time_jump_s ahead of what the receive clock allows
    TIME_JUMP = "time_jump"  # far back without reboot evidence
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

    def reach_m(self, dt_s: float, speed_m_s: float) -> float:
        """How far the vehicle can get in ``dt_s`` from moving at ``speed_m_s`` (noise included) [m]."""
        a = self.max_accel_m_s2
        return min(self.max_speed_m_s * dt_s, speed_m_s * dt_s + 0.5 * a * dt_s * dt_s) + self.noise_m


@dataclass(slots=True)
class _Fix:
    boot_ms: int
    pos: FloatArray
    rx_s: float  # receive time, service clock [s]
    eff_s: float  # effective time: the stamp, no later than the clock relation allows at receipt [s, autopilot]
    speed_m_s: float = 0.0  # the speed estimate once accepted [m/s]

    @property
    def boot_s(self) -> float:
        return self.boot_ms / 1000.0

    @property
    def offset_s(self) -> float:
        """Clock offset: stamp minus receive time [s]."""
        return self.boot_ms / 1000.0 - self.rx_s


class PoseGate:
    """Decides on each LOCAL_POSITION_NED (see the module docstring). Owns the last accepted fix."""

    def __init__(self, limits: PoseLimits) -> None:
        self.limits = limits
        self.last: _Fix | None = None
        self.vel_m_s = np.zeros(3)
        self.clock = ClockRelation(limits.time_jump_s)
        self._history: list[_Fix] = []  # accepted since the anchor, by stamp
        self._tracks: list[list[_Fix]] = []  # candidate tracks: rejected fixes that agree with each other
        self._reboot_evidence = False
        self._reset_counter: int | None = None
        self._reset_window = 0  # poses left in which a jump is the announced estimator reset
        self._reset_unseen = False  # the counter changed and no pose has re-anchored or reported RESET since
        self._agreeing = 0  # poses that agree with the current anchor (the anchor included)

    @property
    def confirmed(self) -> bool:
        """The current anchor is backed by ``reset_samples`` consistent poses (see the module docstring)."""
        # A consistent stream the anchor rejects, half-way to re-anchoring: shorter tracks are a vehicle that moved
        # a little beyond the reach for a sample or two (the tests' scripted autopilot jumps to each setpoint).
        rival = any(len(t) >= max(2, self.limits.reset_samples // 2) for t in self._tracks)
        return self._agreeing >= self.limits.reset_samples and not rival

    def note_reset_counter(self, counter: int) -> bool:
        """The estimator's reset counter (ODOMETRY.reset_counter): a change is reset evidence, and the next
        ``reset_samples`` poses may re-anchor at once (a jump then is the reset, not a spoof); the first pose
        accepted after it reports ``RESET`` (a reset within reach). True when it changed."""
        changed = self._reset_counter is not None and counter != self._reset_counter
        if changed:
            self._reset_window = self.limits.reset_samples
            self._reset_unseen = True
        self._reset_counter = counter
        return changed

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
        boot_s = boot_ms / 1000.0
        last = self.last
        if last is None or (self._reboot_evidence and boot_s < last.eff_s):
            fix = _Fix(boot_ms, p, now_s, boot_s)
            self.clock.restart([(now_s, fix.offset_s)])  # a new time base: a new relation
            return self._anchor(fix, Verdict.ACCEPT if last is None else Verdict.RESET)
        fix = _Fix(boot_ms, p, now_s, min(boot_s, self.clock.latest_stamp_s(now_s)))
        if fix.offset_s > self.clock.base_s + lim.time_jump_s:
            return self._candidate(fix, Verdict.TIME_LEAD)
        verdict = self._versus(last, fix, float(np.linalg.norm(self.vel_m_s)))
        self._reset_window = max(0, self._reset_window - 1)
        if verdict is Verdict.JUMP and self._reset_window > 0:
            self.clock.add(now_s, fix.offset_s)  # an estimator reset: the clocks are the same
            return self._anchor(fix, Verdict.RESET)
        if verdict is Verdict.ACCEPT:
            self._accept(last, fix)
            if self._reset_unseen:  # an announced reset within reach: the same stream, in the new frame
                self._reset_unseen = False
                return Verdict.RESET
            return verdict
        if verdict is Verdict.STALE:
            if last.eff_s - boot_s >= REBOOT_JUMP_S:
                return self._candidate(fix, Verdict.TIME_JUMP)  # far back without boot evidence
            if boot_ms != last.boot_ms and self._contradicts(fix):
                self._agreeing = 0  # two streams claim different positions for one time: neither is trusted
                return Verdict.CONFLICT
            # Reordered, or frozen (the last stamp again: a stream whose clock stopped, which the navigator's pose
            # age holds for): normal on a lossy link, never a reset candidate.
            return verdict
        return self._candidate(fix, verdict)

    def _accept(self, last: _Fix, fix: _Fix) -> None:
        fix.eff_s = max(fix.eff_s, last.eff_s)
        dt = fix.eff_s - last.eff_s
        if dt >= MIN_VEL_DT_S:
            self.vel_m_s = (fix.pos - last.pos) / dt
        fix.speed_m_s = float(np.linalg.norm(self.vel_m_s))
        self.last = fix
        self._remember(fix)
        self.clock.add(fix.rx_s, fix.offset_s)
        self._tracks.clear()
        self._reboot_evidence = False  # the stream went on: no reboot after all
        self._agreeing += 1

    def _versus(self, ref: _Fix, fix: _Fix, speed_m_s: float) -> Verdict:
        """Is ``fix`` a plausible successor of ``ref``? Times are effective times (module docstring, "Time")."""
        if fix.boot_s <= ref.eff_s or fix.boot_ms == ref.boot_ms:
            return Verdict.STALE
        reach = self.limits.reach_m(max(0.0, fix.eff_s - ref.eff_s), speed_m_s)
        if float(np.linalg.norm(fix.pos - ref.pos)) > reach:
            return Verdict.JUMP
        return Verdict.ACCEPT

    def _contradicts(self, fix: _Fix) -> bool:
        """A stale ``fix`` lies further from an accepted pose with the nearest stamp, before or after it, than the
        vehicle can move between their stamps (module docstring, "Two streams")."""
        h = self._history
        if self.last is None or fix.boot_ms < h[0].boot_ms:
            return False  # older than the anchor: from before a reset or reboot, delivered late
        i = bisect.bisect_left(h, fix.boot_ms, key=lambda f: f.boot_ms)
        for near in (h[i - 1] if i > 0 else None, h[i] if i < len(h) else None):
            if near is None:
                continue
            dt = abs(fix.boot_s - near.boot_s)
            if float(np.linalg.norm(fix.pos - near.pos)) > self.limits.reach_m(dt, near.speed_m_s):
                return True
        return False

    def _remember(self, fix: _Fix) -> None:
        """Keep an accepted fix, by stamp (a fix stamped ahead and accepted with a clamped time can be followed by
        one stamped before it), for ``HISTORY_S`` of stamps and at most ``HISTORY_MAX`` fixes."""
        h = self._history
        bisect.insort(h, fix, key=lambda f: f.boot_ms)
        cut = bisect.bisect_left(h, h[-1].boot_ms - round(HISTORY_S * 1000.0), key=lambda f: f.boot_ms)
        del h[: max(cut, len(h) - HISTORY_MAX)]

    def _candidate(self, fix: _Fix, verdict: Verdict) -> Verdict:
        """Add a rejected fix to the first candidate track it plausibly continues, else start a track (beyond
        ``MAX_TRACKS`` the shortest older one goes): junk interleaved with a genuine stream that the anchor rejects
        (a forged anchor) does not keep the genuine stream from re-anchoring, while a second consistent stream
        (a track of two or more fixes) blocks every re-anchor."""
        # A track whose last fix is older than the time-jump tolerance is no stream any more (its reach would grow
        # with the gap): dropped.
        self._tracks = [t for t in self._tracks if fix.rx_s - t[-1].rx_s <= self.limits.time_jump_s]
        track = next((t for t in self._tracks if self._versus(t[-1], fix, _track_speed(t)) is Verdict.ACCEPT), None)
        if track is None:
            if len(self._tracks) >= MAX_TRACKS:
                del self._tracks[min(range(len(self._tracks)), key=lambda i: len(self._tracks[i]))]
            track = []
            self._tracks.append(track)
        track.append(fix)
        rivals = [t for t in self._tracks if t is not track and len(t) >= 2]
        if len(track) >= self.limits.reset_samples and not rivals:
            # Two consistent streams (a spoof beside the real one) are conflicting evidence: neither re-anchors.
            self.clock.restart([(f.rx_s, f.offset_s) for f in track])  # the track may be a new time base
            fix.eff_s = min(fix.boot_s, self.clock.latest_stamp_s(fix.rx_s))
            return self._anchor(fix, Verdict.RESET, agreeing=len(track))
        return verdict

    def _anchor(self, fix: _Fix, verdict: Verdict, *, agreeing: int = 1) -> Verdict:
        self.last = fix
        self._agreeing = agreeing
        self.vel_m_s = np.zeros(3)
        fix.speed_m_s = 0.0
        self._history.clear()
        self._remember(fix)
        self._tracks.clear()
        self._reboot_evidence = False
        self._reset_window = 0
        self._reset_unseen = False
        return verdict


def _track_speed(track: list[_Fix]) -> float:
    """The speed between a track's last two fixes (zero with fewer) [m/s]."""
    if len(track) < 2:
        return 0.0
    a, b = track[-2], track[-1]
    dt = b.eff_s - a.eff_s
    return float(np.linalg.norm(b.pos - a.pos)) / dt if dt >= MIN_VEL_DT_S else 0.0
