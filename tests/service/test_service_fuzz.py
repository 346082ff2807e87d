"""Fuzzing the service's real input path (CI version; benchmarks/fuzz_long.py runs 10^6 frames).

Hypothesis picks the sequence of hostile generators (tests/service/fuzzing.py) and the seed of the values they
draw; each example is a real service on loopback UDP with a genuine autopilot stream interleaved. Checked: the
service survives, no exception escapes a handler, every setpoint is finite and plausible against the genuine
position (brakes: zero velocity), and what was rejected is counted in the status and the NAMED_VALUE_INTs.
"""

from __future__ import annotations

import asyncio
import random

import pytest
from hypothesis import HealthCheck, Phase, given, settings
from hypothesis import strategies as st

from apf_companion.autopilot import MASK_VELOCITY
from apf_companion.goal import Route
from apf_companion.navigator import State
from apf_companion.status import NVI_ERRORS, NVI_REJECTED_LINK, NVI_REJECTED_POSES, NVI_REJECTED_SCANS
from tests.conftest import within
from tests.service.fuzzing import GENERATORS, WEIGHTS, FuzzReport, run_fuzz
from tests.service.test_service_mavlink import rig

pytestmark = pytest.mark.timeout(120)

RATE_HZ = 400.0  # hostile frames per second: the service flies between them (a flood is benchmarks/fuzz_long.py)
# Every generator in every example, as often as its weight says (40 frames at weight 1); hypothesis orders them.
_KINDS = [k for k in sorted(GENERATORS) for _ in range(max(1, round(40 * WEIGHTS.get(k, 1.0))))]


def _check(report: FuzzReport) -> None:
    assert report.alive, "the service task group ended"
    assert report.handler_errors == 0, report.fault_kinds
    assert report.send_errors == 0
    assert not report.bad_setpoints, report.bad_setpoints[:5]
    assert report.setpoints > 0, "the service never flew: the fuzz did not reach the setpoint path"
    rejected = report.rejected
    assert rejected[NVI_REJECTED_POSES] > 0 and rejected[NVI_REJECTED_SCANS] > 0 and rejected[NVI_REJECTED_LINK] > 0
    assert rejected[NVI_ERRORS] == 0
    assert report.counters["link_bad_frames"] > 0 and report.counters["foreign_messages"] > 0
    # The ground station saw the same totals (NAMED_VALUE_INT at 5 Hz: the last one may lag the final count).
    for name, total in rejected.items():
        assert 0 <= report.named_int.get(name, -1) <= total, name
    assert report.named_int[NVI_REJECTED_POSES] > 0


@settings(
    max_examples=4,
    deadline=None,
    derandomize=True,
    database=None,
    phases=[Phase.explicit, Phase.generate],  # no shrinking: one example is a service run of seconds
    suppress_health_check=[HealthCheck.too_slow, HealthCheck.data_too_large, HealthCheck.large_base_example],
)
@given(
    kinds=st.permutations(_KINDS),
    seed=st.integers(0, 2**32 - 1),
)
def test_hostile_frames_never_crash_the_service_or_become_setpoints(kinds: list[str], seed: int) -> None:
    # The generators' values come from a seeded Random, not from hypothesis: how many a generator draws depends on
    # the genuine stream (replays, positions), which hypothesis would see as a flaky strategy.
    report = asyncio.run(run_fuzz(kinds, random.Random(seed), rate_hz=RATE_HZ))
    _check(report)


def test_every_generator_runs_in_a_seeded_flood() -> None:
    """All generators, as fast as the service reads them (the benchmark's mode), a fixed seed."""
    rng = random.Random(9)
    kinds = [k for k in sorted(GENERATORS) for _ in range(60)]
    rng.shuffle(kinds)
    report = asyncio.run(run_fuzz(kinds, rng))
    assert set(report.by_generator) == set(GENERATORS)
    _check(report)


async def test_a_forged_reset_never_makes_a_spoofed_pose_a_hold_point() -> None:
    """Found by the fuzz: an ODOMETRY reset-counter change (or a HEARTBEAT in MAV_STATE_BOOT) from the autopilot's
    ids, then one pose 1 km away. The gate re-anchors on it, but an anchor on evidence alone is not confirmed:
    the service brakes (zero velocity, position ignored) instead of holding at the spoofed point, and navigates
    on from the genuine stream once that re-anchors."""
    route = Route.point(30.0, 0.0, -5.0, source="test")
    async with rig(route=route) as (svc, ap):
        await within(
            svc.clock.now, lambda: svc.navigator.engaged and len(ap.setpoints()) > 10, 10.0, "flying in GUIDED"
        )
        mav, n0 = ap.link.mav, len(ap.setpoints())
        quat, cov = [1.0, 0.0, 0.0, 0.0], [float("nan")] * 21
        for counter in (1, 2):  # the second is a change: an announced estimator reset
            x, y, z = ap.pos
            us = ap.boot_ms() * 1000
            ap.link.send(mav.odometry_encode(us, 1, 8, x, y, z, quat, 0, 0, 0, 0, 0, 0, cov, cov, counter, 0, 0))
        ap.link.send(mav.local_position_ned_encode(ap.boot_ms() + 5, ap.pos[0] + 1000.0, 0.0, -5.0, 0, 0, 0))
        await within(
            svc.clock.now,
            lambda: svc.perception.counters.pose_resets >= 2,
            5.0,
            "spoof anchored, then the genuine stream",
        )
        await within(svc.clock.now, lambda: svc.navigator.state is State.NAVIGATING, 10.0, "navigating on")
        n1 = len(ap.setpoints())
        await within(svc.clock.now, lambda: len(ap.setpoints()) > n1 + 5, 5.0, "setpoints again")
        after = [m for _, m in ap.setpoints()[n0:]]
        brakes = [m for m in after if m.type_mask == MASK_VELOCITY]
        assert brakes and all(m.vx == m.vy == m.vz == 0 for m in brakes)
        positioned = [m for m in after if m.type_mask != MASK_VELOCITY]
        assert positioned and all(abs(m.x) < 40.0 and abs(m.y) < 1.0 for m in positioned)
        assert svc.navigator.counters.unconfirmed_pose_cycles > 0
