"""Zenoh link: an asyncio-friendly wrapper around an eclipse-zenoh session.

zenoh-python has no asyncio API: subscriber callbacks run on zenoh-owned threads. Each subscription here
keeps a small buffer behind a lock, filled on the zenoh thread, and wakes the event loop with
``loop.call_soon_threadsafe`` at most once per batch, so a stalled loop never accumulates callbacks. The
buffer's overflow policy is chosen per subscription:

- ``Overflow.LATEST_PER_KEY`` (sensors): one sample per key, a newer one overwrites the older
  (counted in ``overwritten``); at most ``max_keys`` keys, the least recently updated key is dropped.
- ``Overflow.FIFO`` (commands): samples in arrival order, at most ``capacity``; when full the OLDEST is
  dropped (counted in ``dropped``), because a newer command (e.g. a goal) supersedes older ones.

Publishing is a non-blocking ``put`` from the loop (publishers use CongestionControl.DROP, so a slow
network never blocks the cycle). Opening and closing the session run in a worker thread.

Every session disables multicast scouting and uses only the explicit ``tcp/HOST:PORT`` (or ``tls/HOST:PORT``)
endpoints given in ``ZenohConfig``; wildcard hosts (0.0.0.0, ::) are rejected. ``config_file`` adds a zenoh JSON5
file for everything else (TLS certificates, authentication, access control; ``deploy/zenoh-*.json5`` and
docs/faults.md); it may not set the mode, the endpoints or multicast scouting, which stay ``ZenohConfig``'s.

Example::

    cfg = ZenohConfig(mode="peer", listen=("tcp/127.0.0.1:7447",))
    async with await ZenohLink.open(cfg) as link:
        sensors = await link.subscribe("apf/sensors/*/ranges", overflow=Overflow.LATEST_PER_KEY)
        sample = await sensors.recv(timeout=1.0)
        link.publish("apf/status", b"{...}", encoding="application/json")
"""

from __future__ import annotations

import asyncio
import contextlib
import ipaddress
import json
import logging
import re
import time
from collections.abc import AsyncIterator
from dataclasses import dataclass
from types import TracebackType
from typing import Self

import zenoh

from apf_companion.errors import ConfigError, LinkError, LinkTimeout
from apf_companion.links.zenoh_buffer import Overflow, SampleHandoff, SubscriptionStats, ZenohSample

__all__ = [
    "DEFAULT_GOAL_KEY",
    "DEFAULT_SENSOR_KEY",
    "DEFAULT_STATUS_KEY",
    "Overflow",
    "SampleHandoff",
    "SubscriptionStats",
    "ZenohConfig",
    "ZenohLink",
    "ZenohSample",
    "ZenohSubscription",
    "open_with_retry",
    "zenoh_error_text",
]

log = logging.getLogger(__name__)

DEFAULT_SENSOR_KEY = "apf/sensors/range0/ranges"
DEFAULT_GOAL_KEY = "apf/cmd/goal"
DEFAULT_STATUS_KEY = "apf/status"

_MODES = ("peer", "client", "router")
_ENDPOINT_RE = re.compile(r"^(?:tcp|tls)/(?P<host>\[[0-9A-Fa-f:.]+\]|[A-Za-z0-9.\-]+):(?P<port>[0-9]{1,5})$")


def _check_endpoint(endpoint: str, *, name: str, allow_port_zero: bool) -> None:
    m = _ENDPOINT_RE.match(endpoint) if isinstance(endpoint, str) else None
    if m is None:
        msg = (
            f"zenoh {name} endpoint {endpoint!r} must be explicit 'tcp/HOST:PORT' or 'tls/HOST:PORT' "
            "(e.g. 'tcp/127.0.0.1:7447')"
        )
        raise ConfigError(msg)
    host = m.group("host").strip("[]")
    try:
        wildcard = ipaddress.ip_address(host).is_unspecified
    except ValueError:
        wildcard = False
    if wildcard:
        msg = f"zenoh {name} endpoint {endpoint!r}: wildcard host; name a specific interface address"
        raise ConfigError(msg)
    port = int(m.group("port"))
    low = 0 if allow_port_zero else 1
    if not low <= port <= 65535:
        msg = f"zenoh {name} endpoint {endpoint!r}: port must be in {low}..65535"
        raise ConfigError(msg)


