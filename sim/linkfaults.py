"""A seeded fault-injection proxy for a UDP MAVLink link (``apf-sim fly --link-faults SPEC``).

The proxy sits between the simulated vehicle and the companion, both on 127.0.0.1::

    vehicle --udpout--> [proxy.vehicle_port | proxy] --> companion's udpin port
    vehicle <---------- [proxy            | proxy] <-- companion replies to the proxy's second socket

Every datagram, in each direction, meets the faults of a ``LinkFaults`` spec (``FaultModel``, one seeded
``numpy.random.Generator`` per direction, a fixed number of draws per datagram, so a seed replays the same fates):

1. blackout: inside a blackout window everything is dropped, on arrival and again on delivery (a datagram queued
   before the window but due inside it is dropped too);
2. loss: dropped with probability ``loss``;
3. delay: ``delay + U(0, jitter)`` seconds, order-preserving (a datagram never overtakes the one before it:
   jitter alone stretches the stream, it does not reorder it);
4. duplicate: with probability ``dup`` a second copy follows the first;
5. reorder: with probability ``reorder`` the datagram is held back and sent right after the next one in its
   direction (a swap), or after ``reorder_hold_s`` when no next one comes.

Times are vehicle seconds: with ``time_scale`` N (the simulator's speed-up) a 0.1 s jitter is 0.1 / N s of wall
time, so the faults mean the same to the vehicle and to the service's scaled clock as on a real link.

Blackout windows are ``DURATION@START``: ``2@40%`` starts at 40 % of the expected flight, measured from
``start_flight(expected_flight_s)`` (apf-sim fly calls it when the takeoff is done); ``2@30s`` (or ``2@30``)
starts 30 s after the proxy opened. A relative blackout never fires without ``start_flight``.
"""

from __future__ import annotations

import asyncio
import contextlib
import dataclasses
import difflib
import enum
import math
import re
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np

from apf_companion.errors import ConfigError

__all__ = [
    "Blackout",
    "Direction",
    "DirectionStats",
    "Fate",
    "FaultModel",
    "LinkFaults",
    "LinkProxy",
]

_PROBABILITIES = ("loss", "dup", "reorder")
_DURATIONS = ("delay", "jitter")
_KEYS = (*_PROBABILITIES, *_DURATIONS, "blackout")
_MAX_DELAY_S = 10.0
_MAX_START_S = 86400.0
_NUMBER = r"[0-9]+(?:\.[0-9]*)?|\.[0-9]+"
_DURATION_RE = re.compile(rf"^(?P<v>{_NUMBER})(?P<unit>ms|s)?$")
_PROBABILITY_RE = re.compile(rf"^(?P<v>{_NUMBER})(?P<pct>%)?$")


def _fail(item: str, what: str) -> ConfigError:
    return ConfigError(f"link fault {item!r}: {what}")


def _probability(key: str, text: str) -> float:
    m = _PROBABILITY_RE.match(text)
    if m is None:
        raise _fail(f"{key}={text}", "expected a probability like 0.3 or 30%")
    value = float(m.group("v")) / (100.0 if m.group("pct") else 1.0)
    if not 0.0 <= value <= 1.0:
        raise _fail(f"{key}={text}", "probability must be in [0, 1] (0 %..100 %)")
    return value


def _duration(key: str, text: str) -> float:
    m = _DURATION_RE.match(text)
    if m is None:
        raise _fail(f"{key}={text}", "expected seconds like 0.1, 0.1s or 100ms")
    value = float(m.group("v")) / (1000.0 if m.group("unit") == "ms" else 1.0)
    if not value <= _MAX_DELAY_S:
        raise _fail(f"{key}={text}", f"at most {_MAX_DELAY_S} s")
    return value


