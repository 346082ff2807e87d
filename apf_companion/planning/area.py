"""The flying area (``PlannerParams.nav_area_ne_m``): which points lie in it, and which straight lines leave it.

Two forms, both in local NED [m]: a rectangle (north_min, east_min, north_max, east_max), and a polygon, a tuple of
(north, east) vertices in order (either direction), for a yard that is not a rectangle (an L-shaped field, a
plot between buildings). A polygon may be concave; it may not cross itself (``polygon_problem``). Keep-out zones
(``PlannerParams.nav_keepout_ne_m``, a fence's exclusion zones) are polygons the vehicle must not enter, inside an
area or without one: ``in_keepout``, ``meets_keepout``.

One rule for every user of the area: the escape grid's blocked cells and its goal (``navfield``), bapf-nav's give-up
on a target outside it (``bapfnav``), its line of sight (``leaves_area``: a straight line that leaves a concave
area starts an escape), the service's refusal of such goals (``goal.route_outside_limits``) and the world files'
check of their start and goal (``sim.world``). Bounds and polygon edges are inside; a non-finite coordinate is
outside.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import numpy.typing as npt

__all__ = [
    "AreaNE",
    "FlyingArea",
    "KeepOuts",
    "PolygonNE",
    "ZoneConflict",
    "area_bounds",
    "area_polygon",
    "area_text",
    "in_keepout",
    "inside_area",
    "is_polygon",
    "leaves_area",
    "meets_keepout",
    "near_edges",
    "outside_zones",
    "polygon_problem",
    "zone_conflict",
    "zones_block_line",
    "zones_bound_lines",
]

#: (north_min, east_min, north_max, east_max) in local NED [m].
AreaNE = tuple[float, float, float, float]
#: The vertices (north, east) of a polygon in local NED [m], in order; the last joins the first.
PolygonNE = tuple[tuple[float, float], ...]
#: A rectangle or a polygon.
FlyingArea = AreaNE | PolygonNE
#: Keep-out zones: polygons in local NED [m].
KeepOuts = tuple[PolygonNE, ...]

FloatArray = npt.NDArray[np.float64]
BoolArray = npt.NDArray[np.bool_]


def is_polygon(area: FlyingArea) -> bool:
    """Whether ``area`` is a polygon (vertex pairs), not a rectangle (four numbers)."""
    return isinstance(area[0], tuple)


def area_bounds(area: FlyingArea) -> AreaNE:
    """The rectangle that holds ``area``: (north_min, east_min, north_max, east_max) [m]."""
    if not is_polygon(area):
        return area  # type: ignore[return-value]
    v = np.array(area, dtype=np.float64)
    low, high = v.min(axis=0), v.max(axis=0)
    return float(low[0]), float(low[1]), float(high[0]), float(high[1])


def area_polygon(area: FlyingArea) -> PolygonNE:
    """The area as a polygon: a rectangle's four corners (counter-clockwise from south-west), a polygon as it is."""
    if is_polygon(area):
        return area  # type: ignore[return-value]
    n0, e0, n1, e1 = area_bounds(area)
    return ((n0, e0), (n1, e0), (n1, e1), (n0, e1))


def area_text(area: FlyingArea) -> str:
    """The area as a config file writes it (TOML): ``[n_min, e_min, n_max, e_max]`` or ``[[n, e], ...]``."""
    if is_polygon(area):
        return "[" + ", ".join(f"[{n!r}, {e!r}]" for n, e in area) + "]"  # type: ignore[misc]
    return "[" + ", ".join(repr(v) for v in area) + "]"


def inside_area(area: FlyingArea, north_m: npt.ArrayLike, east_m: npt.ArrayLike) -> BoolArray:
    """Whether each point (``north_m``, ``east_m``, broadcast together) lies in the area, its edge included."""
    north, east = np.asarray(north_m, dtype=np.float64), np.asarray(east_m, dtype=np.float64)
    if is_polygon(area):
        return _inside_polygon(np.array(area, dtype=np.float64), north, east)
    n_min, e_min, n_max, e_max = area
    inside: BoolArray = (n_min <= north) & (north <= n_max) & (e_min <= east) & (east <= e_max)
    return inside