# zenoh's error texts end each cause with the Rust source line that raised it (" at /root/.cargo/.../x.rs:447.").
_RUST_LOCATION_RE = re.compile(r"\s+at \S+\.rs:\d+\.?")


def zenoh_error_text(err: BaseException) -> str:
    """A zenoh error's message without the Rust source locations zenoh appends to each cause."""
    return _RUST_LOCATION_RE.sub("", str(err)).strip()


# Keys a config_file may not set: ZenohConfig owns them. Values as zenoh.Config().get_json reports the defaults.
_OWNED_KEYS = ("mode", "connect/endpoints", "listen/endpoints")


def _load_config_file(path: str) -> zenoh.Config:
    """Parse a zenoh JSON5 file (zenoh itself rejects unknown keys) and check it leaves mode, endpoints and
    multicast scouting to ZenohConfig. Raises ConfigError."""
    try:
        conf = zenoh.Config.from_file(path)
    except zenoh.ZError as err:
        msg = f"zenoh config_file {path!r}: {err}"
        raise ConfigError(msg) from err
    default = zenoh.Config()
    for key in _OWNED_KEYS:
        if conf.get_json(key) != default.get_json(key):
            msg = f"zenoh config_file {path!r} sets {key!r}: give mode, connect and listen in the service config"
            raise ConfigError(msg)
    if json.loads(conf.get_json("scouting/multicast/enabled")) is True:
        msg = f"zenoh config_file {path!r} enables multicast scouting: it stays off (explicit endpoints only)"
        raise ConfigError(msg)
    return conf


@dataclass(frozen=True, slots=True, kw_only=True)
class ZenohConfig:
    """Validated zenoh session settings. Multicast scouting is always disabled.

    Attributes:
        mode: ``"peer"`` (default), ``"client"`` (needs a router in ``connect``), or ``"router"`` (a
            self-contained router for a companion without zenohd, and for tests).
        connect: Endpoints to connect to, each ``tcp/HOST:PORT`` or ``tls/HOST:PORT`` with port 1..65535.
        listen: Endpoints to listen on, each ``tcp/HOST:PORT`` or ``tls/HOST:PORT`` with port 0..65535.
        config_file: A zenoh JSON5 file with the rest (``transport/link/tls/...`` certificates, ``access_control``);
            it may not set mode, endpoints or multicast scouting. None = zenoh's defaults.
    """

    mode: str = "peer"
    connect: tuple[str, ...] = ()
    listen: tuple[str, ...] = ()
    config_file: str | None = None

    def __post_init__(self) -> None:
        if self.mode not in _MODES:
            msg = f"zenoh mode must be one of {', '.join(_MODES)}, got {self.mode!r}"
            raise ConfigError(msg)
        for name in ("connect", "listen"):
            value = getattr(self, name)
            if isinstance(value, str) or not isinstance(value, tuple | list):
                msg = f"zenoh {name} must be a list of 'tcp/HOST:PORT' strings, got {value!r}"
                raise ConfigError(msg)
            object.__setattr__(self, name, tuple(value))
        for ep in self.connect:
            _check_endpoint(ep, name="connect", allow_port_zero=False)
        for ep in self.listen:
            _check_endpoint(ep, name="listen", allow_port_zero=True)
        if self.mode == "client" and not self.connect:
            msg = "zenoh mode 'client' needs at least one connect endpoint (the router)"
            raise ConfigError(msg)
        if not self.connect and not self.listen:
            msg = "zenoh needs at least one connect or listen endpoint (multicast scouting is disabled)"
            raise ConfigError(msg)
        if self.config_file is not None:
            _load_config_file(self.config_file)

    def describe(self) -> str:
        """The settings for a message: ``mode client, connect tcp/127.0.0.1:7447`` (no Python repr)."""
        parts = [f"mode {self.mode}"]
        for name, endpoints in (("connect", self.connect), ("listen", self.listen)):
            if endpoints:
                parts.append(f"{name} {', '.join(endpoints)}")
        if self.config_file is not None:
            parts.append(f"config_file {self.config_file}")
        return ", ".join(parts)

    def to_zenoh(self) -> zenoh.Config:
        """The equivalent ``zenoh.Config`` (``config_file`` first, then mode, endpoints, scouting off)."""
        conf = zenoh.Config() if self.config_file is None else _load_config_file(self.config_file)
        conf.insert_json5("mode", json.dumps(self.mode))
        conf.insert_json5("scouting/multicast/enabled", "false")
        conf.insert_json5("connect/endpoints", json.dumps(list(self.connect)))
        conf.insert_json5("listen/endpoints", json.dumps(list(self.listen)))
        return conf