@dataclass(frozen=True, slots=True)
class Blackout:
    """One window in which the link carries nothing, both directions.

    Attributes:
        duration_s: Length of the window [vehicle s], > 0.
        start: Seconds after the proxy opened, or (``relative``) a fraction of the expected flight in [0, 1].
        relative: ``start`` is a fraction of the expected flight (``2@40%``), not an absolute time (``2@30s``).
    """

    duration_s: float
    start: float
    relative: bool

    @classmethod
    def parse(cls, text: str) -> Blackout:
        dur, sep, at = text.partition("@")
        if not sep:
            raise _fail(f"blackout={text}", "expected DURATION@START, e.g. 2@40% or 2@30s")
        duration = _duration("blackout", dur)
        if duration <= 0.0:
            raise _fail(f"blackout={text}", "duration must be > 0")
        if at.endswith("%"):
            return cls(duration, _probability("blackout", at), relative=True)
        m = _DURATION_RE.match(at)
        if m is None:
            raise _fail(f"blackout={text}", "START must be a percentage of the flight (40%) or seconds (30s)")
        start = float(m.group("v")) / (1000.0 if m.group("unit") == "ms" else 1.0)
        if not start <= _MAX_START_S:
            raise _fail(f"blackout={text}", f"START at most {_MAX_START_S:g} s")
        return cls(duration, start, relative=False)

    def window(
        self, *, opened_s: float, flight_start_s: float | None, expected_flight_s: float | None
    ) -> tuple[float, float] | None:
        """(start, end) on the proxy clock [vehicle s], or None while a relative window is not anchored yet."""
        if not self.relative:
            t0 = opened_s + self.start
        elif flight_start_s is None or expected_flight_s is None:
            return None
        else:
            t0 = flight_start_s + self.start * expected_flight_s
        return (t0, t0 + self.duration_s)

    def __str__(self) -> str:
        at = f"{self.start * 100:g}%" if self.relative else f"{self.start:g}s"
        return f"blackout={self.duration_s:g}@{at}"


@dataclass(frozen=True, slots=True, kw_only=True)
class LinkFaults:
    """The faults of one link, the same in both directions (each direction draws from its own generator).

    Attributes:
        loss: Probability a datagram is dropped.
        delay_s: Fixed extra latency [vehicle s].
        jitter_s: Extra latency uniform in [0, jitter_s] on top of ``delay_s`` [vehicle s] (order-preserving).
        dup: Probability a datagram is sent twice.
        reorder: Probability a datagram is swapped with the next one in its direction.
        blackouts: Windows in which nothing passes.
    """

    loss: float = 0.0
    delay_s: float = 0.0
    jitter_s: float = 0.0
    dup: float = 0.0
    reorder: float = 0.0
    blackouts: tuple[Blackout, ...] = ()

    def __post_init__(self) -> None:
        for key in ("loss", "dup", "reorder"):
            value = getattr(self, key)
            if not 0.0 <= value <= 1.0:
                raise _fail(f"{key}={value}", "probability must be in [0, 1]")
        for key in ("delay_s", "jitter_s"):
            value = getattr(self, key)
            if not 0.0 <= value <= _MAX_DELAY_S:
                raise _fail(f"{key}={value}", f"must be in [0, {_MAX_DELAY_S}] s")

    @classmethod
    def parse(cls, spec: str) -> LinkFaults:
        """``loss=0.3,jitter=0.1,dup=0.05,reorder=0.05,blackout=2@40%`` (any subset, any order; ``blackout``
        may repeat; ``none`` or an empty string = no faults). Raises ConfigError naming the bad item."""
        text = spec.strip()
        if text in ("", "none"):
            return cls()
        values: dict[str, float] = {}
        blackouts: list[Blackout] = []
        for item in (part.strip() for part in text.split(",")):
            key, sep, value = item.partition("=")
            key, value = key.strip(), value.strip()
            if not sep or not key or not value:
                raise _fail(item, f"expected KEY=VALUE with KEY one of {', '.join(_KEYS)}")
            if key not in _KEYS:
                close = difflib.get_close_matches(key, _KEYS, n=1)
                hint = f"did you mean {close[0]!r}? " if close else ""
                raise _fail(item, f"unknown fault {key!r}; {hint}(allowed: {', '.join(_KEYS)})")
            if key == "blackout":
                blackouts.append(Blackout.parse(value))
                continue
            if key in values:
                raise _fail(item, f"{key} given twice")
            values[key] = _probability(key, value) if key in _PROBABILITIES else _duration(key, value)
        return cls(
            loss=values.get("loss", 0.0),
            delay_s=values.get("delay", 0.0),
            jitter_s=values.get("jitter", 0.0),
            dup=values.get("dup", 0.0),
            reorder=values.get("reorder", 0.0),
            blackouts=tuple(blackouts),
        )

    def __str__(self) -> str:
        parts = [
            f"{name}={value:g}"
            for name, value in (
                ("loss", self.loss),
                ("delay", self.delay_s),
                ("jitter", self.jitter_s),
                ("dup", self.dup),
                ("reorder", self.reorder),
            )
            if value > 0.0
        ]
        parts += [str(b) for b in self.blackouts]
        return ",".join(parts) or "none"


