"""The autopilot's fence parameters, without sockets: what ArduPilot's FENCE_* and PX4's GF_* say is enforced
(fencelimits), how the fence's zones take them (the margin moves edges, the circle round home, the ceiling), the
reader's parameter stage (repeats, give-up, fallback) and goals refused beyond the fence's bounds."""

from __future__ import annotations

import dataclasses
import math
import struct

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from pymavlink.dialects.v20 import ardupilotmega as mavlink
from shapely.geometry import Polygon

from apf_companion.autopilot import Autopilot
from apf_companion.fence import FenceArea, FenceOutcome, fence_area
from apf_companion.fenceclip import grown_keepout, inclusion_area
from apf_companion.fencelimits import FenceLimits, ParamRead, ReadStage, fence_limits, param_float
from apf_companion.fencereader import FenceReader, FenceReaderParams
from apf_companion.goal import FenceBounds, GlobalReference, Route, route_outside_limits
from apf_companion.links.messages import HomePosition, SysStatus
from apf_companion.outbox import Outbox
from apf_companion.planning import inside_area
from tests.service.test_fence import (
    AP,
    ENFORCED,
    L_SHAPE,
    REF,
    VERTEX_OUT,
    _answer,
    _download,
    _give_params,
    _latlon_e7,
    _polygon,
    _reader,
)

AP_DEFAULTS = {
    "FENCE_ENABLE": 1.0,
    "FENCE_TYPE": 7.0,
    "FENCE_RADIUS": 300.0,
    "FENCE_ALT_MAX": 100.0,
    "FENCE_MARGIN": 2.0,
}


def _limits(profile: Autopilot, values: dict[str, float], *, switched_on: bool = False) -> FenceLimits:
    limits = fence_limits(profile, values, switched_on=switched_on)
    assert isinstance(limits, FenceLimits), limits
    return limits


def test_ardupilot_fence_parameters_say_what_is_enforced() -> None:
    """AC_Fence.cpp: FENCE_TYPE's bits configure the ceiling (1), the circle round home (2) and the uploaded zones
    (4). The zones are used whatever FENCE_ENABLE says (4.6 switches fences on at run time without it); the circle
    and the ceiling, configured on every Copter by default, only with FENCE_ENABLE 1. The ceiling kept is
    FENCE_ALT_MAX less FENCE_MARGIN; FENCE_MARGIN_XY, when positive, is the horizontal margin."""
    on = _limits(Autopilot.ARDUPILOT, AP_DEFAULTS)
    assert on == FenceLimits(True, 2.0, 300.0, 98.0, "FENCE_MARGIN 2 m, circle of 300 m round home, ceiling 100 m")
    off = _limits(Autopilot.ARDUPILOT, AP_DEFAULTS | {"FENCE_ENABLE": 0.0})
    assert (off.zones, off.home_radius_m, off.ceiling_m) == (True, None, None)
    assert off.note == "FENCE_MARGIN 2 m, FENCE_ENABLE 0: no circle round home or ceiling"
    ceiling_only = _limits(Autopilot.ARDUPILOT, AP_DEFAULTS | {"FENCE_TYPE": 1.0})
    assert (ceiling_only.zones, ceiling_only.home_radius_m, ceiling_only.ceiling_m) == (False, None, 98.0)
    assert ceiling_only.enforced and "uploaded zones not used" in ceiling_only.note
    assert _limits(Autopilot.ARDUPILOT, AP_DEFAULTS | {"FENCE_TYPE": 0.0}).enforced is False
    assert _limits(Autopilot.ARDUPILOT, AP_DEFAULTS | {"FENCE_TYPE": 3.0, "FENCE_ENABLE": 0.0}).enforced is False
    xy = _limits(Autopilot.ARDUPILOT, AP_DEFAULTS | {"FENCE_MARGIN_XY": 3.0})
    assert (xy.margin_m, xy.ceiling_m) == (3.0, 98.0) and xy.note.startswith("FENCE_MARGIN_XY 3 m")
    union = _limits(Autopilot.ARDUPILOT, AP_DEFAULTS | {"FENCE_OPTIONS": 3.0})
    assert union.union and union.note.endswith("FENCE_OPTIONS union of inclusion zones")
    assert fence_limits(Autopilot.ARDUPILOT, AP_DEFAULTS | {"FENCE_MARGIN": math.nan}) == "FENCE_MARGIN is nan"
    assert fence_limits(Autopilot.ARDUPILOT, AP_DEFAULTS | {"FENCE_OPTIONS": math.inf}) == "FENCE_OPTIONS is inf"
    assert fence_limits(Autopilot.ARDUPILOT, {"FENCE_ENABLE": 1.0}) == "FENCE_TYPE is None"