def leaves_area(area: FlyingArea, start_ne_m: FloatArray, end_ne_m: FloatArray, margin_m: float) -> BoolArray:
    """(A,) whether the straight line from each start (A, 2) inside the area to its end (A, 2) leaves the area or
    passes within ``margin_m`` of one of its reflex (inner) corners: the end lies outside, the line crosses an
    edge, or grazes the corner a concave area turns round. A rectangle is convex: a line between two of its points
    stays in it and has no inner corner to graze (and bapf-nav gives up at once on a target outside it), so only a
    polygon is tested. A start outside, or a line that only touches a vertex or runs along an edge, does not
    leave."""
    if not is_polygon(area) or start_ne_m.shape[0] == 0:
        return np.zeros(start_ne_m.shape[0], dtype=bool)
    v = np.array(area, dtype=np.float64)
    start_in = _inside_polygon(v, start_ne_m[:, 0], start_ne_m[:, 1])
    end_in = _inside_polygon(v, end_ne_m[:, 0], end_ne_m[:, 1])
    a, b = v[None, :, :], np.roll(v, -1, axis=0)[None, :, :]  # (1, V, 2) each edge's ends
    p, q = start_ne_m[:, None, :], end_ne_m[:, None, :]  # (A, 1, 2)
    corners = _reflex_vertices(v)[None, :, :]  # (1, R, 2)
    with np.errstate(invalid="ignore", over="ignore"):  # non-finite lines compare False
        crosses = _crosses(p, q, a, b)
        grazes = _dist2_to_segment(corners, p, q) < margin_m * margin_m
    out: BoolArray = start_in & (~end_in | np.logical_or.reduce(crosses, axis=1) | np.logical_or.reduce(grazes, axis=1))
    return out


def _reflex_vertices(v: FloatArray) -> FloatArray:
    """(R, 2) the vertices of polygon ``v`` (V, 2) where its inside turns by more than 180 degrees."""
    before, after = np.roll(v, 1, axis=0), np.roll(v, -1, axis=0)
    turn = _side(before, v, after)  # > 0: a left turn
    orientation = float(np.sum(v[:, 0] * after[:, 1] - after[:, 0] * v[:, 1]))  # > 0: the vertices turn left
    reflex: FloatArray = v[turn * orientation < 0.0]
    return reflex


def outside_zones(
    area: FlyingArea | None, keepouts: KeepOuts, north_m: npt.ArrayLike, east_m: npt.ArrayLike
) -> BoolArray:
    """Whether each point (broadcast) lies outside the area (when there is one) or in a keep-out zone: where a
    target has no way and a goal is refused. A non-finite point is outside an area and in no keep-out zone."""
    out = in_keepout(keepouts, north_m, east_m)
    if area is not None:
        out |= ~inside_area(area, north_m, east_m)
    return out


@dataclass(frozen=True)
class ZoneConflict:
    """The first of some points that lies outside the flying area or in a keep-out zone (``zone_conflict``)."""

    index: int  #: which point
    keepout: int | None  #: the keep-out zone it lies in; None: it lies outside the area


def zone_conflict(
    area: FlyingArea | None, keepouts: KeepOuts, north_m: npt.ArrayLike, east_m: npt.ArrayLike
) -> ZoneConflict | None:
    """The first point (1-D ``north_m``, ``east_m``) outside the area, else the first in a keep-out zone (zones in
    order), else None. One rule for the service's goal check (``goal.route_outside_limits``), the world files' start
    and goal (``sim.world``) and ``apf-sim fly``'s (``sim.flycli``); each words it for its own source."""
    north = np.atleast_1d(np.asarray(north_m, dtype=np.float64))
    east = np.atleast_1d(np.asarray(east_m, dtype=np.float64))
    if area is not None:
        out = np.flatnonzero(~inside_area(area, north, east))
        if out.size:
            return ZoneConflict(index=int(out[0]), keepout=None)
    for k, zone in enumerate(keepouts):
        inside = np.flatnonzero(in_keepout((zone,), north, east))
        if inside.size:
            return ZoneConflict(index=int(inside[0]), keepout=k)
    return None


def in_keepout(keepouts: KeepOuts, north_m: npt.ArrayLike, east_m: npt.ArrayLike) -> BoolArray:
    """Whether each point (broadcast) lies in a keep-out zone, its edge included (a non-finite point does not)."""
    north, east = np.broadcast_arrays(np.asarray(north_m, dtype=np.float64), np.asarray(east_m, dtype=np.float64))
    out = np.zeros(north.shape, dtype=bool)
    for zone in keepouts:
        out |= _inside_polygon(np.array(zone, dtype=np.float64), north, east)
    return out


