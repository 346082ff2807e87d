"""Fewer setpoints, more caution: measured link quality shortens the navigator's steps (apf_companion/linkquality.py).

Unit tests of the pure parts (``caution_scale``, ``LinkMeter``, ``shortened``, the navigator's setpoint under a
given quality, the config keys), then a flight over real loopback UDP through the seeded fault proxy
(``sim.linkfaults.LinkProxy``) showing shorter steps under 30 % loss than on a clean link.
"""

from __future__ import annotations

import contextlib
import itertools
import math
from collections.abc import AsyncIterator
from dataclasses import dataclass

import numpy as np
import pytest

from apf_companion.config import ServiceConfig, config_from_mapping
from apf_companion.errors import ConfigError
from apf_companion.goal import Route
from apf_companion.linkquality import CLEAN_LINK, CautionParams, LinkMeter, LinkQuality, caution_scale
from apf_companion.navigator import CycleOutput, Navigator, shortened
from apf_companion.service import CompanionService
from apf_companion.setpoint import SetpointKind
from sim.linkfaults import LinkFaults, LinkProxy
from tests.conftest import SimulatorClock, until
from tests.service.test_service_flight import SPEEDUP, airborne_behind, running, service_config
from tests.service.test_service_navigator import feed, make

P = CautionParams(min_scale=0.3, full_loss=0.5, ok_age_s=0.2, full_age_s=0.5, window_s=2.0)


# ---- caution_scale -------------------------------------------------------------------------------------------------
def test_clean_link_is_full_steps() -> None:
    assert caution_scale(CLEAN_LINK, P) == 1.0
    assert caution_scale(LinkQuality(pose_age_s=P.ok_age_s), P) == 1.0


@pytest.mark.parametrize(
    ("quality", "scale"),
    [
        (LinkQuality(pose_loss=0.25), 1.0 - 0.7 * 0.5),
        (LinkQuality(pose_loss=0.5), 0.3),
        (LinkQuality(pose_loss=1.0), 0.3),
        (LinkQuality(send_failures=0.1), 1.0 - 0.7 * 0.2),
        (LinkQuality(pose_age_s=0.35), 1.0 - 0.7 * 0.5),
        (LinkQuality(pose_age_s=5.0), 0.3),
        (LinkQuality(pose_loss=0.1, pose_age_s=0.35, send_failures=0.05), 1.0 - 0.7 * 0.5),  # the worst counts
        (LinkQuality(pose_loss=math.nan), 0.3),  # unmeasurable is the worst
        (LinkQuality(pose_age_s=math.inf), 0.3),
    ],
)
def test_scale_falls_linearly_with_the_worst_measure(quality: LinkQuality, scale: float) -> None:
    assert caution_scale(quality, P) == pytest.approx(scale)


def test_scale_is_monotonic_and_bounded() -> None:
    losses = np.linspace(0.0, 1.0, 51)
    scales = [caution_scale(LinkQuality(pose_loss=float(x)), P) for x in losses]
    assert all(a >= b for a, b in itertools.pairwise(scales))
    assert min(scales) == pytest.approx(P.min_scale) and max(scales) == 1.0
    off = CautionParams(min_scale=1.0)
    assert caution_scale(LinkQuality(pose_loss=1.0, pose_age_s=9.0), off) == 1.0


@pytest.mark.parametrize(
    "kw",
    [{"min_scale": 0.0}, {"min_scale": 1.5}, {"full_loss": 0.0}, {"ok_age_s": 0.5}, {"window_s": 0.0}],
)
def test_bad_caution_params(kw: dict[str, float]) -> None:
    with pytest.raises(ConfigError):
        CautionParams(**kw)


# ---- LinkMeter -----------------------------------------------------------------------------------------------------
def _stream(meter: LinkMeter, n: int, *, keep: int = 1, every: int = 1, start_ms: int = 1000) -> None:
    """A 10 Hz pose stream of ``n`` poses, of which ``keep`` in each ``every`` arrive."""
    for k in range(n):
        if k % every < keep:
            meter.pose(start_ms + 100 * k)


def test_meter_no_loss() -> None:
    meter = LinkMeter(P)
    _stream(meter, 50)
    assert meter.pose_loss() == pytest.approx(0.0, abs=1e-9)
    q = meter.quality(10.0, 9.95)
    assert q.pose_loss == meter.pose_loss() and q.pose_age_s == pytest.approx(0.05) and q.send_failures == 0.0


@pytest.mark.parametrize("loss", [0.1, 0.3, 0.5])
def test_meter_measures_the_share_of_lost_poses(loss: float) -> None:
    """Seeded random loss; the estimate after each arrival, averaged over a long stream, is the loss rate."""
    meter = LinkMeter(P)
    rng = np.random.default_rng(1)
    estimates = []
    for k in range(3000):
        if k < 5 or rng.random() >= loss:
            meter.pose(1000 + 100 * k)
            if k > 50:
                estimates.append(meter.pose_loss())
    assert float(np.mean(estimates)) == pytest.approx(loss, abs=0.05)


