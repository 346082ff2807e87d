"""The pose plausibility gate alone (pure: explicit times and positions)."""

from __future__ import annotations

import math

import numpy as np

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
    assert gate.check(11_000, (x, 0.0, -5.0), 2.1) is Verdict.TIME_LEAD  # 9 s ahead, 50 ms later


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


def test_an_announced_reset_within_reach_reports_reset_on_the_first_pose_after_it() -> None:
    """PX4 EKF2 publishes the reset counter and the position of one update together (EKF2.cpp PublishOdometry /
    PublishLocalPosition): a reset of 0.2 m is within the gate's reach (accepted as a move), but the remembered
    points are 0.2 m off. The first pose after the counter changed reports RESET (the anchor stays confirmed: the
    stream went on); a jump later in the window still re-anchors."""
    gate = PoseGate(PoseLimits(reset_samples=4))
    gate.note_reset_counter(4)
    stream(gate, 0, (0.0, 0.0, -5.0), 5)
    assert gate.confirmed
    assert gate.note_reset_counter(5) and not gate.note_reset_counter(5)
    assert gate.check(250, (0.0, 0.2, -5.0), 0.25) is Verdict.RESET
    assert gate.confirmed
    assert gate.check(300, (0.0, 0.2, -5.0), 0.3) is Verdict.ACCEPT
    assert gate.check(350, (0.0, 20.0, -5.0), 0.35) is Verdict.RESET  # late in the window: still the reset
    assert gate.check(400, (0.0, 20.0, -5.0), 0.4) is Verdict.ACCEPT


def test_a_rejected_consistent_track_unconfirms_the_anchor_until_it_re_anchors() -> None:
    """An EKF reset seen only in LOCAL_POSITION_NED: from the second rejected pose of the new frame on, the old
    anchor is not confirmed (the service brakes instead of holding at an old-frame point) until the new frame
    re-anchors; a single junk pose does not unconfirm it. Half ``reset_samples`` (here 2 of 5) rejected in a row
    unconfirm it."""
    gate = PoseGate(PoseLimits(reset_samples=5))
    stream(gate, 0, (0.0, 0.0, -5.0), 10)
    assert gate.confirmed
    assert gate.check(500, (0.0, 300.0, -5.0), 0.5) is Verdict.JUMP  # one junk pose
    assert gate.confirmed
    assert gate.check(525, (0.0, 0.0, -5.0), 0.525) is Verdict.ACCEPT
    verdicts, confirmed = [], []
    for k in range(6):
        t_ms = 550 + 50 * k
        verdicts.append(gate.check(t_ms, (0.0, 5.0, -5.0), t_ms / 1000.0))
        confirmed.append(gate.confirmed)
    assert verdicts == [Verdict.JUMP] * 4 + [Verdict.RESET, Verdict.ACCEPT]
    assert confirmed == [True, False, False, False, True, True]


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


# ---- time: stamps against the receive clock (docs/hardening.md "Pose plausibility", "Time") ----------------------


def genuine(gate: PoseGate, t_s: float, pos: tuple[float, float, float], delay_s: float = 0.01) -> Verdict:
    """The autopilot's pose measured at ``t_s`` (its clock = the service clock), received ``delay_s`` later."""
    return gate.check(round(t_s * 1000.0), pos, t_s + delay_s)


