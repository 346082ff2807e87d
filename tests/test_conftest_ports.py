"""The test suite's own port picking (tests/conftest.py ``free_port``), which the parallel run relies on."""

from __future__ import annotations

import itertools
import socket
from pathlib import Path

import pytest

from tests import conftest
from tests.conftest import PORT_BLOCK, free_port, worker_port_block


def test_each_worker_has_its_own_block_below_the_ephemeral_range(monkeypatch: pytest.MonkeyPatch) -> None:
    ephemeral = Path("/proc/sys/net/ipv4/ip_local_port_range")
    low = int(ephemeral.read_text().split()[0]) if ephemeral.exists() else 32768
    for run in ("run-a", "run-b"):
        monkeypatch.setenv("PYTEST_XDIST_TESTRUNUID", run)
        bases = []
        for worker in ("gw0", "gw1", "gw2", "gw23"):
            monkeypatch.setenv("PYTEST_XDIST_WORKER", worker)
            bases.append(worker_port_block())
        assert len(set(bases)) == len(bases)
        assert all(b >= conftest.PORT_BASE and b + PORT_BLOCK <= low for b in bases)
        assert all((b - conftest.PORT_BASE) % PORT_BLOCK == 0 for b in bases)
    monkeypatch.delenv("PYTEST_XDIST_WORKER")
    monkeypatch.delenv("PYTEST_XDIST_TESTRUNUID")
    alone = worker_port_block()  # without xdist: a block by the process id
    assert alone >= conftest.PORT_BASE and alone + PORT_BLOCK <= low


@pytest.mark.parametrize("kind", [socket.SOCK_STREAM, socket.SOCK_DGRAM])
def test_a_taken_port_is_passed_over(monkeypatch: pytest.MonkeyPatch, kind: int) -> None:
    base = worker_port_block()
    monkeypatch.setattr(conftest, "_port_picks", itertools.count(0))
    first = free_port(kind)
    monkeypatch.setattr(conftest, "_port_picks", itertools.count(first - base))
    with socket.socket(socket.AF_INET, kind) as held:
        held.bind(("127.0.0.1", first))
        second = free_port(kind)
    assert base <= first < second < base + PORT_BLOCK
    with socket.socket(socket.AF_INET, kind) as s:
        s.bind(("127.0.0.1", second))  # released: the test's own bind succeeds
