"""The flying area's geometry (``planning.area``): a rectangle and the same rectangle as a polygon hold the same
points, edges included; a concave polygon's notch is outside; a line leaves a polygon where it crosses an edge or
ends outside; polygons that cross themselves or have no area are refused."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from apf_companion.planning import (
    ZoneConflict,
    area_bounds,
    area_polygon,
    area_text,
    inside_area,
    polygon_problem,
    zone_conflict,
)
from apf_companion.planning.area import (
    KeepOuts,
    _dist2_to_segment,
    in_keepout,
    leaves_area,
    meets_keepout,
    near_edges,
    outside_zones,
)

#: An L: 20 m x 20 m less its north-east 12 m x 12 m (north 8-20, east 8-20 is outside).
L_SHAPE = ((0.0, 0.0), (20.0, 0.0), (20.0, 8.0), (8.0, 8.0), (8.0, 20.0), (0.0, 20.0))

_coord = st.integers(-40, 40).map(lambda k: k * 0.25)  # on the rectangles' lattice: edge points are common


@settings(max_examples=300, deadline=None)
@given(
    n0=_coord,
    e0=_coord,
    dn=st.integers(1, 40).map(lambda k: k * 0.25),
    de=st.integers(1, 40).map(lambda k: k * 0.25),
    points=st.lists(st.tuples(_coord, _coord), min_size=1, max_size=30),
    clockwise=st.booleans(),
)
def test_a_rectangle_as_a_polygon_holds_the_same_points(
    n0: float, e0: float, dn: float, de: float, points: list[tuple[float, float]], clockwise: bool
) -> None:
    rect = (n0, e0, n0 + dn, e0 + de)
    corners = [(n0, e0), (n0 + dn, e0), (n0 + dn, e0 + de), (n0, e0 + de)]
    polygon = tuple(reversed(corners) if clockwise else corners)
    pts = np.array([*points, (math.nan, e0), (n0, math.inf)])
    assert inside_area(rect, pts[:, 0], pts[:, 1]).tolist() == inside_area(polygon, pts[:, 0], pts[:, 1]).tolist()
    assert area_bounds(polygon) == rect
    assert area_polygon(rect) == tuple(corners) and area_polygon(polygon) == polygon
    # Convex: a line from inside leaves exactly when it ends outside (the polygon's crossing test agrees); the
    # rectangle's form is not tested at all (bapf-nav gives up on a target outside it).
    start_in = inside_area(rect, pts[:, 0], pts[:, 1])
    end_in = start_in[::-1]
    assert leaves_area(polygon, pts, pts[::-1], 0.6).tolist() == (start_in & ~end_in).tolist()  # no inner corner
    assert not leaves_area(rect, pts, pts[::-1], 0.6).any()


def test_an_l_shaped_area_leaves_out_its_notch_and_holds_its_edges() -> None:
    north = np.array([1.0, 15.0, 15.0, 4.0, 8.0, 8.0, 14.0, 20.0, 20.1, -0.1, math.nan])
    east = np.array([1.0, 4.0, 15.0, 15.0, 14.0, 8.0, 8.0, 5.0, 5.0, 3.0, 1.0])
    assert inside_area(L_SHAPE, north, east).tolist() == [
        True, True, False, True,  # the arms hold their points; the notch is outside
        True, True, True, True,  # on an inner edge, the inner corner, the other inner edge, the outer edge
        False, False, False,  # just beyond the outer edges; not a number
    ]  # fmt: skip
    # A grid of cell centres (broadcast): the notch's share of the bounds, 144 of 400 m^2.
    centres = np.arange(0.25, 20.0, 0.5)
    inside = inside_area(L_SHAPE, centres[:, None], centres[None, :])
    assert inside.shape == (40, 40) and int((~inside).sum()) == 24 * 24
    assert area_bounds(L_SHAPE) == (0.0, 0.0, 20.0, 20.0)
    assert area_text(L_SHAPE).startswith("[[0.0, 0.0], [20.0, 0.0], [20.0, 8.0]")
    assert area_text((0.0, -1.5, 3.0, 4.0)) == "[0.0, -1.5, 3.0, 4.0]"


def test_a_line_leaves_a_concave_area_across_its_notch() -> None:
    starts = np.array([[16.0, 2.0], [16.0, 2.0], [2.0, 16.0], [16.0, 2.0], [16.0, 2.0], [15.0, 15.0], [4.0, 4.0]])
    ends = np.array([[2.0, 16.0], [2.0, 2.0], [2.0, 2.0], [25.0, 2.0], [8.0, 8.0], [2.0, 2.0], [4.0, 4.0]])
    assert leaves_area(L_SHAPE, starts, ends, 0.0).tolist() == [
        True,  # across the notch, both ends inside
        False,
        False,  # within an arm
        True,  # out across the outer edge
        False,  # to the inner corner (on the edge: inside)
        False,  # a start outside: bapf-nav does not hold an agent outside by its line
        False,  # no line at all
    ]
    along_edge = leaves_area(L_SHAPE, np.array([[8.0, 12.0]]), np.array([[8.0, 19.0]]), 0.0)
    assert not along_edge.any()  # along the inner edge: inside all the way
    assert leaves_area(L_SHAPE, np.zeros((0, 2)), np.zeros((0, 2)), 0.6).shape == (0,)
    # Past the inner corner (8, 8) at 0.4 m: inside all the way, but within a margin of 0.6 m of the corner.
    graze = (np.array([[16.0, 7.6]]), np.array([[7.6, 7.6]]))
    assert not leaves_area(L_SHAPE, *graze, 0.0).any() and leaves_area(L_SHAPE, *graze, 0.6).all()
    assert not leaves_area(L_SHAPE, *graze, 0.3).any()


@pytest.mark.parametrize(
    ("vertices", "problem"),
    [
        (((0.0, 0.0), (5.0, 0.0)), "at least 3 vertices"),
        (((0.0, 0.0), (5.0, 0.0), (10.0, 0.0)), "with an area"),
        (((0.0, 0.0), (5.0, 5.0), (5.0, 0.0), (0.0, 5.0)), "with an area"),  # a symmetric bow tie: no net area
        (((0.0, 0.0), (6.0, 5.0), (6.0, 0.0), (0.0, 3.0)), "do not cross"),  # a bow tie with net area
        (((0.0, 0.0), (5.0, 0.0), (5.0, math.nan)), "with an area"),
    ],
)
def test_polygons_that_cross_themselves_or_have_no_area_are_refused(
    vertices: tuple[tuple[float, float], ...], problem: str
) -> None:
    why = polygon_problem(vertices)
    assert why is not None and problem in why
    assert polygon_problem(L_SHAPE) is None
    assert polygon_problem(tuple(reversed(L_SHAPE))) is None


def test_keep_out_zones_are_met_by_lines_that_cross_end_in_or_pass_within_the_margin() -> None:
    square: KeepOuts = (((7.0, -3.0), (13.0, -3.0), (13.0, 3.0), (7.0, 3.0)),)
    assert in_keepout(square, [10.0, 13.0, 14.0, math.nan], [0.0, 3.0, 0.0, 0.0]).tolist() == [True, True, False, False]
    assert not in_keepout((), [10.0], [0.0]).any()
    # Where a target has no way: outside the area or in a keep-out zone (a non-finite point is outside the area).
    at_n, at_e = [10.0, 1.0, 30.0, math.nan], [0.0, 0.0, 0.0, 0.0]
    assert outside_zones(None, square, at_n, at_e).tolist() == [True, False, False, False]
    assert outside_zones((-5.0, -5.0, 25.0, 5.0), square, at_n, at_e).tolist() == [True, False, True, True]
    starts = np.array([[0.0, 0.0], [0.0, 3.5], [0.0, 3.7], [10.0, 0.0], [0.0, 0.0], [20.0, 20.0]])
    ends = np.array([[20.0, 0.0], [20.0, 3.5], [20.0, 3.7], [20.0, 20.0], [10.0, 1.0], [30.0, 30.0]])
    assert meets_keepout(square, starts, ends, 0.6).tolist() == [
        True,  # across
        True,  # along it, 0.5 m off: within the margin
        False,  # 0.7 m off
        True,  # from inside
        True,  # into it
        False,  # far away
    ]
    assert meets_keepout(square, starts[1:2], ends[1:2], 0.4).tolist() == [False]
    assert not meets_keepout((), starts, ends, 0.6).any()
    north = np.array([7.0, 6.5, 6.3, 10.0, 10.0])
    assert near_edges(square[0], north, np.array([0.0, 0.0, 0.0, 0.0, 2.5]), 0.6).tolist() == [
        True, True, False, False, True,
    ]  # fmt: skip


def _inside_every_edge(v: np.ndarray, north: np.ndarray, east: np.ndarray) -> np.ndarray:
    """The even-odd rule over every edge, none skipped (what ``_inside_polygon`` did before it skipped edges)."""
    odd = np.zeros(north.shape, dtype=bool)
    on_edge = np.zeros(north.shape, dtype=bool)
    for (an, ae), (bn, be) in zip(v.tolist(), np.roll(v, -1, axis=0).tolist(), strict=True):
        straddles = (ae > east) != (be > east)
        if ae != be:
            odd ^= straddles & (north < an + (east - ae) * ((bn - an) / (be - ae)))
        cross = (bn - an) * (east - ae) - (be - ae) * (north - an)
        box = (min(an, bn) <= north) & (north <= max(an, bn)) & (min(ae, be) <= east) & (east <= max(ae, be))
        on_edge |= (cross == 0.0) & box
    return odd | on_edge


@settings(max_examples=80, deadline=None)
@given(
    st.lists(st.tuples(st.floats(5.0, 300.0), st.floats(0.0, 6.28)), min_size=3, max_size=40, unique_by=lambda p: p[1]),
    st.tuples(st.floats(-320.0, 320.0), st.floats(-320.0, 320.0)),
    st.floats(0.05, 3.0),
)
def test_skipping_far_edges_changes_no_answer(
    rays: list[tuple[float, float]], corner: tuple[float, float], margin_m: float
) -> None:
    """A 16 m grid anywhere in or around a star-shaped fence of up to 300 m (vertices and grid lines on the same
    0.25 m lattice, so points on edges and vertices occur): the same insideness and nearness to the edges as with
    every edge measured."""
    ring = tuple(
        (round(r * math.cos(a) * 4) / 4, round(r * math.sin(a) * 4) / 4) for r, a in sorted(rays, key=lambda p: p[1])
    )
    if polygon_problem(ring) is not None:
        return
    v = np.array(ring)
    cells = (np.round(np.array(corner) * 4) / 4)[:, None] + np.arange(64)[None, :] * 0.25
    north, east = np.broadcast_arrays(cells[0][:, None], cells[1][None, :])
    assert inside_area(ring, north, east).tolist() == _inside_every_edge(v, north, east).tolist()
    every = np.zeros(north.shape, dtype=bool)
    pts = np.stack([north, east], axis=-1)
    for a, b in zip(v, np.roll(v, -1, axis=0), strict=True):
        every |= _dist2_to_segment(pts, a, b) < margin_m * margin_m
    assert near_edges(ring, north, east, margin_m).tolist() == every.tolist()


@pytest.mark.parametrize("side", ["north", "south", "east", "west"])
def test_an_edge_just_beyond_a_grid_is_near_its_border_cells(side: str) -> None:
    """A 100 m square fence whose edge runs 0.5 m beyond a 16 m grid's border cells: those cells (and only those)
    are within a 0.6 m margin, whichever side the edge is on."""
    square = ((-50.0, -50.0), (50.0, -50.0), (50.0, 50.0), (-50.0, 50.0))
    lo = {"north": (33.5, 0.0), "south": (-49.5, 0.0), "east": (0.0, 33.5), "west": (0.0, -49.5)}[side]
    cells = np.array(lo)[:, None] + np.arange(65)[None, :] * 0.25  # 16 m: north/east border 0.5 m from the edge
    north, east = np.broadcast_arrays(cells[0][:, None], cells[1][None, :])
    near = near_edges(square, north, east, 0.6)
    border = {"north": near[-1, :], "south": near[0, :], "east": near[:, -1], "west": near[:, 0]}[side]
    assert border.all() and near.sum() == border.size
    assert inside_area(square, north, east).all()


def test_zone_conflict_names_the_first_point_outside_the_area_then_the_first_in_a_keep_out_zone() -> None:
    """One rule for the service's goal check, the world files and ``apf-sim fly``: the area first, then the zones in
    order; non-finite points lie outside an area and in no zone."""
    area = (0.0, 0.0, 10.0, 10.0)
    zones = (((2.0, 2.0), (4.0, 2.0), (4.0, 4.0), (2.0, 4.0)), ((6.0, 6.0), (8.0, 6.0), (8.0, 8.0), (6.0, 8.0)))
    assert zone_conflict(area, zones, [1.0, 5.0], [1.0, 9.0]) is None
    assert zone_conflict(area, zones, [7.0, 3.0, 11.0], [7.0, 3.0, 0.0]) == ZoneConflict(index=2, keepout=None)
    assert zone_conflict(area, zones, [1.0, 7.0, 3.0], [1.0, 7.0, 3.0]) == ZoneConflict(index=2, keepout=0)
    assert zone_conflict(None, zones, [7.0], [7.0]) == ZoneConflict(index=0, keepout=1)
    assert zone_conflict(None, zones, [math.nan], [3.0]) is None
    assert zone_conflict(area, (), 5.0, math.inf) == ZoneConflict(index=0, keepout=None)