def test_poses_each_stamped_just_within_the_tolerance_after_the_last_walk_nowhere() -> None:
    """Found by review (session 28): the tolerance was applied from every accepted pose, so it added up. Ten poses
    50 ms apart on the wire, each stamped 0.95 s after the previous and 5 m further east, walked the pose 50 m.
    Now a pose's time is held to the receive clock: the first gains no reach (a jump), the rest lead by more than
    the tolerance (counted), and the genuine stream between them is accepted throughout."""
    gate = PoseGate(PoseLimits())
    for k in range(40):
        assert genuine(gate, k * 0.05, (0.0, 0.0, -5.0)) is Verdict.ACCEPT
    verdicts = []
    for i in range(1, 11):
        t = 2.0 + 0.05 * i
        verdicts.append(gate.check(2000 + 950 * i, (0.0, 5.0 * i, -5.0), t))  # the forged pose
        assert genuine(gate, t, (0.0, 0.0, -5.0)) is Verdict.ACCEPT
    assert verdicts == [Verdict.JUMP] + [Verdict.TIME_LEAD] * 9
    assert gate.last is not None and gate.last.pos.tolist() == [0.0, 0.0, -5.0] and gate.confirmed


def test_one_pose_stamped_ahead_beside_the_vehicle_does_not_make_the_genuine_stream_stale() -> None:
    """A forged pose 0.1 m aside stamped 0.95 s ahead is a plausible position; it is accepted with its time held
    to its receipt, so the genuine poses after it are newer, not stale (they were, for 0.95 s, and then jumped)."""
    gate = PoseGate(PoseLimits())
    for k in range(40):
        genuine(gate, k * 0.05, (0.0, 0.0, -5.0))
    assert gate.check(2950, (0.0, 0.1, -5.0), 2.0) is Verdict.ACCEPT
    for k in range(1, 30):
        assert genuine(gate, 2.0 + 0.05 * k, (0.0, 0.0, -5.0)) is Verdict.ACCEPT
    assert gate.confirmed


def test_poses_stamped_ahead_gain_at_most_the_tolerance_in_all() -> None:
    """The relation rises with the third-highest offset, and at most ``time_jump_s`` above a floor that follows at
    1 ms/s: forged poses beside the vehicle, three at a time, each stamped 0.9 s beyond the relation, cannot
    ratchet it. The effective time of the last accepted pose stays within the tolerance of the receive clock."""
    gate = PoseGate(PoseLimits())
    t = 0.0
    for _ in range(40):
        genuine(gate, t, (0.0, 0.0, -5.0), delay_s=0.0)
        t += 0.05
    for _ in range(60):
        for _ in range(3):
            t += 0.001
            gate.check(round((t + gate.clock.base_s + 0.9) * 1000.0), (0.0, 0.0, -5.0), t)
        t += 0.05
        genuine(gate, t, (0.0, 0.0, -5.0), delay_s=0.0)
    assert gate.clock.base_s <= 1.0 + 1e-3 * t + 1e-9
    assert gate.last is not None and gate.last.eff_s <= t + 1.0 + 1e-3 * t + 1e-9


def test_a_late_burst_after_a_silent_link_is_accepted() -> None:
    """The link holds everything for 2 s, then delivers it within 20 ms: every pose is stamped before its receipt
    (late, not early) and the vehicle, flying at 5 m/s, moved as the stamps say."""
    gate = PoseGate(PoseLimits())
    for k in range(40):
        assert genuine(gate, k * 0.05, (0.25 * k, 0.0, -5.0)) is Verdict.ACCEPT
    burst = [gate.check(2000 + 50 * k, (10.0 + 0.25 * k, 0.0, -5.0), 4.0 + 0.0005 * k) for k in range(40)]
    assert burst == [Verdict.ACCEPT] * 40
    for k in range(40, 80):
        assert genuine(gate, 2.0 + 0.05 * k, (10.0 + 0.25 * k, 0.0, -5.0)) is Verdict.ACCEPT
    assert gate.confirmed


