"""Scans reaching the running service over a real zenoh session (loopback, free ports, multicast scouting off).

ROS 2 sources publish LaserScan CDR without naming an encoding: zenoh-bridge-ros2dds (``route_publisher.rs``:
``publisher.put(sample)``) and rmw_zenoh (``rmw_publisher_data.cpp``: ``z_publisher_put`` with default options)
leave zenoh's default ``zenoh/bytes``; other publishers say ``application/octet-stream``. The publisher here is a
plain zenoh session doing the same, so the samples take the service's real path (``ZenohInputs`` ->
``PerceptionFrontEnd.on_scan_payload``).
"""

from __future__ import annotations

import asyncio
import contextlib
import json
from collections.abc import AsyncIterator, Callable
from typing import Any

import numpy as np
import pytest
import zenoh

from apf_companion.config import config_from_mapping
from apf_companion.perception import RangeScan, ScanFrame, encode_laserscan_cdr, encode_scan_json
from apf_companion.service import CompanionService
from tests.conftest import HANG_S, free_port, until

KEY = "scan"  # where zenoh-bridge-ros2dds puts /scan


def _scan() -> RangeScan:
    n = 72
    return RangeScan(
        t_s=0.0,
        frame=ScanFrame.BODY_FRD,
        bearings_rad=np.deg2rad(np.arange(n) * 5.0 - 180.0),
        ranges_m=np.full(n, 4.0),
        range_min_m=0.1,
        range_max_m=12.0,
    )


@contextlib.asynccontextmanager
async def service_and_publisher() -> AsyncIterator[tuple[CompanionService, zenoh.Session]]:
    """The service (zenoh listening on a free port, ranges from zenoh only, nothing on its MAVLink port) running
    in this loop, and a plain zenoh peer connected to it."""
    zport = free_port()
    cfg = config_from_mapping(
        {
            "link": {"connect": "udpin:127.0.0.1:0"},
            "sensors": {"mavlink": False, "zenoh": True},
            "zenoh": {"enabled": True, "mode": "peer", "listen": [f"tcp/127.0.0.1:{zport}"], "sensor_key": KEY},
        }
    )
    svc = await CompanionService.open(cfg)
    conf = zenoh.Config()
    conf.insert_json5("mode", '"peer"')
    conf.insert_json5("connect/endpoints", json.dumps([f"tcp/127.0.0.1:{zport}"]))
    conf.insert_json5("listen/endpoints", "[]")
    conf.insert_json5("scouting/multicast/enabled", "false")
    session = zenoh.open(conf)
    try:
        async with asyncio.TaskGroup() as tg:
            task = tg.create_task(svc.run())
            try:
                yield svc, session
            finally:
                svc.stop()
                await task
    finally:
        session.close()  # type: ignore[no-untyped-call]


def _put(session: zenoh.Session, payload: bytes, encoding: str | None) -> None:
    """One sample on ``KEY``; ``encoding`` None puts it as zenoh-bridge-ros2dds does, naming none."""
    if encoding is None:
        session.put(KEY, payload)
    else:
        session.put(KEY, payload, encoding=zenoh.Encoding(encoding))


async def _put_until_counted(svc: CompanionService, put: Callable[[], Any]) -> None:
    """Put until the service counted a scan or a bad scan (the peers may still be connecting)."""
    c = svc.perception.counters

    def counted() -> bool:
        if c.scans or c.bad_scans:
            return True
        put()
        return False

    await until(counted, HANG_S, "a scan or a bad scan counted")


@pytest.mark.parametrize("encoding", [None, "application/octet-stream"], ids=["default zenoh/bytes", "octet-stream"])
async def test_a_laserscan_without_a_cdr_encoding_is_a_scan(encoding: str | None) -> None:
    payload = encode_laserscan_cdr(_scan(), frame_id="laser")
    async with service_and_publisher() as (svc, session):
        await _put_until_counted(svc, lambda: _put(session, payload, encoding))
        c = svc.perception.counters
        assert (c.scans >= 1, c.bad_scans) == (True, 0)


@pytest.mark.parametrize(
    ("encoding", "payload"),
    [
        ("application/cdr", encode_laserscan_cdr(_scan())),
        ("application/json", encode_scan_json(_scan())),
        (None, encode_scan_json(_scan())),
    ],
    ids=["cdr", "json", "json with the default encoding"],
)
async def test_explicit_encodings_and_default_json_still_decode(encoding: str | None, payload: bytes) -> None:
    async with service_and_publisher() as (svc, session):
        await _put_until_counted(svc, lambda: _put(session, payload, encoding))
        c = svc.perception.counters
        assert (c.scans >= 1, c.bad_scans) == (True, 0)


async def test_garbage_with_the_default_encoding_is_a_bad_scan() -> None:
    async with service_and_publisher() as (svc, session):
        await _put_until_counted(svc, lambda: _put(session, b"\x12\x34garbage", None))
        c = svc.perception.counters
        assert (c.scans, c.bad_scans >= 1) == (0, True)
