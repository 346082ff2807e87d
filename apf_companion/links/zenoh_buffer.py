"""A zenoh subscription's samples between zenoh's thread and the event loop: the overflow policies' buffers and the
lock that guards them (``SampleHandoff``). No zenoh and no asyncio here; apf_companion.links.zenoh uses it.

- ``Overflow.LATEST_PER_KEY`` (sensors): one sample per key, a newer one overwrites the older (counted in
  ``overwritten``); at most ``capacity`` keys, the least recently updated key is dropped (counted in ``dropped``).
- ``Overflow.FIFO`` (commands): samples in arrival order, at most ``capacity``; when full the OLDEST is dropped
  (counted in ``dropped``), because a newer command (e.g. a goal) supersedes older ones.
"""

from __future__ import annotations

import collections
import enum
import threading
from collections.abc import Callable
from dataclasses import dataclass
from typing import Protocol

__all__ = ["Overflow", "SampleHandoff", "SubscriptionStats", "ZenohSample"]


@dataclass(frozen=True, slots=True, kw_only=True)
class ZenohSample:
    """One received sample, copied out of zenoh on its thread.

    Attributes:
        key_expr: The key the sample was published on.
        payload: The payload bytes.
        encoding: The zenoh encoding string (e.g. ``"application/json"``, ``"zenoh/bytes"``).
        t_s: ``time.monotonic()`` when the zenoh callback ran [s].
    """

    key_expr: str
    payload: bytes
    encoding: str
    t_s: float


class Overflow(enum.Enum):
    """What a subscription's buffer does when the event loop does not keep up."""

    LATEST_PER_KEY = "latest_per_key"
    FIFO = "fifo"


@dataclass(slots=True)
class SubscriptionStats:
    """Counters of one subscription (read from the event loop)."""

    received: int = 0
    overwritten: int = 0
    dropped: int = 0


class _Buffer(Protocol):
    """An overflow policy's buffer (the caller holds the lock)."""

    def put(self, item: ZenohSample) -> None: ...
    def pop(self) -> ZenohSample | None: ...
    def __len__(self) -> int: ...


class _LatestPerKey:
    """``Overflow.LATEST_PER_KEY``: one sample per key, a newer one overwrites the older; at most ``capacity`` keys,
    the least recently updated one dropped."""

    def __init__(self, capacity: int, stats: SubscriptionStats) -> None:
        self._capacity = capacity
        self._stats = stats
        self._latest: collections.OrderedDict[str, ZenohSample] = collections.OrderedDict()

    def put(self, item: ZenohSample) -> None:
        if item.key_expr in self._latest:
            self._stats.overwritten += 1
            self._latest.move_to_end(item.key_expr)
        self._latest[item.key_expr] = item
        if len(self._latest) > self._capacity:
            self._latest.popitem(last=False)
            self._stats.dropped += 1

    def pop(self) -> ZenohSample | None:
        return self._latest.popitem(last=False)[1] if self._latest else None

    def __len__(self) -> int:
        return len(self._latest)


class _Fifo:
    """``Overflow.FIFO``: samples in arrival order, at most ``capacity``; when full the oldest is dropped."""

    def __init__(self, capacity: int, stats: SubscriptionStats) -> None:
        self._capacity = capacity
        self._stats = stats
        self._fifo: collections.deque[ZenohSample] = collections.deque()

    def put(self, item: ZenohSample) -> None:
        if len(self._fifo) >= self._capacity:
            self._fifo.popleft()
            self._stats.dropped += 1
        self._fifo.append(item)

    def pop(self) -> ZenohSample | None:
        return self._fifo.popleft() if self._fifo else None

    def __len__(self) -> int:
        return len(self._fifo)


_BUFFERS: dict[Overflow, Callable[[int, SubscriptionStats], _Buffer]] = {
    Overflow.LATEST_PER_KEY: _LatestPerKey,
    Overflow.FIFO: _Fifo,
}


class SampleHandoff:
    """The state a subscription shares between zenoh's thread and the event loop, behind one lock: the overflow
    policy's buffer, its counters, whether it is closed and whether a wake-up of the loop is on its way."""

    def __init__(self, overflow: Overflow, capacity: int) -> None:
        self.stats = SubscriptionStats()
        self.closed = False
        self._lock = threading.Lock()
        self._buffer = _BUFFERS[overflow](capacity, self.stats)
        self._wake_scheduled = False

    def offer(self, item: ZenohSample) -> bool:
        """Buffer ``item`` (zenoh's thread); True when the loop must be woken (once per batch)."""
        with self._lock:
            if self.closed:
                return False
            self.stats.received += 1
            self._buffer.put(item)
            schedule = not self._wake_scheduled
            self._wake_scheduled = True
        return schedule

    def woken(self) -> None:
        """The loop woke up: the next sample schedules another wake-up."""
        with self._lock:
            self._wake_scheduled = False

    def take(self) -> ZenohSample | None:
        """The next buffered sample, or None."""
        with self._lock:
            return self._buffer.pop()

    def pending(self) -> int:
        with self._lock:
            return len(self._buffer)

    def close(self) -> None:
        with self._lock:
            self.closed = True