def test_px4_geofence_parameters_say_what_is_enforced() -> None:
    """geofence_params.c: GF_MAX_HOR_DIST / GF_MAX_VER_DIST 0 are off (the default), and count only while
    GF_ACTION is not 0 (None: PX4 checks no breach); the uploaded zones always."""
    px4 = {"GF_ACTION": 2.0, "GF_MAX_HOR_DIST": 0.0, "GF_MAX_VER_DIST": 0.0}
    assert _limits(Autopilot.PX4, px4) == FenceLimits(True, 0.0, None, None, "no circle, no ceiling")
    both = _limits(Autopilot.PX4, px4 | {"GF_MAX_HOR_DIST": 150.0, "GF_MAX_VER_DIST": 60.0})
    assert (both.home_radius_m, both.ceiling_m, both.margin_m) == (150.0, 60.0, 0.0)
    assert both.note == "circle of 150 m round home, ceiling 60 m"
    warn = _limits(Autopilot.PX4, px4 | {"GF_ACTION": 1.0, "GF_MAX_VER_DIST": 60.0})  # a warning is a check too
    assert (warn.home_radius_m, warn.ceiling_m, warn.note) == (None, 60.0, "ceiling 60 m")
    off = _limits(Autopilot.PX4, px4 | {"GF_ACTION": 0.0, "GF_MAX_HOR_DIST": 150.0, "GF_MAX_VER_DIST": 60.0})
    assert off == FenceLimits(True, 0.0, None, None, "GF_ACTION 0 (none): no circle round home or ceiling")
    circle_off = _limits(Autopilot.PX4, px4 | {"GF_ACTION": 0.0, "GF_MAX_HOR_DIST": 150.0})
    assert circle_off.note == "GF_ACTION 0 (none): no circle round home" and circle_off.zones
    assert _limits(Autopilot.PX4, px4 | {"GF_ACTION": 0.0}).note == "no circle, no ceiling"


def test_px4_integer_parameters_arrive_as_their_bytes() -> None:
    """PX4 puts an INT32's bytes in PARAM_VALUE's float (PARAM_ENCODE_BYTEWISE); ArduPilot casts the value."""
    (as_float,) = struct.unpack("<f", struct.pack("<i", 3))
    assert as_float != 3.0 and param_float(as_float, mavlink.MAV_PARAM_TYPE_INT32, Autopilot.PX4) == 3.0
    (minus,) = struct.unpack("<f", struct.pack("<i", -1))
    assert param_float(minus, mavlink.MAV_PARAM_TYPE_INT32, Autopilot.PX4) == -1.0
    assert param_float(3.0, mavlink.MAV_PARAM_TYPE_INT32, Autopilot.ARDUPILOT) == 3.0
    assert param_float(150.0, mavlink.MAV_PARAM_TYPE_REAL32, Autopilot.PX4) == 150.0


def test_the_parameter_read_repeats_the_unanswered_and_gives_up() -> None:
    read = ParamRead(("A", "B", "C"), timeout_s=1.0, retries=2)
    assert read.due(0.0) == ()  # not started
    read.start()
    assert read.due(0.0) == ("A", "B", "C") and read.due(0.5) == ()
    read.on_value("B", 1.0)
    read.on_value("X", 9.0)  # not asked for: not kept
    assert read.due(1.0) == ("A", "C") and read.values == {"B": 1.0}
    read.on_value("A", 2.0)
    read.on_value("C", 3.0)
    assert read.stage is ReadStage.DONE and read.values == {"A": 2.0, "B": 1.0, "C": 3.0}
    read.start()
    for t in (0.0, 1.0, 2.0):
        assert read.due(t) == ("A", "B", "C")
    assert read.due(3.0) == () and _stage(read) is ReadStage.FAILED and read.reason == "no A after 3 requests"