def test_meter_regular_loss_after_a_clean_stream() -> None:
    """Every other pose lost: the clean stream before it (within the interval memory) gives the true interval."""
    meter = LinkMeter(P)
    _stream(meter, 10)
    _stream(meter, 100, keep=1, every=2, start_ms=2000)
    assert meter.pose_loss() == pytest.approx(0.5, abs=0.03)


def test_meter_fills_its_window_from_the_first_pose() -> None:
    """A young stream is not taken for a lossy one: the window spans only what was streamed so far."""
    meter = LinkMeter(P)
    _stream(meter, 3)
    assert meter.pose_loss() == pytest.approx(0.0, abs=1e-9)
    assert LinkMeter(P).pose_loss() == 0.0  # nothing known yet
    lone = LinkMeter(P)
    _stream(lone, 1)
    assert lone.pose_loss() == 0.0  # no interval known yet


def test_meter_after_a_burst_of_loss_recovers_within_the_window() -> None:
    meter = LinkMeter(P)
    _stream(meter, 30)
    _stream(meter, 30, keep=1, every=5, start_ms=4000)
    assert meter.pose_loss() > 0.6
    _stream(meter, 30, start_ms=7000)  # 3 s of clean stream: more than the 2 s window
    assert meter.pose_loss() == pytest.approx(0.0, abs=1e-9)


def test_meter_restarts_on_a_new_time_base() -> None:
    meter = LinkMeter(P)
    _stream(meter, 10, start_ms=49_000)
    _stream(meter, 30, keep=1, every=3, start_ms=50_000)
    assert meter.pose_loss() > 0.5
    _stream(meter, 10, start_ms=100)  # the autopilot rebooted: its time went back
    assert meter.pose_loss() == pytest.approx(0.0, abs=1e-9)


def test_meter_send_failures_over_the_window() -> None:
    meter = LinkMeter(P)
    for k in range(10):
        meter.sent(k % 5 != 0, 0.1 * k)  # 2 of 10 failed
    assert meter.quality(0.95, None).send_failures == pytest.approx(0.2)
    assert meter.quality(10.0, None) == CLEAN_LINK  # all of them left the window; no pose: no age


# ---- the navigator's setpoints -------------------------------------------------------------------------------------
def test_shortened() -> None:
    pos = np.array([0.0, 0.0, -5.0])
    target = np.array([0.4, 0.0, -6.0])
    assert np.array_equal(shortened(pos, target, fraction=1.0, step_m=0.4, dim=2), target)
    half = shortened(pos, target, fraction=0.5, step_m=0.4, dim=2)
    assert half == pytest.approx([0.2, 0.0, -6.0])  # horizontal only in 2D: the target's altitude is kept
    lagging = shortened(pos, np.array([0.0, 1.0, -5.0]), fraction=0.5, step_m=0.4, dim=2)
    assert lagging == pytest.approx([0.0, 0.5, -5.0])  # more than a step away: half of the way
    near = np.array([0.1, 0.0, -5.0])
    assert np.array_equal(shortened(pos, near, fraction=0.5, step_m=0.4, dim=2), near)  # within half a step
    d3 = shortened(pos, np.array([0.0, 0.0, -5.4]), fraction=0.5, step_m=0.4, dim=3)
    assert d3 == pytest.approx([0.0, 0.0, -5.2])


def _first_step(link: LinkQuality, cfg: ServiceConfig | None = None) -> tuple[Navigator, CycleOutput]:
    nav = make(cfg)
    feed(nav, 0.1, (0, 0, -5))
    nav.set_route(Route.point(10.0, 0.0, -5.0, source="test"), 0.1)
    return nav, nav.cycle(0.1, link)


def test_lossy_link_shortens_the_step_the_speed_and_the_drift() -> None:
    _, clean = _first_step(CLEAN_LINK)
    nav, lossy = _first_step(LinkQuality(pose_loss=0.3))
    c = caution_scale(LinkQuality(pose_loss=0.3), nav.params.caution)
    p = nav.params.caution
    assert c == pytest.approx(1.0 - (1.0 - p.min_scale) * 0.3 / p.full_loss)
    assert clean.caution == 1.0 and lossy.caution == pytest.approx(c)
    assert clean.setpoint is not None and lossy.setpoint is not None
    assert lossy.setpoint.kind is SetpointKind.NAVIGATE and lossy.decision == clean.decision == "GREEDY"
    step = math.dist(clean.setpoint.pos_ned_m[:2], (0.0, 0.0))
    assert step == pytest.approx(nav.params.step_m)
    assert math.dist(lossy.setpoint.pos_ned_m[:2], (0.0, 0.0)) == pytest.approx(c * step)
    # Same direction, feed-forward scaled by the same fraction (the silent-drift cap shrinks with it).
    assert np.asarray(lossy.setpoint.vel_ned_m_s) == pytest.approx(c * np.asarray(clean.setpoint.vel_ned_m_s))
    safety = ServiceConfig().safety
    assert math.hypot(*lossy.setpoint.vel_ned_m_s[:2]) * safety.guid_timeout_s <= c * safety.silent_drift_m + 1e-9
    assert nav.counts()["shortened_setpoints"] == 1


