"""The intersection (or union) of a fence's inclusion zones, as one polygon for bapf-nav's flying area (local NED
[m]), and its exclusion zones grown by the fence's margin.

ArduPilot keeps the vehicle inside every inclusion zone (``libraries/AC_Fence/AC_PolyFence_loader.cpp``,
``breached``: outside any one of them is a breach), unless FENCE_OPTIONS bit 1 asks for their union; PX4 keeps it
inside every one too (``src/modules/navigator/geofence.cpp``, ``isInsidePolygonOrCircle`` ANDs every zone). The
intersection is the area both allow; under the union option, the union. The circle round home (ArduPilot's
FENCE_TYPE circle, PX4's GF_MAX_HOR_DIST) is checked apart from the zones, so it clips either (``bound``).

Clipping concave polygons against each other is a job for a geometry engine (collinear edges, touching vertices,
results in several pieces): shapely (GEOS) does it. Of several pieces, the one that holds the vehicle is the area:
the others cannot be reached without leaving it. A piece of more than ``MAX_AREA_VERTICES`` vertices (two circles'
32-gons clip to up to 64 and more) is shrunk by ``t`` and then simplified by ``t`` (Douglas-Peucker moves the
boundary by at most ``t``), so the result stays inside the intersection; ``t`` grows from 5 cm until it fits.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

# Imported with the service (0.1-0.2 s at start), not when a fence first needs it: an import in flight would hold
# the event loop, and the cycles with it, for as long.
import shapely
from shapely.geometry import Point, Polygon

from apf_companion.planning import PolygonNE
from apf_companion.planning.params import MAX_AREA_VERTICES

__all__ = ["grown_keepout", "inclusion_area"]

#: Vertices are snapped to this grid before a margin's offset [m].
SNAP_M = 1e-6
#: A margin's offset may miss the exact one by this much [m] (GEOS's mitre at a needle-sharp vertex: 30 um seen);
#: a fence's vertices are placed to a centimetre.
EXACT_TO_M = 1e-3
#: Shrink-and-simplify tolerances tried, in turn, for a piece with too many vertices [m].
SIMPLIFY_STEPS_M = (0.05, 0.1, 0.2, 0.4, 0.8)


def inclusion_area(
    zones: Sequence[PolygonNE],
    vehicle_ne_m: tuple[float, float],
    inset_m: float = 0.0,
    *,
    union: bool = False,
    bound: PolygonNE | None = None,
) -> PolygonNE | str:
    """The piece of the zones' intersection (their ``union``), clipped to ``bound`` and moved in by ``inset_m``
    [m] (the fence's margin), that holds the vehicle, as a polygon of at most ``MAX_AREA_VERTICES`` vertices inside
    it; or why there is none. The zones are valid simple polygons (``polygon_problem``). The inset's mitre joins
    cut reflex corners deeper than a round offset would: never wider than the margin allows."""
    what = "union" if union else "intersection"
    try:
        shapes = [Polygon(zone) for zone in zones]
        common = shapely.union_all(shapes) if union else shapely.intersection_all(shapes)
        if bound is not None:
            common = common.intersection(Polygon(bound))
        exact = None
        if inset_m > 0.0:  # snapped first (``grown_keepout``); must lie in the round (exact) inset, to a millimetre
            exact = common.buffer(-inset_m, quad_segs=16).buffer(EXACT_TO_M)
            common = _snapped(common).buffer(-(inset_m + SNAP_M), join_style="mitre")
    except shapely.errors.GEOSException as err:  # a zone GEOS cannot take (polygon_problem passed it)
        return f"the inclusion zones cannot be {'united' if union else 'intersected'} ({err})"
    pieces = [g for g in getattr(common, "geoms", [common]) if isinstance(g, Polygon) and g.area > 0.0]
    if not pieces:
        return "the inclusion zones do not overlap"
    vehicle = Point(vehicle_ne_m)
    holding = [p for p in pieces if p.covers(vehicle)]
    if not holding:
        return f"the vehicle is outside the inclusion zones' {what}"
    piece = holding[0]
    if exact is not None and not exact.covers(piece):
        return f"the inclusion zones' {what} cannot be moved in by the margin"
    if piece.interiors:  # an intersection of simple zones has none; a union may (zones round a courtyard)
        return f"the inclusion zones' {what} has a hole"
    fitted = _fit(piece, vehicle)
    if fitted is None:
        return f"the inclusion zones' {what} needs more than {MAX_AREA_VERTICES} vertices"
    return fitted


def grown_keepout(zone: PolygonNE, grow_m: float) -> PolygonNE | None:
    """An exclusion zone grown by ``grow_m`` [m] (the fence's margin) with mitre joins, which cover the round
    offset; None when GEOS cannot grow it, the result does not cover the round offset (checked against its
    inscribed 64-gon arcs: a residue of at most 0.12 % of the margin), or it needs more than ``MAX_AREA_VERTICES``
    vertices even when grown by a tolerance more and simplified by it (which stays outside the grown zone).
    Vertices are first snapped to a micrometre (``SNAP_M``: far below the 1 cm of a fence's 1e-7 degrees), which
    drops near-duplicates whose direction the mitre would follow; the growth adds the snap back."""
    try:
        base = _snapped(Polygon(zone))
        grown = base.buffer(grow_m + SNAP_M, join_style="mitre")
        must_cover = Polygon(zone).buffer(grow_m, quad_segs=16)
        for t in (0.0, *SIMPLIFY_STEPS_M):
            fitted = grown if t == 0.0 else base.buffer(grow_m + SNAP_M + t, join_style="mitre").simplify(t)
            if (
                isinstance(fitted, Polygon)
                and _vertex_count(fitted) <= MAX_AREA_VERTICES
                and fitted.covers(grown)
                and fitted.buffer(EXACT_TO_M).covers(must_cover)
            ):
                return _vertices(fitted)
    except shapely.errors.GEOSException:
        return None
    return None


def _snapped(geometry: shapely.Geometry) -> shapely.Geometry:
    """``geometry`` with its vertices on the ``SNAP_M`` grid. GEOS may warn through numpy (a zero-length edge
    divides by zero) on degenerate zones; the result is checked against the exact offset where it is used."""
    with np.errstate(divide="ignore", invalid="ignore"):
        return shapely.set_precision(geometry, SNAP_M)


def _fit(piece: Polygon, vehicle: Point) -> PolygonNE | None:
    """``piece``'s vertices, or those of a polygon inside it with at most ``MAX_AREA_VERTICES`` (module docstring)."""
    if _vertex_count(piece) <= MAX_AREA_VERTICES:
        return _vertices(piece)
    for t in SIMPLIFY_STEPS_M:
        smaller = piece.buffer(-t, join_style="mitre").simplify(t, preserve_topology=True)
        if (
            isinstance(smaller, Polygon)
            and not smaller.is_empty
            and _vertex_count(smaller) <= MAX_AREA_VERTICES
            and piece.covers(smaller)
            and smaller.covers(vehicle)
        ):
            return _vertices(smaller)
    return None


def _vertex_count(polygon: Polygon) -> int:
    return len(polygon.exterior.coords) - 1  # the ring repeats its first vertex


def _vertices(polygon: Polygon) -> PolygonNE:
    return tuple((float(n), float(e)) for n, e in polygon.exterior.coords[:-1])