def _copy_sample(sample: zenoh.Sample, key_expr: str) -> ZenohSample | None:
    """The sample copied out of zenoh (on its thread), None (logged) if it cannot be read."""
    try:
        return ZenohSample(
            key_expr=str(sample.key_expr),
            payload=sample.payload.to_bytes(),
            encoding=str(sample.encoding),
            t_s=time.monotonic(),
        )
    except Exception:  # never let an exception escape into zenoh's thread
        log.exception("zenoh.sample_copy_failed", extra={"key_expr": key_expr})
        return None


class ZenohSubscription:
    """A bounded, thread-safe buffer between a zenoh subscriber callback and asyncio.

    Create through ``ZenohLink.subscribe``. Consume with ``await recv(timeout=...)``, ``try_recv()`` or
    ``async for sample in sub``. The samples wait in its ``SampleHandoff``; zenoh's thread only calls
    ``_on_sample``, everything else runs on the event loop.
    """

    def __init__(self, key_expr: str, loop: asyncio.AbstractEventLoop, *, overflow: Overflow, capacity: int) -> None:
        if not isinstance(capacity, int) or capacity < 1:
            msg = f"subscription capacity must be an int >= 1, got {capacity!r}"
            raise ConfigError(msg)
        self.key_expr = key_expr
        self.overflow = overflow
        self.capacity = capacity
        self._handoff = SampleHandoff(overflow, capacity)
        self.stats = self._handoff.stats
        self._loop = loop
        self._event = asyncio.Event()
        self._subscriber: zenoh.Subscriber[None] | None = None
        # Set on every wake too, so ZenohLink.samples() can wait on all subscriptions at once.
        self._link_event: asyncio.Event | None = None

    @property
    def _closed(self) -> bool:
        return self._handoff.closed

    def _on_sample(self, sample: zenoh.Sample) -> None:
        """zenoh's callback, on zenoh's thread: copy, buffer, and wake the loop once per batch."""
        item = _copy_sample(sample, self.key_expr)
        if item is not None and self._handoff.offer(item):
            # RuntimeError: the loop is closed, nobody is listening any more.
            with contextlib.suppress(RuntimeError):
                self._loop.call_soon_threadsafe(self._wake)

    def _wake(self) -> None:
        self._handoff.woken()
        self._event.set()
        if self._link_event is not None:
            self._link_event.set()

    def _pop(self) -> ZenohSample | None:
        """Next buffered sample or None; clears the wake event when empty."""
        item = self._handoff.take()
        if item is None:
            self._event.clear()  # on the loop, as the wake-up that sets it: no sample can slip in between
        return item

    def try_recv(self) -> ZenohSample | None:
        """The next buffered sample without waiting, or None."""
        return self._pop()

    def pending(self) -> int:
        """Number of buffered samples."""
        return self._handoff.pending()

    async def recv(self, timeout: float) -> ZenohSample:
        """Wait up to ``timeout`` seconds for the next sample.

        Raises LinkTimeout on the deadline and LinkError once the subscription is closed and drained.
        """
        deadline = self._loop.time() + timeout
        while True:
            item = self._pop()
            if item is not None:
                return item
            if self._closed:
                msg = f"zenoh subscription {self.key_expr!r} is closed"
                raise LinkError(msg)
            remaining = deadline - self._loop.time()
            if remaining <= 0.0:
                msg = f"no zenoh sample on {self.key_expr!r} within {timeout} s"
                raise LinkTimeout(msg)
            try:
                async with asyncio.timeout(remaining):
                    await self._event.wait()
            except TimeoutError:
                continue  # the loop top re-checks the buffer, then raises LinkTimeout

    async def __aiter__(self) -> AsyncIterator[ZenohSample]:
        """Yield samples until the subscription is closed."""
        while True:
            item = self._pop()
            if item is not None:
                yield item
                continue
            if self._closed:
                return
            await self._event.wait()

    def _close(self) -> None:
        self._handoff.close()
        self._event.set()


