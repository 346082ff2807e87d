"""The service process's collector: the startup heap frozen, every pause timed (apf_companion/heap.py)."""

from __future__ import annotations

import gc
from collections.abc import Iterator

import pytest

from apf_companion.heap import GcPauses, freeze_startup_heap


@pytest.fixture
def unfrozen() -> Iterator[None]:
    """The test process's heap as it was: frozen objects are never collected, so unfreeze after the test."""
    yield
    gc.unfreeze()


def _cycles(n: int) -> None:
    """``n`` reference cycles that only the cyclic collector can free."""
    for _ in range(n):
        a: list[object] = []
        a.append(a)


def test_freezing_moves_the_survivors_out_of_every_later_collection(unfrozen: None) -> None:
    gc.unfreeze()
    assert gc.get_freeze_count() == 0
    frozen = freeze_startup_heap()
    assert frozen == gc.get_freeze_count() > 1000  # the test process's modules, at least
    # A full collection now walks only what was allocated since: the frozen objects are in no generation.
    late: list[object] = [[]]
    tracked = gc.get_objects()
    assert any(o is late for o in tracked)
    assert len(tracked) < frozen


def test_pauses_are_counted_and_timed_until_closed() -> None:
    pauses = GcPauses()
    try:
        _cycles(100)
        gc.collect()  # a full collection (generation 2)
        gc.collect(0)
        s = pauses.summary()
        assert s.collections >= 2 and s.full >= 1
        assert s.max_pause_ms > 0.0
        assert s.to_dict()["collections"] == s.collections
    finally:
        pauses.close()
    pauses.close()  # idempotent
    gc.collect()
    assert pauses.summary().collections == s.collections  # closed: no longer counted