def test_optional_parameters_an_older_autopilot_lacks_are_absent_after_two_requests() -> None:
    """FENCE_MARGIN_XY and FENCE_OPTIONS (ArduPilot 4.6): an older firmware stays silent about them."""
    read = ParamRead(("A",), timeout_s=1.0, retries=5, optional=("X", "Y"))
    read.start()
    assert read.due(0.0) == ("A", "X", "Y")
    read.on_value("A", 1.0)
    read.on_value("Y", 2.0)
    assert read.due(1.0) == ("X",)
    assert read.due(2.0) == () and _stage(read) is ReadStage.DONE and read.values == {"A": 1.0, "Y": 2.0}


def _last(results: list[FenceArea]) -> FenceArea:
    """The last result told (a call, so that mypy does not narrow it across the reads)."""
    return results[-1]


def _stage(read: ParamRead) -> ReadStage:
    return read.stage


def _inset_ok(area: tuple[tuple[float, float], ...], zone: tuple[tuple[float, float], ...], inset_m: float) -> None:
    """``area`` lies inside ``zone`` moved in by ``inset_m`` and covers most of it (to 2 cm: the zone went through
    latitude/longitude in 1e-7 degrees)."""
    exact = Polygon(zone).buffer(-inset_m)  # round joins: the exact inset
    got = Polygon(area)
    assert exact.buffer(0.02).covers(got)
    assert got.area >= 0.97 * exact.area


def test_the_margin_moves_the_area_in_by_what_the_planners_clearance_does_not_keep() -> None:
    """FENCE_MARGIN 2 m with bapf-nav's C = 0.6 m: the L's edges move in by 1.4 m; with C >= the margin, nothing
    moves. The ceiling and the note follow the parameters."""
    params = AP_DEFAULTS | {"FENCE_TYPE": 5.0}  # polygons and the ceiling, no circle
    area = fence_area(_polygon(L_SHAPE), REF, (10.0, 0.0), _limits(Autopilot.ARDUPILOT, params), None, 0.6)
    assert area.outcome is FenceOutcome.USED and area.polygon_ne_m is not None and not area.provisional
    _inset_ok(area.polygon_ne_m, L_SHAPE, 1.4)
    assert area.bounds == FenceBounds(98.0, None)
    assert area.note == "inclusion polygon, 1.4 m in from its edges, 6 vertices; FENCE_MARGIN 2 m, ceiling 100 m"
    wide_c = fence_area(_polygon(L_SHAPE), REF, (10.0, 0.0), _limits(Autopilot.ARDUPILOT, params), None, 2.5)
    assert wide_c.polygon_ne_m is not None
    assert np.abs(np.array(wide_c.polygon_ne_m) - np.array(L_SHAPE)).max() < 0.01


def test_a_vehicle_within_the_margin_gets_the_uninset_area_for_now() -> None:
    """At (10, -2.5), 0.5 m from the L's west edge: the area without the margin, provisional (read again)."""
    params = AP_DEFAULTS | {"FENCE_TYPE": 4.0}
    area = fence_area(_polygon(L_SHAPE), REF, (10.0, -2.5), _limits(Autopilot.ARDUPILOT, params), None, 0.6)
    assert area.outcome is FenceOutcome.USED and area.provisional
    assert area.polygon_ne_m is not None and len(area.polygon_ne_m) == 6


def test_exclusion_zones_grow_by_the_margin() -> None:
    bed = ((3.0, 11.5), (6.5, 11.5), (6.5, 14.5), (3.0, 14.5))
    items = [*_polygon(L_SHAPE), *_polygon(bed, VERTEX_OUT, first=6)]
    params = AP_DEFAULTS | {"FENCE_TYPE": 4.0}
    area = fence_area(items, REF, (10.0, 0.0), _limits(Autopilot.ARDUPILOT, params), None, 0.6)
    (grown,) = area.keepouts_ne_m
    assert Polygon(grown).covers(Polygon(bed).buffer(1.4 - 0.02))  # the round offset inside the mitred one
    assert Polygon(bed).buffer(1.4 + 0.02, join_style="mitre").covers(Polygon(grown))
    beside = fence_area(items, REF, (2.5, 13.0), _limits(Autopilot.ARDUPILOT, params), None, 0.6)
    assert beside.provisional and np.abs(np.array(beside.keepouts_ne_m[0]) - np.array(bed)).max() < 0.01