def test_a_jittery_reordering_link_never_rejects_a_genuine_pose_as_implausible() -> None:
    """Delays of 0-300 ms (uniform), datagrams delivered in the order they arrive (so some overtake others), the
    vehicle accelerating to 12 m/s and turning: every pose in order is accepted, the overtaken ones are stale, none
    is a jump, a lead or a conflict. (While the relation is learned, a pose that came early is held to its receipt,
    and one it overtook may still be newer than that: one such in the first half second is accepted, harmless.)"""
    rng = np.random.default_rng(7)
    gate = PoseGate(PoseLimits())
    sent = []
    for k in range(600):
        t = 0.05 * k
        speed = min(12.0, 2.0 * t)
        pos = (speed * t * 0.5, 5.0 * math.sin(0.2 * t), -5.0)
        sent.append((t + float(rng.uniform(0.0, 0.3)), round(t * 1000.0), pos))
    newest_ms, late_accepted = -1, []
    for rx, ms, pos in sorted(sent):
        verdict = gate.check(ms, pos, rx)
        if ms > newest_ms:
            assert verdict is Verdict.ACCEPT
        elif verdict is not Verdict.STALE:  # overtaken: a newer pose came first
            assert verdict is Verdict.ACCEPT
            late_accepted.append(rx)
        newest_ms = max(newest_ms, ms)
    assert len(late_accepted) <= 1 and all(rx < 1.0 for rx in late_accepted)
    assert gate.confirmed


def test_clock_drift_and_a_delay_that_shrinks_for_good_are_followed() -> None:
    """The autopilot's clock 500 ppm fast for an hour (the companion's NTP may slew that much), and a link whose
    delay drops from 0.8 s to 10 ms at once (a drained queue): every pose accepted."""
    gate = PoseGate(PoseLimits())
    verdicts = set()
    for k in range(18_000):  # 5 Hz for an hour
        rx = 0.2 * k
        delay = 0.8 if k < 50 else 0.01
        verdicts.add(gate.check(round((rx - delay) * 1.0005 * 1000.0), (0.0, 0.0, -5.0), rx))
    assert verdicts == {Verdict.ACCEPT}


def test_a_stream_stamped_just_ahead_of_the_genuine_one_is_a_conflict_and_unconfirms() -> None:
    """A forged stream sent faster than the genuine one, or stamped a little ahead of it, makes the genuine poses
    stale; walking away at 2 m/s it would move the pose within the vehicle's limits. The genuine poses, stale, now
    contradict the accepted ones of their time: the anchor is not confirmed (the service brakes)."""
    gate = PoseGate(PoseLimits())
    for k in range(40):
        genuine(gate, k * 0.05, (0.0, 0.0, -5.0))
    assert gate.confirmed
    verdicts = []
    for k in range(40, 100):
        t = k * 0.05
        gate.check(round((t + 0.06) * 1000.0), (0.0, 2.0 * (t - 2.0), -5.0), t)  # 60 ms ahead, walking east
        verdicts.append(genuine(gate, t, (0.0, 0.0, -5.0)))
        assert not gate.confirmed or k < 45
    assert Verdict.CONFLICT in verdicts[:10] and verdicts[-20:] == [Verdict.CONFLICT] * 20


def test_reordered_frozen_and_pre_reset_poses_are_stale_not_conflicts() -> None:
    """A genuine pose delivered late, the last stamp again with a new position (a stream whose clock stopped), and
    a pose from before an EKF reset delivered after it: stale, nothing else."""
    gate = PoseGate(PoseLimits(reset_samples=5))
    for k in range(20):
        assert genuine(gate, k * 0.05, (0.05 * k, 0.0, -5.0)) is Verdict.ACCEPT
    assert gate.check(900, (0.9, 0.0, -5.0), 1.2) is Verdict.STALE  # reordered
    assert gate.check(950, (3.0, 0.0, -5.0), 1.2) is Verdict.STALE  # frozen clock
    for k in range(20, 25):  # an EKF reset: 20 m east from now on
        genuine(gate, k * 0.05, (0.05 * k, 20.0, -5.0))
    assert gate.last is not None and gate.last.pos[1] == 20.0
    assert gate.check(975, (0.975, 0.0, -5.0), 1.3) is Verdict.STALE  # from before the reset, late
    assert gate.confirmed
