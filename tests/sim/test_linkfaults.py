"""The fault-injection proxy: spec parsing, the seeded fate model, and the proxy over real loopback UDP."""

from __future__ import annotations

import asyncio
import itertools
import struct
from collections.abc import Callable

import numpy as np
import pytest

from apf_companion.errors import ConfigError
from sim.linkfaults import Blackout, Direction, FaultModel, LinkFaults, LinkProxy
from tests.conftest import HANG_S, until

pytestmark = pytest.mark.timeout(60)

ISSUE_SPEC = "loss=0.3,jitter=0.1,dup=0.05,reorder=0.05,blackout=2@40%"


# ---- spec -----------------------------------------------------------------------------------------------------
def test_parse_issue_spec() -> None:
    f = LinkFaults.parse(ISSUE_SPEC)
    assert f == LinkFaults(
        loss=0.3, jitter_s=0.1, dup=0.05, reorder=0.05, blackouts=(Blackout(2.0, 0.4, relative=True),)
    )
    assert LinkFaults.parse(str(f)) == f


@pytest.mark.parametrize(
    ("spec", "expected"),
    [
        ("", LinkFaults()),
        ("none", LinkFaults()),
        ("loss=30%", LinkFaults(loss=0.3)),
        ("jitter=100ms, delay=0.02s", LinkFaults(jitter_s=0.1, delay_s=0.02)),
        (
            "blackout=2@30s,blackout=500ms@10",
            LinkFaults(blackouts=(Blackout(2.0, 30.0, False), Blackout(0.5, 10.0, False))),
        ),
        ("loss=1", LinkFaults(loss=1.0)),
    ],
)
def test_parse_good_specs(spec: str, expected: LinkFaults) -> None:
    assert LinkFaults.parse(spec) == expected


@pytest.mark.parametrize(
    ("spec", "fragment"),
    [
        ("los=0.3", "did you mean 'loss'"),
        ("loss=0.3,jiter=0.1", "did you mean 'jitter'"),
        ("loss", "KEY=VALUE"),
        ("loss=", "KEY=VALUE"),
        ("loss=1.5", "[0, 1]"),
        ("loss=150%", "[0, 1]"),
        ("loss=-0.1", "probability"),
        ("loss=nan", "probability"),
        ("loss=0.1,loss=0.2", "given twice"),
        ("jitter=inf", "seconds"),
        ("jitter=20", "at most"),
        ("jitter=0.1min", "seconds"),
        ("blackout=2", "DURATION@START"),
        ("blackout=0@40%", "> 0"),
        ("blackout=2@140%", "[0, 1]"),
        ("blackout=2@soon", "START"),
        ("blackout=2@1e9", "START"),
        ("loss=0.3;jitter=0.1", "probability"),
    ],
)
def test_parse_bad_specs(spec: str, fragment: str) -> None:
    with pytest.raises(ConfigError, match="link fault") as info:
        LinkFaults.parse(spec)
    assert fragment in str(info.value)


def test_blackout_windows() -> None:
    rel = Blackout(2.0, 0.4, relative=True)
    assert rel.window(opened_s=0.0, flight_start_s=None, expected_flight_s=None) is None
    assert rel.window(opened_s=0.0, flight_start_s=10.0, expected_flight_s=50.0) == (30.0, 32.0)
    assert Blackout(1.0, 5.0, relative=False).window(opened_s=0.0, flight_start_s=None, expected_flight_s=None) == (
        5.0,
        6.0,
    )


# ---- fate model ---------------------------------------------------------------------------------------------
def test_fault_model_rates_and_determinism() -> None:
    faults = LinkFaults(loss=0.3, jitter_s=0.1, dup=0.05, reorder=0.05)
    model = FaultModel(faults, np.random.default_rng(3))
    fates = [model.next() for _ in range(20_000)]
    again = FaultModel(faults, np.random.default_rng(3))
    assert fates == [again.next() for _ in range(20_000)]
    assert np.mean([f.drop for f in fates]) == pytest.approx(0.3, abs=0.015)
    assert np.mean([f.duplicate for f in fates]) == pytest.approx(0.05, abs=0.006)
    assert np.mean([f.reorder for f in fates]) == pytest.approx(0.05, abs=0.006)
    delays = np.array([f.delay_s for f in fates])
    assert delays.min() >= 0.0
    assert delays.max() <= 0.1
    assert delays.mean() == pytest.approx(0.05, abs=0.003)