@settings(max_examples=60, deadline=None)
@given(
    st.lists(st.tuples(st.floats(-20, 20), st.floats(-20, 20)), min_size=3, max_size=12),
    st.floats(0.05, 5.0),
)
def test_a_grown_keep_out_zone_always_covers_the_exact_offset(points: list[tuple[float, float]], grow_m: float) -> None:
    """Any simple polygon (the convex hull of random points), any margin: never narrower than the round offset."""
    hull = Polygon(points).convex_hull
    if not isinstance(hull, Polygon) or hull.area < 0.5:
        return
    zone = tuple((float(n), float(e)) for n, e in hull.exterior.coords[:-1])
    grown = grown_keepout(zone, grow_m)
    if grown is None:  # GEOS could not: the zone is used as uploaded (said), never a narrower one
        return
    assert len(grown) <= 64
    assert Polygon(grown).buffer(1e-3).covers(hull.buffer(grow_m, quad_segs=16))


@settings(max_examples=60, deadline=None)
@given(
    st.lists(
        st.tuples(st.floats(0.5, 20), st.floats(0, 2 * math.pi)), min_size=3, max_size=16, unique_by=lambda p: p[1]
    ),
    st.floats(0.05, 3.0),
)
def test_an_inset_area_always_lies_within_the_exact_inset(rays: list[tuple[float, float]], inset_m: float) -> None:
    """Any star-shaped polygon (concave corners included), any margin: the area never reaches nearer an edge."""
    ring = [(r * math.cos(a), r * math.sin(a)) for r, a in sorted(rays, key=lambda p: p[1])]
    zone = Polygon(ring)
    if not zone.is_valid or zone.area < 0.5:
        return
    exact = zone.buffer(-inset_m, quad_segs=32)
    if exact.is_empty:
        return
    inner = exact.representative_point()
    area = inclusion_area([tuple(ring)], (inner.x, inner.y), inset_m)
    if isinstance(area, str):  # too many vertices, or GEOS could not: the zone is used as uploaded (said)
        return
    assert exact.buffer(1e-3).covers(Polygon(area))


def test_the_circle_round_home_bounds_goals_and_clips_an_inclusion_zone() -> None:
    """FENCE_TYPE 2 alone: the circle (less the inset) is the area, hundreds of metres across by default and then
    planned on bapf-nav's moving grid; goals outside it are refused. With the L as well: the circle (here 12 m,
    round the vehicle) clips it."""
    home = _latlon_e7(10.0, 5.0)
    alone = _limits(Autopilot.ARDUPILOT, AP_DEFAULTS | {"FENCE_TYPE": 2.0, "FENCE_RADIUS": 40.0})
    area = fence_area([], REF, (10.0, 5.0), alone, home, 0.6)
    assert area.outcome is FenceOutcome.USED and area.polygon_ne_m is not None and len(area.polygon_ne_m) == 32
    assert area.note.startswith("inclusion circle, 1.4 m in from its edges, 32 vertices")
    assert all(math.hypot(n - 10.0, e - 5.0) <= 38.6 + 0.02 for n, e in area.polygon_ne_m)
    assert Polygon(area.polygon_ne_m).area >= 0.98 * math.pi * 38.6**2
    assert area.bounds.home_circle is not None
    north, east, radius = area.bounds.home_circle
    assert (north, east) == pytest.approx((10.0, 5.0), abs=0.01) and radius == pytest.approx(38.6)
    near = Route.point(30.0, 5.0, -5.0, source="test")
    far = Route.point(50.0, 5.0, -5.0, source="test")
    assert route_outside_limits(near, None, max_altitude_m=0.0, max_distance_m=0.0, fence=area.bounds) is None
    why = route_outside_limits(far, None, max_altitude_m=0.0, max_distance_m=0.0, fence=area.bounds)
    assert why == "waypoint 0 lies outside the fence's circle round home (radius less its margin 38.6 m)"
    with_l = _limits(Autopilot.ARDUPILOT, AP_DEFAULTS | {"FENCE_TYPE": 6.0, "FENCE_RADIUS": 12.0})
    clipped = fence_area(_polygon(L_SHAPE), REF, (5.0, 0.0), with_l, home, 0.6)  # (10, 5) is 1 m from an edge
    assert clipped.polygon_ne_m is not None and clipped.note.startswith("intersection of 2 inclusion zones, 1.4 m in")
    assert all(math.hypot(n - 10.0, e - 5.0) <= 12.0 - 1.4 + 1e-6 for n, e in clipped.polygon_ne_m)
    no_home = fence_area([], REF, (10.0, 5.0), alone, None, 0.6)
    assert no_home.outcome is FenceOutcome.NO_FENCE and no_home.provisional  # placed once HOME_POSITION comes


