"""ZenohLink over real zenoh sessions on loopback (free ports, multicast scouting off).

Publishing uses CongestionControl.DROP (a slow network must never block the service), so a burst of puts
can legitimately lose samples when the machine is loaded. Tests that count samples therefore publish one
sample at a time and wait until it arrived (``publish_each``); every wait has a deadline that only bounds a hang.
"""

from __future__ import annotations

import asyncio
import contextlib
import json
import logging
import math
import socket
from collections.abc import AsyncIterator
from typing import Any

import numpy as np
import pytest

from apf_companion.errors import ConfigError, LinkError, LinkTimeout
from apf_companion.links.zenoh import (
    DEFAULT_GOAL_KEY,
    DEFAULT_SENSOR_KEY,
    Overflow,
    ZenohConfig,
    ZenohLink,
    ZenohSample,
    ZenohSubscription,
    open_with_retry,
    zenoh_error_text,
)
from apf_companion.perception import (
    GoalCommand,
    RangeScan,
    ScanFrame,
    decode_goal_json,
    decode_scan_payload,
    encode_goal_json,
    encode_laserscan_cdr,
    encode_scan_json,
)
from tests.conftest import HANG_S, free_port, until

# The all-interfaces address, spelled out only to check that it is refused (nothing here binds it).
ANY_IPV4 = ".".join("0" * 4)


@pytest.mark.parametrize(
    ("kwargs", "match"),
    [
        ({"mode": "router", "listen": ("tcp/127.0.0.1:7447",), "connect": ()}, None),
        ({"mode": "mesh", "listen": ("tcp/127.0.0.1:7447",)}, "mode"),
        ({"listen": ("udp/127.0.0.1:7447",)}, "tcp/HOST:PORT"),
        ({"listen": (f"tcp/{ANY_IPV4}:7447",)}, "wildcard"),
        ({"connect": ("tcp/[::]:7447",)}, "wildcard"),
        ({"connect": ("tcp/127.0.0.1:0",)}, "port"),
        ({"listen": ("tcp/127.0.0.1:70000",)}, "port"),
        ({"listen": ("tcp/127.0.0.1",)}, "tcp/HOST:PORT"),
        ({"listen": "tcp/127.0.0.1:7447"}, "list"),
        ({"mode": "client", "listen": ("tcp/127.0.0.1:7447",)}, "client"),
        ({"mode": "peer"}, "at least one"),
    ],
)
def test_config_validation(kwargs: dict[str, object], match: str | None) -> None:
    if match is None:
        ZenohConfig(**kwargs)  # type: ignore[arg-type]
        return
    with pytest.raises(ConfigError, match=match):
        ZenohConfig(**kwargs)  # type: ignore[arg-type]


def test_config_always_disables_multicast() -> None:
    cfg = ZenohConfig(mode="peer", listen=["tcp/127.0.0.1:7447"], connect=["tcp/localhost:7448"])  # type: ignore[arg-type]
    assert cfg.listen == ("tcp/127.0.0.1:7447",)
    conf = cfg.to_zenoh()
    assert json.loads(conf.get_json("scouting/multicast/enabled")) is False
    assert json.loads(conf.get_json("connect/endpoints")) == ["tcp/localhost:7448"]
    assert json.loads(conf.get_json("mode")) == "peer"


@pytest.fixture
async def pair() -> AsyncIterator[tuple[ZenohLink, ZenohLink]]:
    """Two peers: ``a`` listens, ``b`` connects to it."""
    port = free_port()
    a = await ZenohLink.open(ZenohConfig(mode="peer", listen=(f"tcp/127.0.0.1:{port}",)))
    b = await ZenohLink.open(ZenohConfig(mode="peer", connect=(f"tcp/127.0.0.1:{port}",)))
    try:
        yield a, b
    finally:
        await b.aclose()
        await a.aclose()


async def _publish_until_received(
    pub: ZenohLink, sub: ZenohSubscription, key: str, payload: bytes, encoding: str
) -> ZenohSample:
    """Publish every 20 ms until the subscriber sees a sample (the peers may still be connecting)."""
    try:
        async with asyncio.timeout(HANG_S):
            while True:
                pub.publish(key, payload, encoding=encoding)
                with contextlib.suppress(LinkTimeout):
                    return await sub.recv(timeout=0.02)
    except TimeoutError:
        msg = f"no sample within {HANG_S} s"
        raise AssertionError(msg) from None


