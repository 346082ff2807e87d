"""What a range sensor sees in a World: the nearest obstacle surface in angular windows, and single-ray casts.

Kept apart from the World (``sim/world/model.py``), which holds the obstacles and their distance queries; the
simulated rangefinder (``sim/vehicle/sensor.py``) reads the windows and the tests' scanner (``sim/world/scan.py``)
the rays. Positions are local NED north/east metres, bearings radians clockwise from north, heights metres above
ground. Vectorised over obstacles and over windows or rays; no per-obstacle Python loops.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np
import numpy.typing as npt

if TYPE_CHECKING:
    from sim.world.model import World

__all__ = ["closest_point_on_segments", "ray_cast_m", "window_ranges_m"]

FloatArray = npt.NDArray[np.float64]


def window_ranges_m(
    world: World,
    pos_ne_m: npt.ArrayLike,
    centres_rad: npt.ArrayLike,
    half_width_rad: float,
    *,
    alt_m: float = 0.0,
) -> FloatArray:
    """(S,) exact range to the nearest surface of ``world`` inside each angular window [m]; inf if none.

    The arguments and the result are those of ``World.window_ranges_m``, which calls this.
    """
    p = np.asarray(pos_ne_m, dtype=np.float64).reshape(2)
    c = np.asarray(centres_rad, dtype=np.float64).reshape(-1)
    out = np.full(c.shape, np.inf)
    if world.n_circles:
        out = np.minimum(out, _circle_windows(world, p, c, half_width_rad, alt_m))
    if world.n_walls:
        out = np.minimum(out, _wall_windows(world, p, c, half_width_rad, alt_m))
    return out


def _circle_windows(world: World, p: FloatArray, c: FloatArray, h: float, alt_m: float) -> FloatArray:
    rel = world.circles_ne_m - p
    d = np.hypot(rel[:, 0], rel[:, 1])
    r = world.circle_radii_m
    visible = world.circle_heights_m >= alt_m
    beta = np.arctan2(rel[:, 1], rel[:, 0])  # bearing clockwise from north
    phi = _wrap_pi(beta[None, :] - c[:, None])  # (S, N)
    delta = np.maximum(np.abs(phi) - h, 0.0)  # angle from the window to the centre bearing
    with np.errstate(invalid="ignore", divide="ignore"):
        alpha = np.arcsin(np.clip(np.where(d > 0, r / d, 1.0), 0.0, 1.0))
        perp = d[None, :] * np.sin(delta)
        chord = np.sqrt(np.maximum(r[None, :] ** 2 - perp**2, 0.0))
        rng = d[None, :] * np.cos(delta) - chord
    hit = (delta <= alpha[None, :]) & visible[None, :]
    rng = np.where(hit, np.maximum(rng, 0.0), np.inf)
    inside = (d <= r) & visible
    rng = np.where(inside[None, :], 0.0, rng)
    return np.asarray(rng.min(axis=1), dtype=np.float64)


def _wall_windows(world: World, p: FloatArray, c: FloatArray, h: float, alt_m: float) -> FloatArray:
    # The points of a segment seen inside a convex angular window form one sub-segment; the distance to
    # the sensor is convex along it, so its minimum is at the perpendicular foot (if seen) or at an end of
    # the sub-segment: a segment end point (if seen) or a crossing with a window edge ray.
    a = world.walls_ne_m[:, 0, :] - p  # (M, 2)
    b = world.walls_ne_m[:, 1, :] - p
    visible = world.wall_heights_m >= alt_m
    half = 0.5 * world.wall_thickness_m
    cand = np.full((c.size, a.shape[0]), np.inf)

    def seen(pt: FloatArray) -> npt.NDArray[np.bool_]:
        bearing = np.arctan2(pt[:, 1], pt[:, 0])
        return np.abs(_wrap_pi(bearing[None, :] - c[:, None])) <= h  # (S, M)

    for pt in (a, b, closest_point_on_segments(np.zeros(2), world.walls_ne_m) - p):
        dist = np.hypot(pt[:, 0], pt[:, 1])
        cand = np.minimum(cand, np.where(seen(pt), dist[None, :], np.inf))
    for edge in (c - h, c + h):
        cand = np.minimum(cand, _ray_segment_range(edge, a, b))
    cand = np.where(visible[None, :], np.maximum(cand - half[None, :], 0.0), np.inf)
    return np.asarray(cand.min(axis=1), dtype=np.float64)


def ray_cast_m(world: World, pos_ne_m: npt.ArrayLike, bearings_rad: npt.ArrayLike, *, alt_m: float = 0.0) -> FloatArray:
    """(S,) range along single rays to the first surface of ``world`` [m]; inf if none.

    The arguments and the result are those of ``World.ray_cast_m``, which calls this.
    """
    p = np.asarray(pos_ne_m, dtype=np.float64).reshape(2)
    th = np.asarray(bearings_rad, dtype=np.float64).reshape(-1)
    out = np.full(th.shape, np.inf)
    if world.n_circles:
        rel = world.circles_ne_m - p
        u = np.stack([np.cos(th), np.sin(th)], axis=1)  # (S, 2)
        proj = u @ rel.T  # (S, N)
        d2 = np.sum(rel**2, axis=1)
        disc = proj**2 - (d2 - world.circle_radii_m**2)[None, :]
        with np.errstate(invalid="ignore"):
            t = proj - np.sqrt(disc)
        ok = (disc >= 0) & (proj + np.sqrt(np.maximum(disc, 0)) >= 0) & (world.circle_heights_m >= alt_m)[None, :]
        out = np.minimum(out, np.where(ok, np.maximum(t, 0.0), np.inf).min(axis=1))
    if world.n_walls:
        a = world.walls_ne_m[:, 0, :] - p
        b = world.walls_ne_m[:, 1, :] - p
        rng = np.where((world.wall_heights_m >= alt_m)[None, :], _ray_segment_range(th, a, b), np.inf)
        out = np.minimum(out, rng.min(axis=1))
    return out


def closest_point_on_segments(p: FloatArray, segs: FloatArray) -> FloatArray:
    """(M, 2) the point of each segment ``segs`` (M, 2, 2) nearest to ``p`` (2,) [m].

    Here for the walls' perpendicular foot; the World's distance queries use it too (model.py imports this module,
    so the helper lives on this side).
    """
    a = segs[:, 0, :]
    ab = segs[:, 1, :] - a
    denom = np.sum(ab**2, axis=1)
    with np.errstate(invalid="ignore", divide="ignore"):
        t = np.where(denom > 0, np.sum((p - a) * ab, axis=1) / denom, 0.0)
    t = np.clip(t, 0.0, 1.0)
    return np.asarray(a + t[:, None] * ab, dtype=np.float64)


def _wrap_pi(a: npt.NDArray[np.float64]) -> npt.NDArray[np.float64]:
    return np.asarray((a + np.pi) % (2 * np.pi) - np.pi, dtype=np.float64)


def _ray_segment_range(bearings_rad: FloatArray, a: FloatArray, b: FloatArray) -> FloatArray:
    """(S, M) distance along rays from the origin to segments a->b (relative coordinates); inf on a miss."""
    u = np.stack([np.cos(bearings_rad), np.sin(bearings_rad)], axis=1)  # (S, 2)
    e = b - a  # (M, 2)
    # Solve t*u = a + s*e  ->  t*u - s*e = a (2x2 per pair) by Cramer's rule.
    det = -u[:, 0:1] * e[None, :, 1] + u[:, 1:2] * e[None, :, 0]  # (S, M)
    with np.errstate(invalid="ignore", divide="ignore"):
        t = (-a[None, :, 0] * e[None, :, 1] + a[None, :, 1] * e[None, :, 0]) / det
        s = (u[:, 0:1] * a[None, :, 1] - u[:, 1:2] * a[None, :, 0]) / det
    ok = (np.abs(det) > 1e-12) & (t >= 0) & (s >= 0) & (s <= 1)
    return np.asarray(np.where(ok, t, np.inf), dtype=np.float64)