def test_uploaded_zones_outlast_fence_enable_0_but_not_a_fence_type_without_them() -> None:
    off = _limits(Autopilot.ARDUPILOT, AP_DEFAULTS | {"FENCE_ENABLE": 0.0})
    kept = fence_area(_polygon(L_SHAPE), REF, (10.0, 0.0), off, None, 0.6)
    assert kept.outcome is FenceOutcome.USED and kept.polygon_ne_m is not None and kept.bounds == FenceBounds()
    assert kept.note.endswith("FENCE_ENABLE 0: no circle round home or ceiling")
    nothing = _limits(Autopilot.ARDUPILOT, AP_DEFAULTS | {"FENCE_ENABLE": 0.0, "FENCE_TYPE": 3.0})
    assert fence_area([], REF, (10.0, 5.0), nothing).outcome is FenceOutcome.NO_FENCE  # nothing uploaded either
    uploaded = fence_area(_polygon(L_SHAPE), REF, (10.0, 5.0), nothing)
    assert uploaded.outcome is FenceOutcome.NOT_USED and "uploaded zones not used" in uploaded.note


def test_the_union_option_plans_over_the_union_within_the_circle_round_home() -> None:
    """FENCE_OPTIONS bit 1: two overlapping squares become their union (an L-ish octagon), not their
    intersection; the circle round home still clips it (AC_Fence checks it apart from the zones)."""
    a = ((0.0, 0.0), (10.0, 0.0), (10.0, 10.0), (0.0, 10.0))
    b = ((5.0, 5.0), (15.0, 5.0), (15.0, 15.0), (5.0, 15.0))
    items = [*_polygon(a), *_polygon(b, first=4)]
    params = ENFORCED | {"FENCE_OPTIONS": 2.0}
    union = fence_area(items, REF, (2.0, 2.0), _limits(Autopilot.ARDUPILOT, params))
    assert union.polygon_ne_m is not None and union.note.startswith("union of 2 inclusion zones, 8 vertices")
    assert Polygon(union.polygon_ne_m).area == pytest.approx(175.0, rel=0.01)
    inter = fence_area(items, REF, (7.0, 7.0), _limits(Autopilot.ARDUPILOT, ENFORCED))
    assert inter.polygon_ne_m is not None and Polygon(inter.polygon_ne_m).area == pytest.approx(25.0, rel=0.01)
    home = _latlon_e7(2.0, 2.0)
    circled = ENFORCED | {"FENCE_OPTIONS": 2.0, "FENCE_TYPE": 6.0, "FENCE_RADIUS": 8.0}
    clipped = fence_area(items, REF, (2.0, 2.0), _limits(Autopilot.ARDUPILOT, circled), home)
    assert clipped.polygon_ne_m is not None
    assert clipped.note.startswith("union of 2 inclusion zones within the circle round home")
    assert all(math.hypot(n - 2.0, e - 2.0) <= 8.0 + 0.02 for n, e in clipped.polygon_ne_m)
    assert not inside_area(clipped.polygon_ne_m, 14.0, 14.0) and inside_area(union.polygon_ne_m, 14.0, 14.0)


def test_goals_above_the_fences_ceiling_are_refused() -> None:
    high = Route.point(0.0, 0.0, -99.0, source="test")
    bounds = FenceBounds(98.0, None)
    why = route_outside_limits(high, None, max_altitude_m=120.0, max_distance_m=0.0, fence=bounds)
    assert why == "waypoint 0 is 99 m above home (the fence's ceiling less its margin = 98)"
    assert route_outside_limits(high, None, max_altitude_m=120.0, max_distance_m=0.0) is None