async def _subscriptions_known(sub_side: ZenohLink, pub_side: ZenohLink) -> None:
    """Return once ``pub_side`` knows every subscription ``sub_side`` declared so far.

    A probe subscription is declared last and probed until a sample arrives; declarations travel in order, so
    the earlier ones have arrived too. Probing on the subscription under test instead would leave retried
    warm-up samples in flight that land in it later and upset its counts.
    """
    probe = await sub_side.subscribe("apf/probe/ready")
    await _publish_until_received(pub_side, probe, "apf/probe/ready", b"?", "text/plain")


async def publish_each(pub: ZenohLink, sub: ZenohSubscription, items: list[tuple[str, bytes]]) -> None:
    """Publish ``(key, payload)`` one at a time, each once ``sub`` has received the previous one.

    One put on an idle session is never dropped, so the subscriber sees exactly these samples, in order,
    however loaded the machine is (a burst could lose some to CongestionControl.DROP).
    """
    for key, payload in items:
        before = sub.stats.received
        pub.publish(key, payload, encoding="text/plain")
        await until(lambda: sub.stats.received > before, HANG_S, f"sample {key}={payload!r} received")  # noqa: B023


async def test_pub_sub_round_trip(pair: tuple[ZenohLink, ZenohLink]) -> None:
    a, b = pair
    sub = await a.subscribe("apf/test/**")
    sample = await _publish_until_received(b, sub, "apf/test/x", b"hello", "text/plain")
    assert sample.key_expr == "apf/test/x"
    assert sample.payload == b"hello"
    assert sample.encoding.startswith("text/plain")
    assert sample.t_s > 0.0
    assert b.published >= 1


async def test_recv_timeout(pair: tuple[ZenohLink, ZenohLink]) -> None:
    a, _ = pair
    sub = await a.subscribe("apf/nothing/here")
    with pytest.raises(LinkTimeout):
        await sub.recv(timeout=0.05)
    assert sub.try_recv() is None


async def test_latest_wins_per_key(pair: tuple[ZenohLink, ZenohLink]) -> None:
    a, b = pair
    sub = await a.subscribe("apf/sensors/*/ranges", overflow=Overflow.LATEST_PER_KEY, capacity=4)
    await _subscriptions_known(a, b)
    items = [
        (f"apf/sensors/{side}/ranges", f"{side[0].upper()}{i}".encode())
        for i in range(50)
        for side in ("left", "right")
    ]
    await publish_each(b, sub, items)
    # Without consuming, only the newest sample of each key is kept.
    assert sub.pending() == 2
    assert sub.stats.overwritten == 98
    got = {s.key_expr: s.payload for s in (await sub.recv(timeout=HANG_S), await sub.recv(timeout=HANG_S))}
    assert got == {"apf/sensors/left/ranges": b"L49", "apf/sensors/right/ranges": b"R49"}
    assert sub.try_recv() is None


async def test_latest_wins_key_bound(pair: tuple[ZenohLink, ZenohLink]) -> None:
    a, b = pair
    sub = await a.subscribe("apf/k/*", overflow=Overflow.LATEST_PER_KEY, capacity=3)
    await _subscriptions_known(a, b)
    await publish_each(b, sub, [(f"apf/k/{i}", b"x") for i in range(6)])
    assert sub.pending() == 3
    assert sub.stats.dropped == 3
    keys = [sub.try_recv() for _ in range(3)]
    assert [k.key_expr for k in keys if k is not None] == ["apf/k/3", "apf/k/4", "apf/k/5"]


async def test_fifo_keeps_order_and_drops_oldest(pair: tuple[ZenohLink, ZenohLink]) -> None:
    a, b = pair
    sub = await a.subscribe(DEFAULT_GOAL_KEY, overflow=Overflow.FIFO, capacity=5)
    await _subscriptions_known(a, b)
    await publish_each(b, sub, [(DEFAULT_GOAL_KEY, str(i).encode()) for i in range(20)])
    assert sub.stats.dropped == 15
    out = [(await sub.recv(timeout=HANG_S)).payload for _ in range(5)]
    assert out == [b"15", b"16", b"17", b"18", b"19"]