class ZenohLink:
    """An open zenoh session used from asyncio. Create with ``await ZenohLink.open(cfg)``."""

    def __init__(self, session: zenoh.Session, cfg: ZenohConfig, loop: asyncio.AbstractEventLoop) -> None:
        self._session = session
        self.config = cfg
        self._loop = loop
        self._subscriptions: list[ZenohSubscription] = []
        self._publishers: dict[tuple[str, str], zenoh.Publisher] = {}
        self._closed = False
        self._any_sample = asyncio.Event()
        self._rr = 0
        self.published = 0
        self.publish_errors = 0

    @classmethod
    async def open(cls, cfg: ZenohConfig, *, timeout: float = 10.0) -> Self:
        """Open a session with ``cfg`` in a worker thread. Raises LinkError if zenoh refuses it
        (e.g. a listen port in use, or no router reachable in client mode), LinkTimeout after ``timeout``."""
        loop = asyncio.get_running_loop()
        conf = cfg.to_zenoh()
        try:
            async with asyncio.timeout(timeout):
                session = await asyncio.to_thread(zenoh.open, conf)
        except TimeoutError as err:
            msg = f"zenoh session did not open within {timeout} s ({cfg.describe()})"
            raise LinkTimeout(msg) from err
        except zenoh.ZError as err:
            msg = f"zenoh session failed to open ({cfg.describe()}): {zenoh_error_text(err)}"
            raise LinkError(msg) from err
        log.info("zenoh.open", extra={"mode": cfg.mode, "connect": cfg.connect, "listen": cfg.listen})
        return cls(session, cfg, loop)

    @property
    def is_closed(self) -> bool:
        """True after ``aclose``."""
        return self._closed

    async def subscribe(
        self, key_expr: str, *, overflow: Overflow = Overflow.LATEST_PER_KEY, capacity: int = 16
    ) -> ZenohSubscription:
        """Declare a subscriber on ``key_expr`` (wildcards allowed) with the given overflow policy.

        ``capacity`` is the number of keys kept (LATEST_PER_KEY) or of samples (FIFO).
        """
        self._check_open()
        sub = ZenohSubscription(key_expr, self._loop, overflow=overflow, capacity=capacity)
        sub._link_event = self._any_sample
        try:
            sub._subscriber = await asyncio.to_thread(self._session.declare_subscriber, key_expr, sub._on_sample)
        except zenoh.ZError as err:
            msg = f"zenoh subscriber on {key_expr!r} failed: {err}"
            raise LinkError(msg) from err
        self._subscriptions.append(sub)
        return sub

    async def samples(self) -> AsyncIterator[ZenohSample]:
        """Yield samples from every subscription of this link, round-robin, until the link is closed.

        Each subscription keeps its own overflow policy; this only merges them for one consumer task.
        """
        while True:
            subs = self._subscriptions
            item = None
            for i in range(len(subs)):
                sub = subs[(self._rr + i) % len(subs)]
                item = sub.try_recv()
                if item is not None:
                    self._rr = (self._rr + i + 1) % len(subs)
                    break
            if item is not None:
                yield item
                continue
            if self._closed:
                return
            self._any_sample.clear()
            # A sample may have landed between the scan above and the clear: look again before waiting.
            if any(sub.pending() for sub in subs):
                continue
            await self._any_sample.wait()

    def publish(self, key_expr: str, payload: bytes | str, *, encoding: str = "application/json") -> None:
        """Put ``payload`` on ``key_expr`` without blocking (dropped under congestion).

        Raises LinkError when the link is closed or zenoh rejects the key or payload.
        """
        self._check_open()
        try:
            pub = self._publishers.get((key_expr, encoding))
            if pub is None:
                pub = self._session.declare_publisher(
                    key_expr,
                    encoding=encoding,
                    congestion_control=zenoh.CongestionControl.DROP,
                    express=True,
                )
                self._publishers[(key_expr, encoding)] = pub
            pub.put(payload)
        except zenoh.ZError as err:
            self.publish_errors += 1
            msg = f"zenoh publish on {key_expr!r} failed: {err}"
            raise LinkError(msg) from err
        self.published += 1

    def _check_open(self) -> None:
        if self._closed:
            msg = "zenoh link is closed"
            raise LinkError(msg)

    def _close_blocking(self) -> None:
        # zenoh's stubs leave these unannotated (they return None).
        for sub in self._subscriptions:
            if sub._subscriber is not None:
                sub._subscriber.undeclare()  # type: ignore[no-untyped-call]
        for pub in self._publishers.values():
            pub.undeclare()  # type: ignore[no-untyped-call]
        self._session.close()  # type: ignore[no-untyped-call]

    async def aclose(self, *, timeout: float = 5.0) -> None:
        """Stop every subscription and close the session in a worker thread (idempotent)."""
        if self._closed:
            return
        self._closed = True
        for sub in self._subscriptions:
            sub._close()
        self._any_sample.set()
        try:
            async with asyncio.timeout(timeout):
                await asyncio.to_thread(self._close_blocking)
        except TimeoutError:
            log.warning("zenoh.close_timeout", extra={"timeout_s": timeout})
        except zenoh.ZError as err:
            log.warning("zenoh.close_failed", extra={"error": str(err)})
        log.info("zenoh.close", extra={"published": self.published})

    async def __aenter__(self) -> Self:
        return self

    async def __aexit__(
        self, exc_type: type[BaseException] | None, exc: BaseException | None, tb: TracebackType | None
    ) -> None:
        await self.aclose()