def meets_keepout(keepouts: KeepOuts, start_ne_m: FloatArray, end_ne_m: FloatArray, margin_m: float) -> BoolArray:
    """(A,) whether the straight line from each start (A, 2) to its end (A, 2) comes within ``margin_m`` of a
    keep-out zone: either end lies in one, the line crosses one of its edges, or passes closer than the margin."""
    out = np.zeros(start_ne_m.shape[0], dtype=bool)
    if not keepouts or out.size == 0:
        return out
    out |= in_keepout(keepouts, start_ne_m[:, 0], start_ne_m[:, 1])
    out |= in_keepout(keepouts, end_ne_m[:, 0], end_ne_m[:, 1])
    p, q = start_ne_m[:, None, :], end_ne_m[:, None, :]  # (A, 1, 2)
    m2 = margin_m * margin_m
    for zone in keepouts:
        v = np.array(zone, dtype=np.float64)
        a, b = v[None, :, :], np.roll(v, -1, axis=0)[None, :, :]
        with np.errstate(invalid="ignore", over="ignore"):  # non-finite lines compare False
            crosses = _crosses(p, q, a, b)
            # Segments that do not cross are closest at an end of one of them.
            near = np.minimum(
                np.minimum(_dist2_to_segment(a, p, q), _dist2_to_segment(b, p, q)),
                np.minimum(_dist2_to_segment(p, a, b), _dist2_to_segment(q, a, b)),
            )
        out |= np.logical_or.reduce(crosses | (near < m2), axis=1)
    return out


def zones_bound_lines(area: FlyingArea | None, keepouts: KeepOuts) -> bool:
    """Whether ``zones_block_line`` can block a line: the area is a polygon, or there is a keep-out zone."""
    return (area is not None and is_polygon(area)) or bool(keepouts)


def zones_block_line(
    area: FlyingArea | None, keepouts: KeepOuts, start_ne_m: FloatArray, end_ne_m: FloatArray, margin_m: float
) -> BoolArray:
    """(A,) whether the straight line from each start (A, 2) to its end (A, 2) is blocked by the zones: it leaves
    a polygonal flying area or passes within ``margin_m`` of its inner corners (``leaves_area``), or comes within
    ``margin_m`` of a keep-out zone (``meets_keepout``). bapf-nav's line of sight, batch and single agent alike."""
    out = meets_keepout(keepouts, start_ne_m, end_ne_m, margin_m)
    if area is not None:
        out |= leaves_area(area, start_ne_m, end_ne_m, margin_m)
    return out


def near_edges(polygon: PolygonNE, north_m: npt.ArrayLike, east_m: npt.ArrayLike, margin_m: float) -> BoolArray:
    """Whether each point (broadcast) lies closer than ``margin_m`` to an edge of ``polygon``. Only the edges that
    come within the margin of the points' bounding box are measured: a grid of 16 m inside a fence of hundreds of
    metres meets few of its edges, or none."""
    north, east = np.broadcast_arrays(np.asarray(north_m, dtype=np.float64), np.asarray(east_m, dtype=np.float64))
    pts = np.stack([north, east], axis=-1)
    out = np.zeros(north.shape, dtype=bool)
    m2 = margin_m * margin_m
    v = np.array(polygon, dtype=np.float64)
    w = np.roll(v, -1, axis=0)
    box = _finite_box(north, east)
    if box is None:
        return out
    n_lo, n_hi, e_lo, e_hi = box
    near = (
        (np.minimum(v[:, 0], w[:, 0]) <= n_hi + margin_m)
        & (np.maximum(v[:, 0], w[:, 0]) >= n_lo - margin_m)
        & (np.minimum(v[:, 1], w[:, 1]) <= e_hi + margin_m)
        & (np.maximum(v[:, 1], w[:, 1]) >= e_lo - margin_m)
    )
    with np.errstate(invalid="ignore", over="ignore"):  # non-finite points compare False
        for a, b in zip(v[near], w[near], strict=True):
            out |= _dist2_to_segment(pts, a, b) < m2
    return out