def test_no_faults_model_passes_everything() -> None:
    model = FaultModel(LinkFaults(), np.random.default_rng(0))
    for _ in range(1000):
        fate = model.next()
        assert not (fate.drop or fate.duplicate or fate.reorder)
        assert fate.delay_s == 0.0


# ---- proxy over real loopback UDP ---------------------------------------------------------------------------
class _Sink(asyncio.DatagramProtocol):
    def __init__(self) -> None:
        self.got: list[tuple[bytes, tuple[str, int]]] = []
        self.event = asyncio.Event()
        self.transport: asyncio.DatagramTransport | None = None

    def connection_made(self, transport: asyncio.BaseTransport) -> None:
        assert isinstance(transport, asyncio.DatagramTransport)
        self.transport = transport

    def datagram_received(self, data: bytes, addr: tuple[str, int]) -> None:
        self.got.append((data, addr))
        self.event.set()

    def ids(self) -> list[int]:
        return [struct.unpack("!I", d[:4])[0] for d, _ in self.got]


async def _endpoint() -> tuple[asyncio.DatagramTransport, _Sink]:
    loop = asyncio.get_running_loop()
    transport, sink = await loop.create_datagram_endpoint(_Sink, local_addr=("127.0.0.1", 0))
    return transport, sink


async def _wait_for(cond: Callable[[], object]) -> None:
    await until(cond, HANG_S, "the proxy settled")


async def _pump(
    faults: LinkFaults, *, n: int, seed: int, reorder_hold_s: float = 0.2
) -> tuple[LinkProxy, list[int], list[int]]:
    """Send n numbered datagrams each way through a proxy; returns the proxy and the ids that arrived at the
    companion and at the vehicle, once every datagram has been sent or dropped."""
    companion_t, companion = await _endpoint()
    vehicle_t, vehicle = await _endpoint()
    proxy = await LinkProxy.open(
        faults, companion_port=companion_t.get_extra_info("sockname")[1], seed=seed, reorder_hold_s=reorder_hold_s
    )
    try:
        target = ("127.0.0.1", proxy.vehicle_port)
        vehicle_t.sendto(struct.pack("!I", 0) + b"hello", target)  # the proxy learns the vehicle's address
        await _wait_for(lambda: proxy.stats[Direction.TO_COMPANION].received == 1)
        for i in range(1, n):
            vehicle_t.sendto(struct.pack("!I", i) + b"up", target)
            companion_t.sendto(struct.pack("!I", i) + b"down", ("127.0.0.1", proxy.companion_side_port))
            await asyncio.sleep(0)  # one loop turn per datagram: loopback socket buffers never overflow

        def settled() -> bool:
            s_up, s_down = proxy.stats[Direction.TO_COMPANION], proxy.stats[Direction.TO_VEHICLE]
            return (
                s_up.received == n
                and s_down.received == n - 1
                and proxy.pending() == 0
                and len(companion.got) == s_up.delivered
                and len(vehicle.got) == s_down.delivered
            )

        await _wait_for(settled)
        return proxy, companion.ids(), vehicle.ids()
    finally:
        await proxy.aclose()
        companion_t.close()
        vehicle_t.close()


async def test_proxy_without_faults_forwards_both_ways_in_order() -> None:
    proxy, up, down = await _pump(LinkFaults(), n=300, seed=0)
    assert up == list(range(300))
    assert down == list(range(1, 300))
    assert proxy.stats[Direction.TO_VEHICLE].dropped == 0


async def test_proxy_loss_rate_over_loopback() -> None:
    n = 3000
    proxy, up, down = await _pump(LinkFaults(loss=0.3), n=n, seed=11)
    for ids, direction in ((up, Direction.TO_COMPANION), (down, Direction.TO_VEHICLE)):
        stats = proxy.stats[direction]
        assert len(ids) == stats.delivered == stats.received - stats.dropped
        assert len(ids) / stats.received == pytest.approx(0.7, abs=0.035)  # 4 sigma at n = 3000
        assert ids == sorted(ids)  # loss alone never reorders
        assert len(set(ids)) == len(ids)
    # Independent generators per direction: the two directions lose different datagrams.
    assert set(up[1:]) != set(down)


