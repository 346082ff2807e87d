"""Errors a user sees at once: nothing heard from the autopilot, or a refused TCP connection, is a WARNING that
says what to check."""

from __future__ import annotations

import asyncio
import logging

import pytest

from apf_companion.config import config_from_mapping
from apf_companion.links import MavlinkLink
from apf_companion.service import CompanionService
from tests.conftest import HANG_S, free_port, until

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