def test_caution_off_by_config() -> None:
    cfg = config_from_mapping({"safety": {"caution_min_scale": 1.0}})
    _, clean = _first_step(CLEAN_LINK, cfg)
    _, lossy = _first_step(LinkQuality(pose_loss=0.9, pose_age_s=0.45), cfg)
    assert clean.setpoint == lossy.setpoint and lossy.caution == 1.0


@pytest.mark.parametrize(
    ("section", "key", "value"),
    [
        ("safety", "caution_min_scale", 0.0),
        ("safety", "caution_min_scale", 1.01),
        ("safety", "caution_full_loss", 0.0),
        ("safety", "caution_ok_age_s", -0.1),
        ("safety", "caution_window_s", 0.0),
        ("safety", "caution_ok_age_s", 0.5),  # not below cycle.pose_max_age_s (0.5)
    ],
)
def test_config_keys_are_validated(section: str, key: str, value: float) -> None:
    with pytest.raises(ConfigError, match=f"{section}.{key}"):
        config_from_mapping({section: {key: value}})


def test_config_reaches_the_navigator() -> None:
    cfg = config_from_mapping(
        {
            "safety": {"caution_min_scale": 0.4, "caution_full_loss": 0.4, "caution_ok_age_s": 0.1},
            "cycle": {"pose_max_age_s": 0.8},
        }
    )
    assert make(cfg).params.caution == CautionParams(
        min_scale=0.4, full_loss=0.4, ok_age_s=0.1, full_age_s=0.8, window_s=2.0
    )


# ---- over loopback through the fault proxy -------------------------------------------------------------------------
@dataclass
class _Step:
    caution: float
    step_m: float  # from the pose the cycle planned from to the setpoint's position, horizontal
    speed_m_s: float  # the setpoint's feed-forward, horizontal


@contextlib.asynccontextmanager
async def _flight_through(faults: LinkFaults) -> AsyncIterator[tuple[CompanionService, list[_Step]]]:
    """Service (udpin) <- seeded fault proxy <- simulator, in this loop; records each navigation step's length
    (from the pose the cycle planned from to the setpoint's position) and the caution it was flown with."""
    cfg = service_config(cycle={"pose_max_age_s": 1.0, "ranges_max_age_s": 1.0})
    svc = await CompanionService.open(
        cfg, route=Route.point(3.0, 12.0, -5.0, source="test"), clock=SimulatorClock(SPEEDUP)
    )
    assert svc.link is not None and svc.link.local_address is not None
    proxy = await LinkProxy.open(faults, companion_port=svc.link.local_address[1], seed=7, time_scale=SPEEDUP)
    steps: list[_Step] = []
    nav = svc.navigator
    cycle = nav.cycle

    def recording(now_s: float, link: LinkQuality = CLEAN_LINK) -> CycleOutput:
        pose = nav.pose
        out = cycle(now_s, link)
        sp = out.setpoint
        if sp is not None and sp.kind is SetpointKind.NAVIGATE and pose is not None:
            step = math.dist(sp.pos_ned_m[:2], pose.pos_ned_m[:2].tolist())
            steps.append(_Step(out.caution, step, math.hypot(*sp.vel_ned_m_s[:2])))
        return out

    nav.cycle = recording  # type: ignore[method-assign]
    sim = await airborne_behind(proxy.vehicle_port)
    try:
        async with running(svc, sim):
            yield svc, steps
    finally:
        await proxy.aclose()


@pytest.mark.slow
@pytest.mark.timeout(300)
async def test_steps_are_shorter_through_a_lossy_proxy() -> None:
    n = 40  # navigation setpoints looked at in each flight
    async with _flight_through(LinkFaults()) as (_, clean):
        await until(lambda: len(clean) >= n, 240.0, f"{n} navigation setpoints on a clean link")
    async with _flight_through(LinkFaults(loss=0.3)) as (svc, lossy):
        await until(lambda: len(lossy) >= n, 240.0, f"{n} navigation setpoints through 30 % loss")
        assert svc.link_meter.pose_loss() > 0.1
    # After the first ones (the loss window fills). While the vehicle tracks a bacteria point the step shrinks
    # as it gets there, so the reach is compared at the 90th percentile (a fresh step) and the speed by median.
    clean_steps = np.array([s.step_m for s in clean[5:n]])
    lossy_steps = np.array([s.step_m for s in lossy[5:n]])
    assert all(s.caution == 1.0 for s in clean[:n])
    cautions = np.array([s.caution for s in lossy[5:n]])
    assert float(np.median(cautions)) < 0.9
    reach = (float(np.percentile(lossy_steps, 90)), float(np.percentile(clean_steps, 90)))
    assert reach[0] < 0.85 * reach[1], reach
    speeds = (float(np.median([s.speed_m_s for s in lossy[5:n]])), float(np.median([s.speed_m_s for s in clean[5:n]])))
    assert speeds[0] < 0.85 * speeds[1], speeds
    assert svc.navigator.counts()["shortened_setpoints"] > 0