@dataclass(frozen=True, slots=True)
class Fate:
    """What happens to one datagram (outside blackouts)."""

    drop: bool
    delay_s: float
    duplicate: bool
    reorder: bool


class FaultModel:
    """The per-datagram fates of one direction: pure, seeded, four uniform draws per datagram whatever the
    outcome, so the n-th datagram's fate depends only on the seed and n."""

    def __init__(self, faults: LinkFaults, rng: np.random.Generator) -> None:
        self.faults = faults
        self._rng = rng

    def next(self) -> Fate:
        u_loss, u_delay, u_dup, u_reorder = self._rng.random(4)
        f = self.faults
        return Fate(
            drop=bool(u_loss < f.loss),
            delay_s=f.delay_s + float(u_delay) * f.jitter_s,
            duplicate=bool(u_dup < f.dup),
            reorder=bool(u_reorder < f.reorder),
        )


class Direction(enum.Enum):
    TO_COMPANION = "to_companion"  # vehicle -> companion
    TO_VEHICLE = "to_vehicle"  # companion -> vehicle


@dataclass(slots=True)
class DirectionStats:
    """Counters of one direction (datagrams)."""

    received: int = 0
    delivered: int = 0
    dropped: int = 0  # random loss
    blackout_dropped: int = 0
    duplicated: int = 0
    reordered: int = 0  # swapped with the next datagram
    send_errors: int = 0  # e.g. ICMP port unreachable: the peer is not listening (yet)
    max_delay_s: float = 0.0


@dataclass(slots=True)
class _Lane:
    """One direction: its fate stream, its order-preserving delivery queue and its held (reordered) datagram."""

    model: FaultModel
    stats: DirectionStats = field(default_factory=DirectionStats)
    queue: deque[tuple[float, bytes]] = field(default_factory=deque)
    last_due_s: float = -math.inf
    timer: asyncio.TimerHandle | None = None
    held: tuple[bytes, float] | None = None
    held_timer: asyncio.TimerHandle | None = None


class _Endpoint(asyncio.DatagramProtocol):
    def __init__(self, on_datagram: Callable[[bytes, tuple[str, int]], None], on_error: Callable[[], None]) -> None:
        self._on_datagram = on_datagram
        self._on_error = on_error

    def datagram_received(self, data: bytes, addr: tuple[str, int]) -> None:
        self._on_datagram(data, addr)

    def error_received(self, exc: Exception) -> None:
        self._on_error()


