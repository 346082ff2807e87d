"""Errors a user sees at once: nothing heard from the autopilot, or a refused TCP connection, is a WARNING that
says what to check."""

from __future__ import annotations

import asyncio
import logging
import socket

import pytest

from apf_companion.config import config_from_mapping
from apf_companion.links import MavlinkLink
from apf_companion.service import CompanionService
from sim.vehicle import SimConfig, Simulator
from sim.world import World
from tests.conftest import HANG_S, SimulatorClock, free_port, until

pytestmark = pytest.mark.timeout(60)


def _warnings(caplog: pytest.LogCaptureFixture, event: str) -> list[logging.LogRecord]:
    return [r for r in caplog.records if r.getMessage() == event and r.levelno == logging.WARNING]


async def test_no_heartbeat_is_a_warning_saying_what_to_check(caplog: pytest.LogCaptureFixture) -> None:
    caplog.set_level(logging.INFO)
    # time_scale 20: the 5 s (vehicle time) of silence pass in a quarter of a wall second
    cfg = config_from_mapping({"link": {"connect": "udpin:127.0.0.1:0"}, "cycle": {"time_scale": 20.0}})
    svc = await CompanionService.open(cfg)
    task = asyncio.create_task(svc.run())
    try:
        await until(lambda: _warnings(caplog, "link.no_heartbeat"), HANG_S, "no-heartbeat warning")
    finally:
        svc.stop()
        await task
    (rec,) = _warnings(caplog, "link.no_heartbeat")[:1]
    assert "nothing sends to 127.0.0.1:" in rec.hint  # type: ignore[attr-defined]
    assert rec.connect == "udpin:127.0.0.1:0"  # type: ignore[attr-defined]


async def test_refused_tcp_connection_is_a_warning_with_a_hint(caplog: pytest.LogCaptureFixture) -> None:
    caplog.set_level(logging.DEBUG)
    port = free_port()  # nothing listens there
    link = await MavlinkLink.open(f"tcp:127.0.0.1:{port}", source_system=1, source_component=191)
    try:
        await until(lambda: _warnings(caplog, "mavlink.tcp_connect_failed"), HANG_S, "refused warning")
        rec = _warnings(caplog, "mavlink.tcp_connect_failed")[0]
        assert f"listening at 127.0.0.1:{port}" in rec.hint  # type: ignore[attr-defined]
        assert "refused" in rec.error.lower() or "connect" in rec.error.lower()  # type: ignore[attr-defined]
        # the retries (with backoff) stay at DEBUG: one warning per streak of failures
        await until(
            lambda: sum(r.getMessage() == "mavlink.tcp_connect_failed" for r in caplog.records) >= 2,
            HANG_S,
            "a retry",
        )
        assert len(_warnings(caplog, "mavlink.tcp_connect_failed")) == 1
    finally:
        await link.aclose()


async def test_a_dry_run_without_poses_says_why(caplog: pytest.LogCaptureFixture) -> None:
    """The bundled simulator streams nothing unasked, as a default ArduCopter: a dry run (no stream requests) gets
    HEARTBEATs but no LOCAL_POSITION_NED, and says once what to set instead of holding in silence."""
    caplog.set_level(logging.INFO)
    port = free_port(socket.SOCK_DGRAM)
    cfg = config_from_mapping({"link": {"connect": f"udpin:127.0.0.1:{port}"}, "dry_run": True})
    sim = await Simulator.start(
        SimConfig(links=[f"udpout:127.0.0.1:{port}"], profile="ardupilot", world=World.empty(), speedup=4.0, seed=1)
    )
    clock = SimulatorClock(4.0)
    try:
        svc = await CompanionService.open(cfg, clock=clock)
        clock.follow(sim)
        task = asyncio.create_task(svc.run())
        try:
            await until(lambda: _warnings(caplog, "dry_run.no_pose"), HANG_S, "the dry-run no-pose warning")
            assert svc.handlers.heard and svc.perception.counters.poses == 0
            t_warned = clock.now()
            await until(lambda: clock.now() >= t_warned + 3.0, HANG_S, "3 s more")
        finally:
            svc.stop()
            result = await task
    finally:
        await sim.aclose()
    (rec,) = _warnings(caplog, "dry_run.no_pose")  # once
    assert "SRn_POSITION" in rec.hint and "MAV_n_MODE" in rec.hint  # type: ignore[attr-defined]
    assert not _warnings(caplog, "link.no_heartbeat")
    assert result.counters["setpoints_sent"] == 0
