"""systemd notify and watchdog: READY=1 once running, WATCHDOG=1 from completed planning cycles (none while the
cycle fails), STATUS= with the state, STOPPING=1 at the end; over a real AF_UNIX datagram socket as NOTIFY_SOCKET,
with the service flying the bundled simulator."""

from __future__ import annotations

import os
import socket
from collections.abc import Iterator
from pathlib import Path

import pytest

from apf_companion.goal import Route
from apf_companion.navigator import State
from apf_companion.sdnotify import SystemdNotifier, Watchdog
from sim.world import World
from tests.conftest import until
from tests.service.test_service_flight import flight, service_config

pytestmark = pytest.mark.timeout(90)

WATCHDOG_USEC = 200_000  # pet every 0.1 s wall


class NotifyListener:
    """The systemd side: a bound AF_UNIX datagram socket; ``drain`` collects what arrived."""

    def __init__(self, path: Path) -> None:
        self.sock = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM)
        self.sock.bind(str(path))
        self.sock.setblocking(False)
        self.messages: list[dict[str, str]] = []

    def drain(self) -> list[dict[str, str]]:
        while True:
            try:
                data = self.sock.recv(4096)
            except BlockingIOError:
                return self.messages
            self.messages.append(dict(line.split("=", 1) for line in data.decode().splitlines()))

    def having(self, key: str) -> list[dict[str, str]]:
        return [m for m in self.drain() if key in m]


@pytest.fixture
def listener(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> Iterator[NotifyListener]:
    path = tmp_path / "notify"
    lis = NotifyListener(path)
    monkeypatch.setenv("NOTIFY_SOCKET", str(path))
    monkeypatch.setenv("WATCHDOG_USEC", str(WATCHDOG_USEC))
    monkeypatch.setenv("WATCHDOG_PID", str(os.getpid()))
    yield lis
    lis.sock.close()


async def test_ready_watchdog_status_and_stopping_from_a_simulated_flight(listener: NotifyListener) -> None:
    route = Route.point(8.0, 3.0, -5.0, source="test")
    async with flight(World.empty(), service_config(), route=route, spawn_mode="LOITER") as (svc, _sim):
        await until(lambda: len(listener.having("WATCHDOG")) >= 3, what="watchdog pets")
        msgs = listener.drain()
        ready = next(i for i, m in enumerate(msgs) if m.get("READY") == "1")
        assert ready < next(i for i, m in enumerate(msgs) if "WATCHDOG" in m)  # READY before the first pet
        await until(lambda: any(m.get("STATUS", "").startswith("NAVIGATING") for m in listener.drain()), what="status")
        assert svc.watchdog is not None and svc.watchdog.interval_s == pytest.approx(0.1)
    assert listener.drain()[-1].get("STOPPING") == "1"


async def test_a_failing_cycle_stops_the_watchdog_and_heartbeats_do_not_pet_it(listener: NotifyListener) -> None:
    route = Route.point(8.0, 3.0, -5.0, source="test")
    async with flight(World.empty(), service_config(), route=route, spawn_mode="LOITER") as (svc, _sim):
        await until(lambda: len(listener.having("WATCHDOG")) >= 2, what="watchdog pets")
        good_cycle = svc.navigator.cycle

        def stalled(now_s: float) -> None:
            raise RuntimeError("the planning cycle is broken")

        assert svc.watchdog is not None and svc.link is not None
        wd, stats = svc.watchdog, svc.link.stats
        listener.drain()
        mark, pets, errors, sent = len(listener.messages), wd.pets, svc.counters.handler_errors, stats.packets_sent
        svc.navigator.cycle = stalled  # type: ignore[assignment,method-assign]
        # 30 failed cycles (3 s of vehicle time at the 10 Hz cycle) span many watchdog half-periods: no pet in any,
        # while the status task still sends (HEARTBEAT, NAMED_VALUE_*): only the planning cycle pets.
        t_stall, half_period = wd.monotonic(), wd.interval_s or 0.0
        await until(lambda: svc.counters.handler_errors >= errors + 30, what="cycles failing")
        await until(lambda: wd.monotonic() > t_stall + 3 * half_period, what="three watchdog half-periods")
        await until(lambda: stats.packets_sent > sent + 2, what="the status task still sends")
        assert not [m for m in listener.drain()[mark:] if "WATCHDOG" in m]
        assert wd.pets == pets
        svc.navigator.cycle = good_cycle  # type: ignore[method-assign]
        await until(lambda: wd.pets > pets and any("WATCHDOG" in m for m in listener.drain()[mark:]), what="pets")
        assert svc.navigator.state is not State.IDLE


def test_watchdog_pets_at_half_the_period_on_an_injected_clock(tmp_path: Path) -> None:
    path = tmp_path / "n"
    lis = NotifyListener(path)
    t = [100.0]
    wd = Watchdog(SystemdNotifier(str(path), watchdog_usec=1_000_000), monotonic=lambda: t[0])
    try:
        for _ in range(10):  # ten cycles within 0.45 s: one pet, one STATUS
            wd.pet("NAVIGATING: new goal")
            t[0] += 0.05
        assert wd.pets == 1
        t[0] += 0.5
        wd.pet("HOLDING: pose stale")
        assert wd.pets == 2
        assert lis.drain() == [
            {"WATCHDOG": "1", "STATUS": "NAVIGATING: new goal"},
            {"WATCHDOG": "1", "STATUS": "HOLDING: pose stale"},
        ]
    finally:
        lis.sock.close()
        wd.notifier.close()


def test_from_env_only_with_notify_socket_and_watchdog_only_for_this_process() -> None:
    assert SystemdNotifier.from_env({}) is None
    n = SystemdNotifier.from_env({"NOTIFY_SOCKET": "@apf/notify", "WATCHDOG_USEC": "3000000"})
    assert n is not None and n.address == "\0apf/notify" and n.watchdog_usec == 3_000_000
    n.close()
    other = SystemdNotifier.from_env({"NOTIFY_SOCKET": "/x", "WATCHDOG_USEC": "3000000", "WATCHDOG_PID": "1"})
    assert other is not None and other.watchdog_usec is None  # pid 1 is not this test
    other.close()
    bad = SystemdNotifier.from_env({"NOTIFY_SOCKET": "/x", "WATCHDOG_USEC": "soon"})
    assert bad is not None and bad.watchdog_usec is None
    bad.close()


def test_a_missing_socket_is_counted_never_raised(tmp_path: Path) -> None:
    n = SystemdNotifier(str(tmp_path / "absent"))
    try:
        assert not n.notify(READY=1) and not n.notify(WATCHDOG=1)
        assert n.errors == 2 and n.sent == 0
    finally:
        n.close()