class LinkProxy:
    """The running proxy. Open with ``await LinkProxy.open(faults, companion_port=..., seed=...)``; point the
    vehicle at ``127.0.0.1:vehicle_port``. ``stats`` has the counters per direction."""

    def __init__(
        self,
        faults: LinkFaults,
        *,
        seed: int,
        time_scale: float,
        reorder_hold_s: float,
        clock: Callable[[], float] | None = None,
    ) -> None:
        if not (math.isfinite(time_scale) and time_scale > 0.0):
            msg = f"link proxy time_scale must be a finite number > 0, got {time_scale!r}"
            raise ConfigError(msg)
        self.faults = faults
        self.time_scale = time_scale
        self.reorder_hold_s = reorder_hold_s
        seeds = np.random.SeedSequence(seed).spawn(2)
        self._lanes = {
            d: _Lane(FaultModel(faults, np.random.default_rng(s))) for d, s in zip(Direction, seeds, strict=True)
        }
        self._loop = asyncio.get_running_loop()
        self._opened_wall = self._loop.time()
        self._clock = clock
        self._flight_start_s: float | None = None
        self._expected_flight_s: float | None = None
        self._vehicle_addr: tuple[str, int] | None = None
        self._companion_addr: tuple[str, int] = ("127.0.0.1", 0)
        self._vehicle_side: asyncio.DatagramTransport | None = None
        self._companion_side: asyncio.DatagramTransport | None = None
        self._closed = False

    @classmethod
    async def open(
        cls,
        faults: LinkFaults,
        *,
        companion_port: int,
        seed: int = 0,
        time_scale: float = 1.0,
        listen_port: int = 0,
        reorder_hold_s: float = 0.2,
        clock: Callable[[], float] | None = None,
    ) -> LinkProxy:
        """Listen for the vehicle on 127.0.0.1:``listen_port`` (0 = any free port) and forward to the companion
        on 127.0.0.1:``companion_port``. ``reorder_hold_s``: longest a reordered datagram waits [vehicle s].
        ``clock``: the proxy's time [vehicle s]; default wall seconds since open times ``time_scale`` (a test
        passes its own, so that blackout windows and delays are decided on its time, not on the wall clock)."""
        proxy = cls(faults, seed=seed, time_scale=time_scale, reorder_hold_s=reorder_hold_s, clock=clock)
        proxy._companion_addr = ("127.0.0.1", companion_port)
        loop = proxy._loop
        vehicle_side, _ = await loop.create_datagram_endpoint(
            lambda: _Endpoint(proxy._from_vehicle, proxy._lane_error(Direction.TO_VEHICLE)),
            local_addr=("127.0.0.1", listen_port),
        )
        companion_side, _ = await loop.create_datagram_endpoint(
            lambda: _Endpoint(proxy._from_companion, proxy._lane_error(Direction.TO_COMPANION)),
            local_addr=("127.0.0.1", 0),
        )
        proxy._vehicle_side = vehicle_side
        proxy._companion_side = companion_side
        return proxy

    # ---- clock and windows ---------------------------------------------------------------------------------
    def now_s(self) -> float:
        """Proxy clock [vehicle s since open, or the injected clock's reading]."""
        if self._clock is not None:
            return self._clock()
        return (self._loop.time() - self._opened_wall) * self.time_scale

    def start_flight(self, expected_flight_s: float) -> None:
        """Anchor the relative blackouts (``2@40%``): the flight starts now and should take this long [s].
        Only the first call counts."""
        if self._flight_start_s is None:
            self._flight_start_s = self.now_s()
            self._expected_flight_s = expected_flight_s

    def blackout_windows(self) -> list[tuple[float, float]]:
        """The blackout windows known so far, on the proxy clock [vehicle s]."""
        windows = (
            b.window(opened_s=0.0, flight_start_s=self._flight_start_s, expected_flight_s=self._expected_flight_s)
            for b in self.faults.blackouts
        )
        return [w for w in windows if w is not None]

    def in_blackout(self, t_s: float) -> bool:
        return any(t0 <= t_s < t1 for t0, t1 in self.blackout_windows())

    # ---- addresses and counters ----------------------------------------------------------------------------
    @property
    def vehicle_port(self) -> int:
        """Where the vehicle sends (its ``udpout`` port)."""
        assert self._vehicle_side is not None
        return int(self._vehicle_side.get_extra_info("sockname")[1])

    @property
    def companion_side_port(self) -> int:
        """The proxy's source port towards the companion (the peer the companion replies to)."""
        assert self._companion_side is not None
        return int(self._companion_side.get_extra_info("sockname")[1])

    @property
    def stats(self) -> dict[Direction, DirectionStats]:
        return {d: lane.stats for d, lane in self._lanes.items()}

    def stats_dict(self) -> dict[str, dict[str, float]]:
        """Counters per direction, JSON-ready."""
        return {d.value: dataclasses.asdict(s) for d, s in self.stats.items()}

    # ---- datapath ------------------------------------------------------------------------------------------
    def _lane_error(self, direction: Direction) -> Callable[[], None]:
        def count() -> None:
            self._lanes[direction].stats.send_errors += 1

        return count

    def _from_vehicle(self, data: bytes, addr: tuple[str, int]) -> None:
        self._vehicle_addr = addr
        self._accept(Direction.TO_COMPANION, data)

    def _from_companion(self, data: bytes, addr: tuple[str, int]) -> None:
        if addr == self._companion_addr:
            self._accept(Direction.TO_VEHICLE, data)

    def _accept(self, direction: Direction, data: bytes) -> None:
        lane = self._lanes[direction]
        lane.stats.received += 1
        fate = lane.model.next()  # drawn for every datagram, so blackouts do not shift later fates
        now = self.now_s()
        if self._closed or self.in_blackout(now):
            lane.stats.blackout_dropped += 1
            return
        if fate.drop:
            lane.stats.dropped += 1
            return
        copies = [data, data] if fate.duplicate else [data]
        lane.stats.duplicated += int(fate.duplicate)
        hold = fate.reorder and lane.held is None
        if hold:
            lane.held = (data, fate.delay_s)
            lane.held_timer = self._loop.call_later(
                self.reorder_hold_s / self.time_scale, self._release_held, direction, False
            )
            copies = copies[1:]
        for copy in copies:
            self._enqueue(direction, copy, fate.delay_s)
        if not hold and lane.held is not None:
            self._release_held(direction, True)  # the held datagram goes out right after this one

    def _release_held(self, direction: Direction, swapped: bool) -> None:
        lane = self._lanes[direction]
        if lane.held is None:
            return
        data, delay_s = lane.held
        lane.held = None
        if lane.held_timer is not None:
            lane.held_timer.cancel()
            lane.held_timer = None
        lane.stats.reordered += int(swapped)
        self._enqueue(direction, data, delay_s)

    def _enqueue(self, direction: Direction, data: bytes, delay_s: float) -> None:
        lane = self._lanes[direction]
        now = self.now_s()
        due = max(now + delay_s, lane.last_due_s)  # order-preserving: never before the previous datagram
        lane.last_due_s = due
        lane.stats.max_delay_s = max(lane.stats.max_delay_s, due - now)
        lane.queue.append((due, data))
        if lane.timer is None:
            self._arm(direction)

    def _arm(self, direction: Direction) -> None:
        lane = self._lanes[direction]
        due = lane.queue[0][0]
        # Due in vehicle seconds; on another clock than the wall's, _drain re-arms until the datagram is due.
        lane.timer = self._loop.call_later(max(0.0, due - self.now_s()) / self.time_scale, self._drain, direction)

    def _drain(self, direction: Direction) -> None:
        lane = self._lanes[direction]
        lane.timer = None
        now = self.now_s()
        while lane.queue and lane.queue[0][0] <= now:
            _, data = lane.queue.popleft()
            if self.in_blackout(now):
                lane.stats.blackout_dropped += 1
            else:
                self._send(direction, data)
        if lane.queue and not self._closed:
            self._arm(direction)

    def _send(self, direction: Direction, data: bytes) -> None:
        lane = self._lanes[direction]
        transport = self._companion_side if direction is Direction.TO_COMPANION else self._vehicle_side
        addr = self._companion_addr if direction is Direction.TO_COMPANION else self._vehicle_addr
        if transport is None or addr is None or transport.is_closing():
            lane.stats.send_errors += 1
            return
        try:
            transport.sendto(data, addr)
        except OSError:
            lane.stats.send_errors += 1
            return
        lane.stats.delivered += 1

    def pending(self) -> int:
        """Datagrams queued or held (not yet sent or dropped)."""
        return sum(len(lane.queue) + (lane.held is not None) for lane in self._lanes.values())

    async def aclose(self) -> None:
        """Stop forwarding and close both sockets (idempotent); queued datagrams are discarded."""
        if self._closed:
            return
        self._closed = True
        for lane in self._lanes.values():
            for timer in (lane.timer, lane.held_timer):
                if timer is not None:
                    timer.cancel()
            lane.queue.clear()
            lane.held = None
        for transport in (self._vehicle_side, self._companion_side):
            if transport is not None:
                transport.close()
        with contextlib.suppress(asyncio.CancelledError):
            await asyncio.sleep(0)  # let the transports finish closing
