"""Bacteria ring and sphere: radius, count, order and spread (hypothesis)."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from apf_companion.errors import ConfigError
from apf_companion.planning import bacteria_ring, bacteria_sphere

radii = st.floats(min_value=1e-3, max_value=100.0, allow_nan=False, allow_infinity=False)


@settings(max_examples=60, deadline=None)
@given(n=st.integers(min_value=3, max_value=720), radius=radii)
def test_ring_radius_count_angles(n: int, radius: float) -> None:
    ring = bacteria_ring(n, radius)
    assert ring.shape == (n, 2)
    assert ring.dtype == np.float64
    np.testing.assert_allclose(np.hypot(ring[:, 0], ring[:, 1]), radius, rtol=1e-12)
    # Point k (1-based) is at k * 360 / n degrees from +x toward +y; the last one is exactly on +x.
    angles = np.mod(np.arctan2(ring[:, 1], ring[:, 0]), 2 * math.pi)
    expected = np.mod(2 * math.pi * np.arange(1, n + 1) / n, 2 * math.pi)
    wrapped = np.angle(np.exp(1j * (angles - expected)))
    np.testing.assert_allclose(wrapped, 0.0, atol=1e-9)
    assert ring[-1, 0] == radius and ring[-1, 1] == 0.0
    # Even spread: every neighbour gap is the chord of 2 pi / n.
    gaps = np.hypot(*(np.roll(ring, -1, axis=0) - ring).T)
    np.testing.assert_allclose(gaps, 2 * radius * math.sin(math.pi / n), rtol=1e-9)


def test_ring_paper_angles() -> None:
    ring = bacteria_ring(60, 0.4)
    # 6, 12, ..., 360 degrees (the authors' code).
    np.testing.assert_allclose(ring[0], 0.4 * np.array([math.cos(math.radians(6)), math.sin(math.radians(6))]))
    np.testing.assert_allclose(ring[14], [0.0, 0.4], atol=1e-15)  # 90 degrees: +y


@settings(max_examples=40, deadline=None)
@given(n=st.integers(min_value=4, max_value=500), radius=radii)
def test_sphere_radius_count_spread(n: int, radius: float) -> None:
    sphere = bacteria_sphere(n, radius)
    assert sphere.shape == (n, 3)
    np.testing.assert_allclose(np.linalg.norm(sphere, axis=1), radius, rtol=1e-12)
    # Balanced: the centroid is near the centre, and no two points crowd together. For a Fibonacci lattice
    # the nearest-neighbour distance is about radius * sqrt(4 pi / n); require at least a third of it.
    assert np.linalg.norm(sphere.mean(axis=0)) <= radius * 2.0 / math.sqrt(n)
    d = np.linalg.norm(sphere[:, None, :] - sphere[None, :, :], axis=-1)
    np.fill_diagonal(d, np.inf)
    assert d.min() >= radius * math.sqrt(4 * math.pi / n) / 3.0
    # Equal-area bands: z is uniform on (-r, r).
    np.testing.assert_allclose(np.sort(sphere[:, 2]), radius * (1 - (2 * np.arange(n)[::-1] + 1) / n), rtol=1e-9)


def test_sphere_covers_every_direction() -> None:
    sphere = bacteria_sphere(60, 1.0)
    rng = np.random.default_rng(7)
    dirs = rng.normal(size=(2000, 3))
    dirs /= np.linalg.norm(dirs, axis=1, keepdims=True)
    # Every direction is within ~30 degrees of some point (60 points: cap angle about 15 degrees).
    best = (dirs @ sphere.T).max(axis=1)
    assert best.min() > math.cos(math.radians(30))


@pytest.mark.parametrize(("fn", "n"), [(bacteria_ring, 2), (bacteria_sphere, 3)])
def test_too_few_points(fn: object, n: int) -> None:
    with pytest.raises(ConfigError, match="n_points"):
        fn(n, 0.4)  # type: ignore[operator]


@pytest.mark.parametrize("radius", [0.0, -1.0, float("nan")])
def test_bad_radius(radius: float) -> None:
    with pytest.raises(ConfigError, match="radius_m"):
        bacteria_ring(60, radius)