async def test_sensor_json_and_cdr_and_goal_end_to_end(pair: tuple[ZenohLink, ZenohLink]) -> None:
    a, b = pair
    scan = RangeScan(
        t_s=0.0,
        frame=ScanFrame.BODY_FRD,
        bearings_rad=np.deg2rad(np.arange(-90.0, 91.0, 5.0)),
        ranges_m=np.where(np.arange(37) % 3 == 0, math.inf, 4.0),
        range_min_m=0.2,
        range_max_m=10.0,
        time_boot_ms=77,
    )
    sensors = await a.subscribe(DEFAULT_SENSOR_KEY)
    s_json = await _publish_until_received(b, sensors, DEFAULT_SENSOR_KEY, encode_scan_json(scan), "application/json")
    got = decode_scan_payload(s_json.payload, s_json.encoding, t_s=s_json.t_s)
    np.testing.assert_array_equal(got.ranges_m, scan.ranges_m)
    assert got.time_boot_ms == 77
    s_cdr = await _publish_until_received(b, sensors, DEFAULT_SENSOR_KEY, encode_laserscan_cdr(scan), "application/cdr")
    got = decode_scan_payload(s_cdr.payload, s_cdr.encoding, t_s=s_cdr.t_s)
    np.testing.assert_array_equal(got.ranges_m, scan.ranges_m)
    np.testing.assert_allclose(got.bearings_rad, scan.bearings_rad, atol=1e-6)

    goals = await a.subscribe(DEFAULT_GOAL_KEY, overflow=Overflow.FIFO)
    goal = GoalCommand(pos_ned_m=np.array([22.0, 22.0, -5.0]))
    s_goal = await _publish_until_received(b, goals, DEFAULT_GOAL_KEY, encode_goal_json(goal), "application/json")
    assert decode_goal_json(s_goal.payload) == goal


async def test_close_behaviour(pair: tuple[ZenohLink, ZenohLink]) -> None:
    a, b = pair
    sub = await a.subscribe("apf/close/test")
    waiting = asyncio.Event()

    async def consume() -> ZenohSample:
        waiting.set()  # recv runs on without a pause until it waits for a sample
        return await sub.recv(timeout=HANG_S)

    consumer = asyncio.create_task(consume())
    await waiting.wait()  # resumed only once the consumer has paused: inside recv, waiting
    await a.aclose()
    with pytest.raises(LinkError, match="closed"):
        await consumer
    assert a.is_closed
    await a.aclose()  # idempotent
    with pytest.raises(LinkError, match="closed"):
        a.publish("apf/x", b"x")
    with pytest.raises(LinkError, match="closed"):
        await a.subscribe("apf/x")
    # The other side keeps working after its peer went away.
    b.publish("apf/close/test", b"still fine")


async def test_async_iteration_ends_on_close(pair: tuple[ZenohLink, ZenohLink]) -> None:
    a, b = pair
    sub = await a.subscribe("apf/iter", overflow=Overflow.FIFO)
    first = await _publish_until_received(b, sub, "apf/iter", b"0", "text/plain")
    assert first.payload == b"0"

    async def collect() -> list[bytes]:
        return [s.payload async for s in sub]

    task = asyncio.create_task(collect())
    await publish_each(b, sub, [("apf/iter", b"1")])
    await a.aclose()
    items = await asyncio.wait_for(task, timeout=HANG_S)
    assert b"1" in items


async def test_client_mode_through_router() -> None:
    port = free_port()
    router = await ZenohLink.open(ZenohConfig(mode="router", listen=(f"tcp/127.0.0.1:{port}",)))
    c1 = await ZenohLink.open(ZenohConfig(mode="client", connect=(f"tcp/127.0.0.1:{port}",)))
    c2 = await ZenohLink.open(ZenohConfig(mode="client", connect=(f"tcp/127.0.0.1:{port}",)))
    try:
        sub = await c1.subscribe("apf/status")
        sample = await _publish_until_received(c2, sub, "apf/status", b'{"state":"IDLE"}', "application/json")
        assert json.loads(sample.payload) == {"state": "IDLE"}
    finally:
        await c2.aclose()
        await c1.aclose()
        await router.aclose()


async def test_listen_port_in_use_is_a_link_error() -> None:
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        s.bind(("127.0.0.1", 0))
        s.listen(1)
        port = s.getsockname()[1]
        with pytest.raises(LinkError):
            link = await ZenohLink.open(ZenohConfig(mode="peer", listen=(f"tcp/127.0.0.1:{port}",)), timeout=5.0)
            await link.aclose()