def test_the_reader_reads_the_parameters_each_time_and_falls_back_without_them() -> None:
    """Parameters read at every poll: a FENCE_TYPE without polygons takes the zones out, with them again puts
    them back. An autopilot that does not answer them: every uploaded zone is used, and the note says why."""
    results: list[FenceArea] = []
    reader = _reader(5.0, results)
    t = _answer(reader, _polygon(L_SHAPE), 0.0)
    assert _last(results).outcome is FenceOutcome.USED
    t = _answer(reader, _polygon(L_SHAPE), t + 5.0, ENFORCED | {"FENCE_TYPE": 3.0, "FENCE_ENABLE": 0.0})
    assert _last(results).outcome is FenceOutcome.NOT_USED and reader.changes == 1
    t = _answer(reader, _polygon(L_SHAPE), t + 5.0)
    assert _last(results).outcome is FenceOutcome.USED and reader.changes == 2
    assert reader.summary()["limits"] == "FENCE_MARGIN 0 m"
    silent: list[FenceArea] = []
    reader = _reader(5.0, silent)
    t = 0.0
    reader.due(t)
    while reader.download.stage.value == "idle" and t < 10.0:  # nobody answers the parameters
        t += 0.1
        reader.due(t)
    assert reader.limits == "fence parameters not read (no FENCE_ENABLE after 6 requests)"
    _download(reader, _polygon(L_SHAPE), t)
    assert _last(silent).outcome is FenceOutcome.USED
    want = "inclusion polygon of 6 vertices; fence parameters not read (no FENCE_ENABLE after 6 requests): every "
    assert _last(silent).note == want + "uploaded zone used"


def test_the_reader_places_the_circle_round_home_once_home_is_heard() -> None:
    results: list[FenceArea] = []
    reader = _reader(5.0, results)
    circle = ENFORCED | {"FENCE_TYPE": 6.0, "FENCE_RADIUS": 12.0}
    t = _answer(reader, _polygon(L_SHAPE), 0.0, circle)
    assert results[-1].provisional and "no HOME_POSITION yet" in results[-1].note
    lat, lon = _latlon_e7(10.0, 5.0)
    reader.on_record(HomePosition(src=AP, latitude=lat, longitude=lon, altitude=584000))
    _answer(reader, _polygon(L_SHAPE), t + 5.0, circle)
    last = results[-1]
    assert not last.provisional and last.polygon_ne_m is not None and last.note.startswith("intersection of 2")
    assert all(inside_area(last.polygon_ne_m, n, e) for n, e in [(10.0, 5.0), (15.0, 2.0)])
    _give_params(reader, ENFORCED)  # no read running: nothing happens
    assert reader.param_read.values == circle


def test_home_moving_matters_only_to_a_circle_round_it() -> None:
    """ArduCopter sets home again when it arms: without a circle round home nothing is told; with one, the
    circle moves with it."""
    results: list[FenceArea] = []
    reader = _reader(5.0, results)
    reader.on_record(HomePosition(src=AP, latitude=1, longitude=2, altitude=0))
    t = _answer(reader, _polygon(L_SHAPE), 0.0)
    reader.on_record(HomePosition(src=AP, latitude=3, longitude=4, altitude=0))
    t = _answer(reader, _polygon(L_SHAPE), t + 5.0)
    assert len(results) == 1 and reader.changes == 0
    circle = ENFORCED | {"FENCE_TYPE": 6.0, "FENCE_RADIUS": 12.0}
    reader.on_record(
        HomePosition(src=AP, latitude=_latlon_e7(10.0, 5.0)[0], longitude=_latlon_e7(10.0, 5.0)[1], altitude=0)
    )
    t = _answer(reader, _polygon(L_SHAPE), t + 5.0, circle)
    moved = _latlon_e7(12.0, 5.0)
    reader.on_record(HomePosition(src=AP, latitude=moved[0], longitude=moved[1], altitude=0))
    _answer(reader, _polygon(L_SHAPE), t + 5.0, circle)
    circle_now = _last(results).bounds.home_circle
    assert reader.changes == 2 and circle_now is not None and circle_now[0] == pytest.approx(12.0, abs=0.02)


