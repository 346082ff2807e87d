"""The service process's garbage collector: no full collection of the startup heap mid-flight, and its pauses
measured.

CPython's cyclic collector stops the process while it runs. A full (oldest-generation) collection walks every
tracked object; after the imports (numpy, scipy, pymavlink's dialect, the service's parts) that is about 55 000
objects and 10-15 ms on a 2-core x86 VM (``benchmarks/bench_gc.py``), several times a planning cycle's work, and
it comes at a moment the service does not choose. The startup heap lives for the whole run, so walking it again
finds nothing: ``freeze_startup_heap`` collects once, then moves every surviving object to the permanent
generation (``gc.freeze``, the CPython documentation's advice for long-lived processes), and later collections walk
only what the flight allocated since.

``GcPauses`` times every collection through ``gc.callbacks`` (the interpreter calls them around each one), so the
status and the result show whether a collection, not the planner, made a slow cycle.
"""

from __future__ import annotations

import gc
import time
from dataclasses import dataclass
from typing import Any

__all__ = ["GcPauses", "GcSummary", "freeze_startup_heap"]

#: The oldest generation: a collection of it walks every tracked object that is not frozen.
_OLDEST = 2


def freeze_startup_heap() -> int:
    """Collect once, then freeze the survivors (``gc.freeze``): returns how many objects are frozen. Call it once
    the service is built and its links are open, before the flight; the process's own entry point does (``apf-companion
    run``), not the library, so an embedding program keeps its own collector policy."""
    gc.collect()
    gc.freeze()
    return gc.get_freeze_count()


@dataclass(frozen=True, slots=True)
class GcSummary:
    """Collections since ``GcPauses`` started: how many, how many were full, the longest pause [ms], and how
    many objects are frozen (not walked)."""

    collections: int
    full: int
    max_pause_ms: float
    frozen: int

    def to_dict(self) -> dict[str, Any]:
        return {
            "collections": self.collections,
            "full": self.full,
            "max_pause_ms": round(self.max_pause_ms, 3),
            "frozen": self.frozen,
        }


class GcPauses:
    """Times the collector's pauses while open (``gc.callbacks``); ``close`` stops it. One per running service."""

    def __init__(self) -> None:
        self._started: float | None = None
        self._collections = 0
        self._full = 0
        self._max_s = 0.0
        gc.callbacks.append(self._on_gc)

    def _on_gc(self, phase: str, info: dict[str, int]) -> None:
        now = time.perf_counter()
        if phase == "start":
            self._started = now
            return
        if self._started is None:  # opened during a collection: its start was not seen
            return
        self._collections += 1
        self._full += info.get("generation") == _OLDEST
        self._max_s = max(self._max_s, now - self._started)
        self._started = None

    def summary(self) -> GcSummary:
        return GcSummary(
            collections=self._collections,
            full=self._full,
            max_pause_ms=self._max_s * 1000.0,
            frozen=gc.get_freeze_count(),
        )

    def close(self) -> None:
        """Stop timing (idempotent)."""
        if self._on_gc in gc.callbacks:
            gc.callbacks.remove(self._on_gc)