async def test_bad_key_is_a_link_error(pair: tuple[ZenohLink, ZenohLink]) -> None:
    a, _ = pair
    with pytest.raises(LinkError):
        await a.subscribe("apf//bad")
    with pytest.raises(LinkError):
        a.publish("apf//bad", b"x")
    assert a.publish_errors == 1


async def test_link_samples_merges_subscriptions(pair: tuple[ZenohLink, ZenohLink]) -> None:
    a, b = pair
    sensors = await a.subscribe(DEFAULT_SENSOR_KEY)
    goals = await a.subscribe(DEFAULT_GOAL_KEY, overflow=Overflow.FIFO)
    await _publish_until_received(b, sensors, DEFAULT_SENSOR_KEY, b"warm", "application/json")
    await _publish_until_received(b, goals, DEFAULT_GOAL_KEY, b"warm", "application/json")
    while sensors.try_recv() or goals.try_recv():
        pass

    waiting = asyncio.Event()

    async def collect(n: int) -> list[tuple[str, bytes]]:
        out: list[tuple[str, bytes]] = []
        waiting.set()  # samples() runs on without a pause until it waits for a sample
        async for s in a.samples():
            out.append((s.key_expr, s.payload))
            if len(out) == n:
                break
        return out

    task = asyncio.create_task(collect(3))
    await publish_each(b, goals, [(DEFAULT_GOAL_KEY, b"g1"), (DEFAULT_GOAL_KEY, b"g2")])
    await publish_each(b, sensors, [(DEFAULT_SENSOR_KEY, b"s1")])
    got = await asyncio.wait_for(task, timeout=HANG_S)
    assert sorted(got) == [(DEFAULT_GOAL_KEY, b"g1"), (DEFAULT_GOAL_KEY, b"g2"), (DEFAULT_SENSOR_KEY, b"s1")]
    # FIFO order within the goal subscription is kept.
    assert [p for k, p in got if k == DEFAULT_GOAL_KEY] == [b"g1", b"g2"]

    waiting.clear()
    ended = asyncio.create_task(collect(100))
    await waiting.wait()  # resumed only once collect has paused: waiting for a sample
    await a.aclose()
    assert await asyncio.wait_for(ended, timeout=HANG_S) == []


async def _refuse_one_connect(port: int) -> None:
    """Accept one TCP connection on 127.0.0.1:``port`` and hang up: proof that a peer tried it and failed."""
    loop = asyncio.get_running_loop()
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as srv:
        srv.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        srv.bind(("127.0.0.1", port))
        srv.listen(1)
        srv.setblocking(False)
        async with asyncio.timeout(HANG_S):
            conn, _ = await loop.sock_accept(srv)
        conn.close()


async def test_peer_connects_to_a_late_listener() -> None:
    # The service may start before the sensor bridge: a peer keeps retrying its connect endpoint.
    port = free_port()
    early = await ZenohLink.open(ZenohConfig(mode="peer", connect=(f"tcp/127.0.0.1:{port}",)))
    late: ZenohLink | None = None
    try:
        sub = await early.subscribe(DEFAULT_SENSOR_KEY)
        await _refuse_one_connect(port)  # the early peer's connect attempt fails: the case under test
        late = await ZenohLink.open(ZenohConfig(mode="peer", listen=(f"tcp/127.0.0.1:{port}",)))
        sample = await _publish_until_received(late, sub, DEFAULT_SENSOR_KEY, b"late", "text/plain")
        assert sample.payload == b"late"
    finally:
        if late is not None:
            await late.aclose()
        await early.aclose()


def _no_internals(text: str) -> None:
    """No Python repr of the config, no Rust source location from zenoh's error chain."""
    assert "ZenohConfig(" not in text and ".rs:" not in text and ".cargo" not in text, text


def test_zenoh_error_text_drops_the_rust_source_locations() -> None:
    raw = (
        "Can not create a new TCP link bound to tcp/127.0.0.1:9: [127.0.0.1:9: Connection refused (os error 111) "
        "at /root/.cargo/git/checkouts/zenoh-9c599d5ef3e0480e/cc83980/io/zenoh-link-commons/src/tcp.rs:105.] at "
        "/root/.cargo/git/checkouts/zenoh-9c599d5ef3e0480e/cc83980/io/zenoh-link-commons/src/tcp.rs:133."
    )
    assert zenoh_error_text(ValueError(raw)) == (
        "Can not create a new TCP link bound to tcp/127.0.0.1:9: [127.0.0.1:9: Connection refused (os error 111)]"
    )