def test_a_provisional_area_is_told_once_and_again_when_it_is_whole() -> None:
    """The vehicle within FENCE_MARGIN of the L's edge: the L as uploaded, told once (read again every poll about a
    reference that moves by centimetres: no news), then the L moved in once the vehicle is 3 m from the edge."""
    results: list[FenceArea] = []
    where = [(10.0, -2.0)]
    rng = np.random.default_rng(5)

    def reference() -> tuple[GlobalReference, tuple[float, float]]:  # the pose moves by centimetres each time
        n, e, d = REF.pos_ned_m
        return dataclasses.replace(REF, pos_ned_m=(n + float(rng.normal(0.0, 0.01)), e, d)), where[0]

    outbox = Outbox(None, dry_run=False, target_system=1, target_component=1, now_s=lambda: 0.0)
    params = FenceReaderParams(our_system=1, our_component=191, autopilot=AP, poll_s=5.0)
    reader = FenceReader(params, outbox=outbox, reference=reference, on_area=results.append)
    margin = ENFORCED | {"FENCE_MARGIN": 2.0}
    t = 0.0
    for _ in range(3):
        t = _answer(reader, _polygon(L_SHAPE), t, margin) + 5.0
    assert len(results) == 1 and results[0].provisional and reader.changes == 0
    where[0] = (10.0, 0.0)
    _answer(reader, _polygon(L_SHAPE), t, margin)
    assert len(results) == 2 and not _last(results).provisional
    assert _last(results).note.startswith("inclusion polygon, 2 m in from its edges")


def test_implausible_parameters_fail_safe() -> None:
    """A margin no zone survives keeps the zone as uploaded (provisional, read again); a negative ceiling refuses
    every goal above home; a negative radius or margin is no circle, no margin; NaN is no parameters at all."""
    huge = _limits(Autopilot.ARDUPILOT, AP_DEFAULTS | {"FENCE_TYPE": 5.0, "FENCE_MARGIN": 1e9})
    area = fence_area(_polygon(L_SHAPE), REF, (10.0, 0.0), huge, None, 0.6)
    assert area.outcome is FenceOutcome.USED and area.provisional and area.polygon_ne_m is not None
    assert len(area.polygon_ne_m) == 6
    low = _limits(Autopilot.ARDUPILOT, AP_DEFAULTS | {"FENCE_ALT_MAX": -5.0})
    assert low.ceiling_m == -7.0
    why = route_outside_limits(
        Route.point(0.0, 0.0, -1.0, source="test"), None, max_altitude_m=0.0, max_distance_m=0.0,
        fence=FenceBounds(low.ceiling_m, None),
    )  # fmt: skip
    assert why is not None and "ceiling" in why
    odd = _limits(Autopilot.ARDUPILOT, AP_DEFAULTS | {"FENCE_RADIUS": -1.0, "FENCE_MARGIN": -3.0})
    assert (odd.home_radius_m, odd.margin_m) == (None, 0.0)
    nan_dist = {"GF_ACTION": 2.0, "GF_MAX_HOR_DIST": math.nan, "GF_MAX_VER_DIST": 0.0}
    assert fence_limits(Autopilot.PX4, nan_dist) == "GF_MAX_HOR_DIST is nan"
    assert isinstance(fence_limits(Autopilot.PX4, nan_dist | {"GF_MAX_HOR_DIST": 0.0, "GF_ACTION": math.nan}), str)


def test_a_fence_switched_on_at_run_time_brings_its_circle_and_ceiling() -> None:
    """ArduPilot 4.6 switches its fence on without FENCE_ENABLE (MAV_CMD_DO_FENCE_ENABLE, an RC switch,
    FENCE_AUTOENABLE on arming); SYS_STATUS's GEOFENCE enabled bit says so."""
    off = AP_DEFAULTS | {"FENCE_ENABLE": 0.0}
    assert _limits(Autopilot.ARDUPILOT, off).ceiling_m is None
    on = _limits(Autopilot.ARDUPILOT, off, switched_on=True)
    assert (on.home_radius_m, on.ceiling_m) == (300.0, 98.0)
    assert on.note == "FENCE_MARGIN 2 m, switched on (SYS_STATUS), circle of 300 m round home, ceiling 100 m"
    results: list[FenceArea] = []
    reader = _reader(5.0, results)
    bit = mavlink.MAV_SYS_STATUS_GEOFENCE
    reader.on_record(SysStatus(src=AP, present=bit, enabled=bit, health=bit))
    _answer(reader, [], 0.0, ENFORCED | {"FENCE_ENABLE": 0.0, "FENCE_TYPE": 1.0})
    assert _last(results).bounds.ceiling_m == 100.0 and reader.switched_on
    reader.on_record(SysStatus(src=AP, present=bit, enabled=0, health=bit))
    assert not reader.switched_on