async def test_proxy_duplicates_and_reorders() -> None:
    proxy, up, _ = await _pump(LinkFaults(dup=0.1, reorder=0.1), n=1000, seed=5, reorder_hold_s=5.0)
    stats = proxy.stats[Direction.TO_COMPANION]
    assert stats.duplicated > 50
    assert stats.reordered > 50
    assert len(up) == 1000 + stats.duplicated
    assert set(up) == set(range(1000))
    assert sum(1 for a, b in itertools.pairwise(up) if b < a) == stats.reordered
    assert sum(1 for a, b in itertools.pairwise(up) if b == a) >= stats.duplicated - stats.reordered


async def test_proxy_jitter_delays_in_order() -> None:
    # 50 ms of wall-clock jitter at time_scale 1, order kept.
    proxy, up, _ = await _pump(LinkFaults(jitter_s=0.05), n=200, seed=2)
    assert up == list(range(200))
    assert 0.0 < proxy.stats[Direction.TO_COMPANION].max_delay_s <= 0.05 + 1e-6


async def test_proxy_is_deterministic_for_a_seed() -> None:
    faults = LinkFaults(loss=0.3, dup=0.05, reorder=0.05, jitter_s=0.002)
    first = await _pump(faults, n=800, seed=42, reorder_hold_s=5.0)
    second = await _pump(faults, n=800, seed=42, reorder_hold_s=5.0)
    other = await _pump(faults, n=800, seed=43, reorder_hold_s=5.0)
    assert first[1] == second[1]
    assert first[2] == second[2]
    assert first[1] != other[1]


async def test_blackout_drops_everything_in_its_window() -> None:
    """On the test's own clock: each datagram is sent at a known proxy time and settled before time moves on, so
    exactly the ones inside the window are lost, however slow the machine."""
    companion_t, companion = await _endpoint()
    vehicle_t, _ = await _endpoint()
    now_s = 0.0
    proxy = await LinkProxy.open(
        LinkFaults.parse("blackout=2@50%"),
        companion_port=companion_t.get_extra_info("sockname")[1],
        seed=0,
        clock=lambda: now_s,
    )
    try:
        target = ("127.0.0.1", proxy.vehicle_port)
        proxy.start_flight(1.0)
        t0, t1 = proxy.blackout_windows()[0]
        assert (t0, t1) == pytest.approx((0.5, 2.5))
        stats = proxy.stats[Direction.TO_COMPANION]

        def settled(n: int) -> Callable[[], bool]:
            return lambda: stats.received == n and proxy.pending() == 0

        sent: list[tuple[int, float]] = []
        for i in range(70):
            now_s = 0.05 * i  # 0 .. 3.45 s: before, in and after the window
            sent.append((i, now_s))
            vehicle_t.sendto(struct.pack("!I", i), target)
            await _wait_for(settled(i + 1))
        await _wait_for(lambda: len(companion.got) == stats.delivered)
        got = set(companion.ids())
        inside = {k for k, t in sent if t0 <= t < t1}
        assert inside and stats.blackout_dropped == len(inside)
        assert got == {k for k, _ in sent} - inside
    finally:
        await proxy.aclose()
        companion_t.close()
        vehicle_t.close()


async def test_proxy_counts_a_companion_not_listening() -> None:
    # Nobody listens on the companion port (yet): the datagram is counted, nothing raises.
    companion_t, _ = await _endpoint()
    port = companion_t.get_extra_info("sockname")[1]
    companion_t.close()
    vehicle_t, _ = await _endpoint()
    proxy = await LinkProxy.open(LinkFaults(), companion_port=port, seed=0)
    try:

        def received(n: int) -> Callable[[], bool]:
            return lambda: proxy.stats[Direction.TO_COMPANION].received == n

        for k in range(5):  # one at a time: each is received before the next is sent
            vehicle_t.sendto(b"x" * 10, ("127.0.0.1", proxy.vehicle_port))
            await _wait_for(received(k + 1))
        stats = proxy.stats[Direction.TO_COMPANION]
        # Each one sent into the void (or refused with an ICMP error, counted); none raised.
        await _wait_for(lambda: stats.delivered + stats.send_errors >= 5 and proxy.pending() == 0)
    finally:
        await proxy.aclose()
        vehicle_t.close()


def test_bad_time_scale() -> None:
    async def go() -> None:
        await LinkProxy.open(LinkFaults(), companion_port=1, time_scale=0.0)

    with pytest.raises(ConfigError, match="time_scale"):
        asyncio.run(go())