CLIENT_RETRY_MIN_S = 0.5  # first wait after a failed client open [s]
CLIENT_RETRY_MAX_S = 5.0  # the backoff doubles up to this [s]
CLIENT_RETRY_TOTAL_S = 60.0  # give up (LinkError) after this long in all [s] (the service: zenoh.router_wait_s)
CLIENT_RETRY_WARN_S = 30.0  # a failed attempt is a WARNING at most this often (the first always), else DEBUG [s]
ROUTER_HINT = (
    "is zenohd (or another zenoh router) running and listening there (with TLS: do the certificates match)? "
    "--log-level DEBUG shows zenoh's error for each attempt"
)


async def open_with_retry(
    cfg: ZenohConfig, *, total_s: float = CLIENT_RETRY_TOTAL_S, warn_every_s: float = CLIENT_RETRY_WARN_S
) -> ZenohLink:
    """``ZenohLink.open``; in client mode a router that is not up yet (zenoh refuses at once) is retried with a
    doubling backoff (``CLIENT_RETRY_MIN_S`` .. ``CLIENT_RETRY_MAX_S``) until ``total_s`` have passed since the
    first attempt, the last one at ``total_s`` (0 = one attempt). The first failure is one WARNING
    ``zenoh.router_unreachable`` naming the router and what happens next; later ones repeat it (with the count of
    attempts) at most every ``warn_every_s``, and are DEBUG lines (``zenoh.router_retry``, with zenoh's error) in
    between. Peer and router modes are not retried (their failures are configuration errors, e.g. a listen port
    in use).

    Raises:
        LinkError: the router was not reached within ``total_s`` (one line: the router, the time, the attempts);
            in peer or router mode, the failure of the one attempt.
    """
    loop = asyncio.get_running_loop()
    router = ", ".join(cfg.connect)
    start_s = loop.time()
    warn_at_s, backoff_s, attempts = start_s, CLIENT_RETRY_MIN_S, 0
    while True:
        try:
            return await ZenohLink.open(cfg)
        except LinkError as err:
            if cfg.mode != "client":
                raise
            attempts += 1
            waited_s = loop.time() - start_s
            log.debug("zenoh.router_retry", extra={"router": router, "attempts": attempts, "error": str(err)})
            if waited_s >= total_s:
                msg = (
                    f"zenoh router at {router} unreachable: gave up after {waited_s:.1f} s and {attempts} "
                    f"attempt{'s' if attempts > 1 else ''} (zenoh.router_wait_s = {total_s:g}); {ROUTER_HINT}"
                )
                raise LinkError(msg) from err
            if loop.time() >= warn_at_s:
                warn_at_s = loop.time() + warn_every_s
                log.warning(
                    "zenoh.router_unreachable",
                    extra={
                        "router": router,
                        "attempts": attempts,
                        "waited_s": round(waited_s, 1),
                        "then": f"retrying for up to {total_s:g} s in all, then giving up (the service exits 1)",
                        "hint": ROUTER_HINT,
                    },
                )
            await asyncio.sleep(min(backoff_s, total_s - waited_s))  # the last attempt at total_s
            backoff_s = min(2.0 * backoff_s, CLIENT_RETRY_MAX_S)