def test_a_breach_the_autopilot_reports_is_said_and_counted() -> None:
    """GCS.cpp: GEOFENCE present and not healthy is a breach (``!fence->sys_status_failed()``); healthy again, it
    is over; a new breach counts again. No fence present says nothing."""
    reader = _reader(5.0, [])
    bit = mavlink.MAV_SYS_STATUS_GEOFENCE
    sequence = [(bit, bit), (bit, 0), (bit, 0), (bit, bit), (bit, 0), (0, 0)]
    seen = []
    for present, health in sequence:
        reader.on_record(SysStatus(src=AP, present=present, enabled=present, health=health))
        seen.append((reader.breached, reader.breaches))
    assert seen == [(False, 0), (True, 1), (True, 1), (False, 1), (True, 2), (False, 2)]
    assert reader.summary()["breached"] is False and reader.summary()["breaches"] == 2


def test_the_floor_refuses_goals_below_it_plus_the_margin() -> None:
    """FENCE_TYPE bit 8 (FENCE_ALT_MIN, 4.x, read when the autopilot has it) with the fence on: goals below the
    floor plus the margin (``get_safe_alt_min_m``) are refused; off, or an autopilot without it, no floor."""
    with_floor = AP_DEFAULTS | {"FENCE_TYPE": 15.0, "FENCE_ALT_MIN": 5.0}
    limits = _limits(Autopilot.ARDUPILOT, with_floor)
    assert limits.floor_m == 7.0 and limits.note.endswith("ceiling 100 m, floor 5 m")
    assert _limits(Autopilot.ARDUPILOT, with_floor | {"FENCE_ENABLE": 0.0}).floor_m is None
    assert _limits(Autopilot.ARDUPILOT, AP_DEFAULTS | {"FENCE_TYPE": 15.0}).floor_m is None  # no FENCE_ALT_MIN
    area = fence_area([], REF, (10.0, 5.0), limits, _latlon_e7(10.0, 5.0), 0.6)
    assert area.bounds.floor_m == 7.0
    bounds = FenceBounds(98.0, None, 7.0)
    low = route_outside_limits(Route.point(0.0, 0.0, -6.0, source="test"), None, max_altitude_m=0.0,
                               max_distance_m=0.0, fence=bounds)  # fmt: skip
    assert low == "waypoint 0 is 6 m above home (the fence's floor plus its margin = 7)"
    ok = route_outside_limits(Route.point(0.0, 0.0, -8.0, source="test"), None, max_altitude_m=0.0,
                              max_distance_m=0.0, fence=bounds)  # fmt: skip
    assert ok is None
    # goal.min_altitude_m beside it: the higher floor counts, and its name is in the reason
    low = route_outside_limits(Route.point(0.0, 0.0, -6.0, source="test"), None, max_altitude_m=0.0,
                               max_distance_m=0.0, min_altitude_m=1.0, fence=bounds)  # fmt: skip
    assert low == "waypoint 0 is 6 m above home (the fence's floor plus its margin = 7)"
    low = route_outside_limits(Route.point(0.0, 0.0, -8.0, source="test"), None, max_altitude_m=0.0,
                               max_distance_m=0.0, min_altitude_m=10.0, fence=bounds)  # fmt: skip
    assert low == "waypoint 0 is 8 m above home (goal.min_altitude_m = 10)"
    floor_only = _limits(Autopilot.ARDUPILOT, AP_DEFAULTS | {"FENCE_TYPE": 8.0, "FENCE_ALT_MIN": 5.0})
    assert floor_only.enforced and fence_area([], REF, (10.0, 5.0), floor_only).outcome is FenceOutcome.USED
