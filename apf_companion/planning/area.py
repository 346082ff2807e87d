"""The flying area (``PlannerParams.nav_area_ne_m``): which points lie in it, and which straight lines leave it.

Two forms, both in local NED [m]: a rectangle (north_min, east_min, north_max, east_max), and a polygon, a tuple of
(north, east) vertices in order (either direction), for a yard that is not a rectangle (an L-shaped field, a
plot between buildings). A polygon may be concave; it may not cross itself (``polygon_problem``).

One rule for every user of the area: the escape grid's blocked cells and its goal (``navfield``), bapf-nav's give-up
on a target outside it (``bapfnav``), its line of sight (``leaves_area``: a straight line that leaves a concave
area starts an escape), the service's refusal of such goals (``goal.route_outside_limits``) and the world files'
check of their start and goal (``sim.world``). Bounds and polygon edges are inside; a non-finite coordinate is
outside.
"""

from __future__ import annotations

import math

import numpy as np
import numpy.typing as npt

__all__ = [
    "AreaNE",
    "FlyingArea",
    "PolygonNE",
    "area_bounds",
    "area_text",
    "inside_area",
    "is_polygon",
    "leaves_area",
    "polygon_problem",
]

#: (north_min, east_min, north_max, east_max) in local NED [m].
AreaNE = tuple[float, float, float, float]
#: The vertices (north, east) of a polygon in local NED [m], in order; the last joins the first.
PolygonNE = tuple[tuple[float, float], ...]
#: A rectangle or a polygon.
FlyingArea = AreaNE | PolygonNE

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


def leaves_area(area: FlyingArea, start_ne_m: FloatArray, end_ne_m: FloatArray) -> BoolArray:
    """(A,) whether the straight line from each start (A, 2) inside the area to its end (A, 2) leaves the area: the
    end lies outside, or the line crosses an edge. A rectangle is convex: a line between two of its points stays in
    it (and bapf-nav gives up at once on a target outside it), so only a polygon is tested. A start outside, or a
    line that only touches a vertex or runs along an edge, does not leave."""
    if not is_polygon(area) or start_ne_m.shape[0] == 0:
        return np.zeros(start_ne_m.shape[0], dtype=bool)
    v = np.array(area, dtype=np.float64)
    start_in = _inside_polygon(v, start_ne_m[:, 0], start_ne_m[:, 1])
    end_in = _inside_polygon(v, end_ne_m[:, 0], end_ne_m[:, 1])
    a, b = v[None, :, :], np.roll(v, -1, axis=0)[None, :, :]  # (1, V, 2) each edge's ends
    p, q = start_ne_m[:, None, :], end_ne_m[:, None, :]  # (A, 1, 2)
    with np.errstate(invalid="ignore", over="ignore"):  # non-finite lines compare False
        crosses = (_side(p, q, a) * _side(p, q, b) < 0.0) & (_side(a, b, p) * _side(a, b, q) < 0.0)
    out: BoolArray = start_in & (~end_in | np.logical_or.reduce(crosses, axis=1))
    return out


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
    crosses = (_side(a, b, c) * _side(a, b, d) < 0.0) & (_side(c, d, a) * _side(c, d, b) < 0.0)
    if crosses.any():
        return "a polygon whose edges do not cross"
    return None


def _side(a: FloatArray, b: FloatArray, p: FloatArray) -> FloatArray:
    """Which side of the line a -> b each p lies on: the cross product's sign (0 on the line); broadcast."""
    side: FloatArray = (b[..., 0] - a[..., 0]) * (p[..., 1] - a[..., 1]) - (b[..., 1] - a[..., 1]) * (
        p[..., 0] - a[..., 0]
    )
    return side


def _inside_polygon(v: FloatArray, north: FloatArray, east: FloatArray) -> BoolArray:
    """Even-odd rule over the edges of the polygon ``v`` (V, 2), plus the points on an edge. One pass per edge,
    each vectorised over the points (a grid's cells: broadcast shapes, no (points x edges) temporaries)."""
    north, east = np.broadcast_arrays(north, east)
    odd = np.zeros(north.shape, dtype=bool)
    on_edge = np.zeros(north.shape, dtype=bool)
    with np.errstate(invalid="ignore", over="ignore", divide="ignore"):  # non-finite points compare False
        for (an, ae), (bn, be) in zip(v.tolist(), np.roll(v, -1, axis=0).tolist(), strict=True):
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
