"""Shared test helpers: free loopback ports, and waiting on conditions instead of sleeping.

Tests here must pass on a loaded machine (see docs/testing.md): a wait is on a condition, a message or the
simulated clock, and its deadline only bounds a hang. ``HANG_S`` is that deadline for things that should
happen at once.
"""

from __future__ import annotations

import asyncio
import os
import socket
from collections.abc import Callable

import pytest

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

HANG_S = 30.0  # wall seconds: only reached when something hangs
POLL_S = 0.01  # how often ``until`` looks again


def free_port(kind: int = socket.SOCK_STREAM) -> int:
    """A port on 127.0.0.1 that was free a moment ago (bind to 0, read it back, release)."""
    with socket.socket(socket.AF_INET, kind) as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


async def until(condition: Callable[[], object], timeout_s: float = HANG_S, what: str = "condition") -> None:
    """Wait until ``condition()`` is true; AssertionError naming ``what`` if it is not within ``timeout_s`` wall s."""
    try:
        async with asyncio.timeout(timeout_s):
            while not condition():
                await asyncio.sleep(POLL_S)
    except TimeoutError:
        msg = f"{what}: not within {timeout_s} s"
        raise AssertionError(msg) from None


@pytest.fixture
def udp_port() -> int:
    return free_port(socket.SOCK_DGRAM)


@pytest.fixture
def tcp_port() -> int:
    return free_port(socket.SOCK_STREAM)
