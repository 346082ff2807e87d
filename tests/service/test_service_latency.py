"""The loop-latency record: the status window and the whole run's percentiles, in memory that does not grow."""

from __future__ import annotations

import tracemalloc

import numpy as np
import pytest

from apf_companion.reporter import LATENCY_BINS_PER_DECADE, LatencyHistogram, LatencyWindow

HALF_BIN = 10.0 ** (0.5 / LATENCY_BINS_PER_DECADE) - 1.0  # relative error bound of a binned percentile


@pytest.mark.parametrize("q", [1.0, 50.0, 90.0, 99.0, 100.0])
def test_run_percentiles_match_the_samples_within_half_a_bin(q: float) -> None:
    samples = np.random.default_rng(7).lognormal(mean=0.0, sigma=1.2, size=20_000)  # ~1 ms, a long tail
    hist = LatencyHistogram()
    for ms in samples:
        hist.add(float(ms))
    exact = float(np.percentile(samples, q, method="inverted_cdf"))  # nearest rank, as the histogram
    got = hist.percentile(q)
    assert got is not None
    assert abs(got / exact - 1.0) <= HALF_BIN + 1e-12


def test_run_percentiles_of_few_and_extreme_samples() -> None:
    hist = LatencyHistogram()
    assert hist.percentile(50.0) is None
    hist.add(0.7)
    assert hist.percentile(50.0) == hist.percentile(99.0) == 0.7  # kept within the samples' range
    for ms in (0.0, -1.0, 1e9, float("inf"), float("nan")):  # a clock step cannot raise or poison the result
        hist.add(ms)
    assert hist.n == 5  # NaN not counted
    assert hist.percentile(0.0) == -1.0
    assert hist.percentile(100.0) == float("inf")


def test_window_memory_does_not_grow_with_the_run() -> None:
    """A week at 10 Hz is 6e6 cycles: the run's record must not keep one object per sample (issue 9 soak)."""
    window = LatencyWindow()
    for ms in np.linspace(0.1, 5.0, 5_000):  # the status window (4096) full, the histogram allocated
        window.add(float(ms))
    tracemalloc.start()
    try:
        before, _ = tracemalloc.get_traced_memory()
        for ms in np.linspace(0.1, 5.0, 100_000):
            window.add(float(ms))
        after, _ = tracemalloc.get_traced_memory()
    finally:
        tracemalloc.stop()
    assert after - before < 16 * 1024  # a list of 100 000 floats would be ~3.2 MB
    p50, p99 = window.run_percentiles()
    assert p50 is not None and p99 is not None
    assert abs(p50 / 2.55 - 1.0) < 0.02 and abs(p99 / 4.95 - 1.0) < 0.02
