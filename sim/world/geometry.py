"""Vectorised geometry on a World's TRUE obstacles (2D, north/east metres): clearance of many positions,
exact segment clearance, and the surface samples a point-based planner sees.

Heights are ignored here: the study and the A* optimum are 2D, so every wall and cylinder blocks.
"""

from __future__ import annotations

import math

import numpy as np
import numpy.typing as npt

from sim.world.model import FloatArray, World

__all__ = [
    "SURFACE_SPACING_M",
    "clearance_many_m",
    "segment_clearance_m",
    "surface_samples_ne_m",
]

SURFACE_SPACING_M = 0.2
"""Default spacing of the surface samples [m]: the perception memory's merge radius (``ObstacleMemory``,
``merge_radius_m`` = 0.2), i.e. the densest map the service itself can hold of a wall, and the spacing of the
range sensor's 5-degree sectors at 2.3 m (2.3 * tan 5 deg = 0.2 m)."""


def _point_segment_dist(p: FloatArray, a: FloatArray, b: FloatArray) -> FloatArray:
    """Distance from points ``p`` (..., 2) to segments a->b (broadcast, (..., 2) each) [m]."""
    ab = b - a
    denom = np.sum(ab * ab, axis=-1)
    with np.errstate(invalid="ignore", divide="ignore"):
        t = np.where(denom > 0, np.sum((p - a) * ab, axis=-1) / denom, 0.0)
    t = np.clip(t, 0.0, 1.0)
    foot = a + t[..., None] * ab
    d = p - foot
    return np.asarray(np.hypot(d[..., 0], d[..., 1]), dtype=np.float64)


def _cross(u: FloatArray, v: FloatArray) -> FloatArray:
    return np.asarray(u[..., 0] * v[..., 1] - u[..., 1] * v[..., 0], dtype=np.float64)


def _segment_segment_dist(p: FloatArray, q: FloatArray, a: FloatArray, b: FloatArray) -> FloatArray:
    """Distance between segments p->q and a->b (broadcast) [m]: 0 when they cross, else the smallest of the
    four end-point-to-segment distances."""
    d = np.minimum(
        np.minimum(_point_segment_dist(p, a, b), _point_segment_dist(q, a, b)),
        np.minimum(_point_segment_dist(a, p, q), _point_segment_dist(b, p, q)),
    )
    d1 = _cross(q - p, a - p)
    d2 = _cross(q - p, b - p)
    d3 = _cross(b - a, p - a)
    d4 = _cross(b - a, q - a)
    crossing = (d1 * d2 < 0) & (d3 * d4 < 0)
    return np.asarray(np.where(crossing, 0.0, d), dtype=np.float64)


def clearance_many_m(world: World, pos_ne_m: npt.ArrayLike) -> FloatArray:
    """(A,) distance from each of (A, 2) positions to the nearest true obstacle surface [m] (negative inside;
    +inf in an empty world)."""
    p = np.asarray(pos_ne_m, dtype=np.float64).reshape(-1, 2)
    out = np.full(p.shape[0], np.inf)
    if world.n_circles:
        rel = p[:, None, :] - world.circles_ne_m[None, :, :]
        d_c = np.hypot(rel[..., 0], rel[..., 1]) - world.circle_radii_m[None, :]
        out = np.minimum(out, d_c.min(axis=1))
    if world.n_walls:
        w = world.walls_ne_m
        d_w = _point_segment_dist(p[:, None, :], w[None, :, 0, :], w[None, :, 1, :]) - 0.5 * world.wall_thickness_m
        out = np.minimum(out, d_w.min(axis=1))
    return out


def segment_clearance_m(world: World, from_ne_m: npt.ArrayLike, to_ne_m: npt.ArrayLike) -> FloatArray:
    """(K,) smallest distance from any point of each straight segment (K, 2) -> (K, 2) to a true obstacle
    surface [m] (exact: point-segment distance to cylinder centres, segment-segment distance to walls)."""
    p = np.asarray(from_ne_m, dtype=np.float64).reshape(-1, 2)
    q = np.asarray(to_ne_m, dtype=np.float64).reshape(-1, 2)
    out = np.full(p.shape[0], np.inf)
    if world.n_circles:
        c = world.circles_ne_m[None, :, :]
        d_c = _point_segment_dist(c, p[:, None, :], q[:, None, :]) - world.circle_radii_m[None, :]
        out = np.minimum(out, d_c.min(axis=1))
    if world.n_walls:
        w = world.walls_ne_m
        d_w = _segment_segment_dist(p[:, None, :], q[:, None, :], w[None, :, 0, :], w[None, :, 1, :])
        out = np.minimum(out, (d_w - 0.5 * world.wall_thickness_m).min(axis=1))
    return out


def surface_samples_ne_m(world: World, spacing_m: float = SURFACE_SPACING_M) -> FloatArray:
    """(K, 2) points on the true obstacle surfaces, at most ``spacing_m`` apart along each outline.

    A cylinder of radius 0 is its centre (the paper's point obstacle); a cylinder of radius r gives
    ceil(2 pi r / spacing) points on its circle; a wall gives its capsule outline (both faces at half the
    thickness from the centre line, plus the two end caps; a zero-thickness wall is its centre line).
    """
    if not (math.isfinite(spacing_m) and spacing_m > 0):
        msg = f"surface spacing must be finite and > 0, got {spacing_m!r}"
        raise ValueError(msg)
    parts: list[FloatArray] = []
    for centre, r in zip(world.circles_ne_m, world.circle_radii_m, strict=True):
        n = max(1, math.ceil(2.0 * math.pi * r / spacing_m)) if r > 0 else 1
        ang = 2.0 * math.pi * np.arange(n) / n
        parts.append(centre + r * np.stack([np.cos(ang), np.sin(ang)], axis=1))
    for (a, b), t in zip(world.walls_ne_m, world.wall_thickness_m, strict=True):
        parts.append(_capsule_outline(a, b, 0.5 * float(t), spacing_m))
    if not parts:
        return np.zeros((0, 2))
    return np.concatenate(parts)


def _capsule_outline(a: FloatArray, b: FloatArray, half_m: float, spacing_m: float) -> FloatArray:
    ab = b - a
    length = float(np.hypot(*ab))
    n_len = max(1, math.ceil(length / spacing_m))
    s = np.linspace(0.0, 1.0, n_len + 1)[:, None]
    line = a + s * ab
    if half_m <= 0.0:
        return np.asarray(line, dtype=np.float64)
    u = ab / length if length > 0 else np.array([1.0, 0.0])
    normal = np.array([-u[1], u[0]])
    n_cap = max(1, math.ceil(math.pi * half_m / spacing_m))
    ang = np.linspace(0.0, math.pi, n_cap + 1)[1:-1, None]
    # Caps: half circles around each end, from one face to the other, facing away from the wall.
    cap_b = b + half_m * (np.cos(ang) * normal - np.sin(ang) * -u)
    cap_a = a + half_m * (-np.cos(ang) * normal + np.sin(ang) * -u)
    return np.concatenate([line + half_m * normal, line - half_m * normal, cap_a, cap_b])