async def test_client_without_router_fails_at_open() -> None:
    port = free_port()
    with pytest.raises(LinkError, match="failed to open") as err:
        await ZenohLink.open(ZenohConfig(mode="client", connect=(f"tcp/127.0.0.1:{port}",)), timeout=HANG_S)
    assert f"(mode client, connect tcp/127.0.0.1:{port}): " in str(err.value)
    _no_internals(str(err.value))


async def test_client_retries_a_router_that_is_not_up_yet(caplog: pytest.LogCaptureFixture) -> None:
    """zenoh refuses a client at once when no router listens; the service's open retries with backoff."""
    port = free_port()
    endpoint = f"tcp/127.0.0.1:{port}"
    task = asyncio.create_task(open_with_retry(ZenohConfig(mode="client", connect=(endpoint,))))
    router = None
    try:
        await until(lambda: any(r.getMessage() == "zenoh.router_unreachable" for r in caplog.records), HANG_S, "1st")
        assert not task.done()
        router = await ZenohLink.open(ZenohConfig(mode="router", listen=(endpoint,)))
        async with asyncio.timeout(HANG_S):
            client = await task
        await client.aclose()
    finally:
        task.cancel()
        if router is not None:
            await router.aclose()
    warning = next(r for r in caplog.records if r.getMessage() == "zenoh.router_unreachable")
    assert warning.levelname == "WARNING" and warning.router == endpoint  # type: ignore[attr-defined]


async def test_client_retry_is_bounded() -> None:
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    cfg = ZenohConfig(mode="client", connect=(endpoint,))
    with pytest.raises(LinkError) as err:
        await open_with_retry(cfg, total_s=1.0)  # at 0, 0.5 and 1.0 s (the last wait cut to the bound)
    assert str(err.value).startswith(f"zenoh router at {endpoint} unreachable: gave up after 1.")
    assert "3 attempts (zenoh.router_wait_s = 1); is zenohd" in str(err.value)
    _no_internals(str(err.value))


def _record_text(record: logging.LogRecord) -> str:
    return " ".join([record.getMessage(), *(str(v) for v in vars(record).values())])


async def test_an_unreachable_router_is_one_clear_warning_not_one_per_attempt(
    caplog: pytest.LogCaptureFixture,
) -> None:
    """The bug: every attempt (14 in 60 s) was a WARNING carrying the config's Python repr and zenoh's Rust
    source paths. Now: one WARNING naming the router and what happens next, the attempts at DEBUG, one error."""
    caplog.set_level(logging.DEBUG, logger="apf_companion.links.zenoh")
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    with pytest.raises(LinkError) as err:
        await open_with_retry(ZenohConfig(mode="client", connect=(endpoint,)), total_s=1.5)
    ours = [r for r in caplog.records if r.name == "apf_companion.links.zenoh"]
    warnings = [r for r in ours if r.levelno >= logging.WARNING]
    assert [w.getMessage() for w in warnings] == ["zenoh.router_unreachable"]
    warning: Any = warnings[0]
    assert warning.router == endpoint and warning.attempts == 1 and "up to 1.5 s" in warning.then
    retries = [r for r in ours if r.getMessage() == "zenoh.router_retry"]
    assert len(retries) >= 3 and f"and {len(retries)} attempts" in str(err.value)  # at 0, 0.5, 1.5 s at least
    for text in [str(err.value), *(_record_text(r) for r in caplog.records)]:
        _no_internals(text)


async def test_the_warning_repeats_with_the_count_of_attempts(caplog: pytest.LogCaptureFixture) -> None:
    """Rate-limited, not silenced: at most once per ``warn_every_s`` (here 0: every attempt), with the count."""
    cfg = ZenohConfig(mode="client", connect=(f"tcp/127.0.0.1:{free_port()}",))
    with pytest.raises(LinkError):
        await open_with_retry(cfg, total_s=1.0, warn_every_s=0.0)  # at 0, 0.5 and 1.0 s
    warnings: list[Any] = [r for r in caplog.records if r.getMessage() == "zenoh.router_unreachable"]
    assert [w.attempts for w in warnings] == [1, 2]  # the attempt at the bound ends it: an error, not a warning
    with pytest.raises(LinkError):
        await open_with_retry(cfg, total_s=0.0)  # one attempt