def _finite_box(north: FloatArray, east: FloatArray) -> tuple[float, float, float, float] | None:
    """(north min, north max, east min, east max) of the finite points, or None when there is none."""
    finite = np.isfinite(north) & np.isfinite(east)
    if not finite.any():
        return None
    n, e = north[finite], east[finite]
    return float(n.min()), float(n.max()), float(e.min()), float(e.max())


def _dist2_to_segment(p: FloatArray, a: FloatArray, b: FloatArray) -> FloatArray:
    """Squared distance from each point p to the segment a-b (broadcast over leading axes; last axis (north, east))."""
    ab = b - a
    length2 = np.maximum(np.einsum("...d,...d->...", ab, ab), 1e-300)
    t = np.clip(np.einsum("...d,...d->...", p - a, ab) / length2, 0.0, 1.0)
    off = p - a - t[..., None] * ab
    d2: FloatArray = np.einsum("...d,...d->...", off, off)
    return d2


def polygon_problem(vertices: PolygonNE) -> str | None:
    """Why ``vertices`` is no usable polygon (fewer than 3 vertices, no area, or edges that cross), or None."""
    if len(vertices) < 3:
        return "at least 3 vertices"
    v = np.array(vertices, dtype=np.float64)
    w = np.roll(v, -1, axis=0)
    twice_area = float(np.sum(v[:, 0] * w[:, 1] - w[:, 0] * v[:, 1]))
    if not math.isfinite(twice_area) or abs(twice_area) <= 1e-9:
        return "a polygon with an area"
    a, b = v[:, None, :], w[:, None, :]  # (V, 1, 2) against (1, V, 2)
    c, d = v[None, :, :], w[None, :, :]
    if _crosses(a, b, c, d).any():
        return "a polygon whose edges do not cross"
    return None


def _crosses(p: FloatArray, q: FloatArray, a: FloatArray, b: FloatArray) -> BoolArray:
    """Whether segment p-q properly crosses segment a-b (each strictly on both sides of the other: a touch at a
    vertex or a run along a line does not count); broadcast."""
    crosses: BoolArray = (_side(p, q, a) * _side(p, q, b) < 0.0) & (_side(a, b, p) * _side(a, b, q) < 0.0)
    return crosses


def _side(a: FloatArray, b: FloatArray, p: FloatArray) -> FloatArray:
    """Which side of the line a -> b each p lies on: the cross product's sign (0 on the line); broadcast."""
    side: FloatArray = (b[..., 0] - a[..., 0]) * (p[..., 1] - a[..., 1]) - (b[..., 1] - a[..., 1]) * (
        p[..., 0] - a[..., 0]
    )
    return side


def _inside_polygon(v: FloatArray, north: FloatArray, east: FloatArray) -> BoolArray:
    """Even-odd rule over the edges of the polygon ``v`` (V, 2), plus the points on an edge. One pass per edge,
    each vectorised over the points (a grid's cells: broadcast shapes, no (points x edges) temporaries). The ray
    runs north: an edge that spans none of the points' east values, or lies wholly south of them, neither crosses a
    ray nor holds a point, and is skipped (a grid deep inside a large fence meets few edges)."""
    north, east = np.broadcast_arrays(north, east)
    odd = np.zeros(north.shape, dtype=bool)
    on_edge = np.zeros(north.shape, dtype=bool)
    box = _finite_box(north, east)
    if box is None:
        return odd
    n_lo, _, e_lo, e_hi = box
    w = np.roll(v, -1, axis=0)
    spans = (
        (np.minimum(v[:, 1], w[:, 1]) <= e_hi)
        & (np.maximum(v[:, 1], w[:, 1]) >= e_lo)
        & (np.maximum(v[:, 0], w[:, 0]) >= n_lo)
    )
    with np.errstate(invalid="ignore", over="ignore", divide="ignore"):  # non-finite points compare False
        for (an, ae), (bn, be) in zip(v[spans].tolist(), w[spans].tolist(), strict=True):
            straddles = (ae > east) != (be > east)
            if ae != be:
                north_at = an + (east - ae) * ((bn - an) / (be - ae))
                odd ^= straddles & (north < north_at)
            cross = (bn - an) * (east - ae) - (be - ae) * (north - an)
            on_edge |= (
                (cross == 0.0)
                & (min(an, bn) <= north)
                & (north <= max(an, bn))
                & (min(ae, be) <= east)
                & (east <= max(ae, be))
            )
    inside: BoolArray = (odd | on_edge) & np.isfinite(north) & np.isfinite(east)
    return inside
