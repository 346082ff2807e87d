"""The pose plausibility gate alone (pure: explicit times and positions)."""

from __future__ import annotations

import math

from apf_companion.perception import PoseGate, PoseLimits, Verdict


def stream(gate: PoseGate, t0_ms: int, pos: tuple[float, float, float], n: int, dt_ms: int = 50) -> list[Verdict]:
    """``n`` poses of a vehicle at rest at ``pos``, stamped and received every ``dt_ms``."""
    return [gate.check(t0_ms + k * dt_ms, pos, (t0_ms + k * dt_ms) / 1000.0) for k in range(n)]


def test_motion_within_the_limits_is_accepted_and_beyond_them_rejected() -> None:
    gate = PoseGate(PoseLimits(max_speed_m_s=10.0, max_accel_m_s2=5.0, noise_m=0.1))
    assert gate.check(0, (0.0, 0.0, -5.0), 0.0) is Verdict.ACCEPT
    x = 0.0
    for k in range(1, 41):  # accelerate at 4 m/s^2 for 2 s (within 5 m/s^2)
        t = k * 0.05
        x = 0.5 * 4.0 * t * t
        assert gate.check(k * 50, (x, 0.0, -5.0), t) is Verdict.ACCEPT
    assert gate.check(2050, (x + 2.0, 0.0, -5.0), 2.05) is Verdict.JUMP  # 40 m/s for one sample
    assert gate.check(2050, (math.nan, 0.0, -5.0), 2.05) is Verdict.NON_FINITE
    assert gate.check(2050, (1e30, 0.0, -5.0), 2.05) is Verdict.OUT_OF_BOUNDS
    assert gate.check(2000, (x, 0.0, -5.0), 2.05) is Verdict.STALE
    assert gate.check(11_000, (x, 0.0, -5.0), 2.1) is Verdict.TIME_JUMP  # 9 s ahead, 50 ms later


def test_a_sustained_new_position_re_anchors_but_an_interleaved_spoof_never_does() -> None:
    gate = PoseGate(PoseLimits(reset_samples=5))
    assert stream(gate, 0, (0.0, 0.0, -5.0), 10) == [Verdict.ACCEPT] * 10
    # A spoofer 50 m away, interleaved with the genuine stream: rejected for ever.
    for k in range(40):
        t_ms = 500 + 50 * k
        assert gate.check(t_ms, (50.0, 0.0, -5.0), t_ms / 1000.0) is Verdict.JUMP
        assert gate.check(t_ms + 25, (0.0, 0.0, -5.0), (t_ms + 25) / 1000.0) is Verdict.ACCEPT
    # An EKF reset: from now on every pose is 20 m east.
    verdicts = stream(gate, 3000, (0.0, 20.0, -5.0), 6)
    assert verdicts == [Verdict.JUMP] * 4 + [Verdict.RESET, Verdict.ACCEPT]


def test_a_reboot_needs_boot_evidence() -> None:
    gate = PoseGate(PoseLimits(reset_samples=100))
    stream(gate, 60_000, (0.0, 0.0, -5.0), 5)
    assert gate.check(100, (0.0, 0.0, -5.0), 60.3) is Verdict.TIME_JUMP
    gate.note_reboot()
    assert gate.check(150, (0.0, 0.0, -5.0), 60.35) is Verdict.RESET
    assert gate.check(200, (0.0, 0.0, -5.0), 60.4) is Verdict.ACCEPT
    gate.note_reboot()  # evidence that the stream then contradicts lapses
    assert gate.check(250, (0.0, 0.0, -5.0), 60.45) is Verdict.ACCEPT
    assert gate.check(10, (0.0, 0.0, -5.0), 60.5) is Verdict.STALE


def test_an_announced_estimator_reset_re_anchors_at_once() -> None:
    gate = PoseGate(PoseLimits(reset_samples=10))
    gate.note_reset_counter(4)
    stream(gate, 0, (0.0, 0.0, -5.0), 5)
    gate.note_reset_counter(4)  # unchanged: no evidence
    assert gate.check(250, (0.0, 20.0, -5.0), 0.25) is Verdict.JUMP
    gate.note_reset_counter(5)  # ODOMETRY.reset_counter moved: the next jump is the reset
    assert gate.check(300, (0.0, 20.0, -5.0), 0.3) is Verdict.RESET
    assert gate.check(350, (0.0, 20.0, -5.0), 0.35) is Verdict.ACCEPT
    assert gate.check(400, (0.0, 60.0, -5.0), 0.4) is Verdict.JUMP  # the evidence was used up


def test_reset_evidence_lapses_after_reset_samples_poses() -> None:
    gate = PoseGate(PoseLimits(reset_samples=3))
    gate.note_reset_counter(0)
    stream(gate, 0, (0.0, 0.0, -5.0), 2)
    gate.note_reset_counter(1)
    stream(gate, 100, (0.0, 0.0, -5.0), 3)  # a reset too small to see: the window closes
    assert gate.check(250, (0.0, 20.0, -5.0), 0.25) is Verdict.JUMP


def test_a_forged_anchor_is_unconfirmed_and_junk_between_genuine_poses_does_not_keep_it() -> None:
    """Found by the fuzz: after a forged reset (ODOMETRY reset counter) one spoofed pose anchors; hostile junk poses
    (1 km jumps, random points) arrive twice as often as the genuine ones. The genuine stream still re-anchors after
    ``reset_samples`` poses (its own candidate track), and that anchor is confirmed at once."""
    gate = PoseGate(PoseLimits(reset_samples=5))
    assert stream(gate, 0, (0.0, 0.0, -5.0), 10) == [Verdict.ACCEPT] * 10
    assert gate.confirmed
    gate.note_reset_counter(1)
    gate.note_reset_counter(2)  # a change: the next jump is taken as the estimator reset
    assert gate.check(500, (1000.0, 0.0, -5.0), 0.5) is Verdict.RESET
    assert not gate.confirmed  # one pose on evidence alone
    verdicts = []
    for k in range(5):
        t_ms = 525 + 50 * k
        gate.check(t_ms, (-700.0 + 300.0 * k, 40.0 * k, -5.0), t_ms / 1000.0)  # junk, never consistent
        gate.check(t_ms + 10, (3.0 * k, -900.0, -5.0), (t_ms + 10) / 1000.0)
        verdicts.append(gate.check(t_ms + 20, (0.0, 0.0, -5.0), (t_ms + 20) / 1000.0))  # genuine
    assert verdicts[-1] is Verdict.RESET and gate.confirmed
    assert gate.last is not None and gate.last.pos.tolist() == [0.0, 0.0, -5.0]


def test_two_consistent_streams_after_a_forged_anchor_re_anchor_neither() -> None:
    """A spoofed stationary point streamed beside the genuine one after a forged anchor: conflicting evidence, so
    neither re-anchors (the service brakes / holds instead of choosing)."""
    gate = PoseGate(PoseLimits(reset_samples=5))
    stream(gate, 0, (0.0, 0.0, -5.0), 10)
    gate.note_reset_counter(1)
    gate.note_reset_counter(2)
    assert gate.check(500, (1000.0, 0.0, -5.0), 0.5) is Verdict.RESET
    for k in range(20):
        t_ms = 525 + 50 * k
        assert gate.check(t_ms, (30.0, 0.0, -5.0), t_ms / 1000.0) is not Verdict.RESET  # the spoof
        assert gate.check(t_ms + 20, (0.0, 0.0, -5.0), (t_ms + 20) / 1000.0) is not Verdict.RESET  # genuine
    assert gate.last is not None and gate.last.pos[0] == 1000.0 and not gate.confirmed
