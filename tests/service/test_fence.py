"""The autopilot's fence as bapf-nav's flying area, without sockets: the download's state machine on an injected
clock (repeats, give-up, stray and refused answers), the items read as one polygon (polygons, circles, exclusion
zones, malformed fences), and the reader's filter (answers to someone else, other mission types)."""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest
from pymavlink.dialects.v20 import ardupilotmega as mavlink

from apf_companion.fence import (
    CIRCLE_VERTICES,
    FenceArea,
    FenceDownload,
    FenceItem,
    FenceOutcome,
    FenceSend,
    FenceStage,
    fence_area,
)
from apf_companion.fencelimits import ReadStage
from apf_companion.fencereader import FenceReader, FenceReaderParams
from apf_companion.goal import EARTH_RADIUS_M, GlobalReference
from apf_companion.links.messages import MissionAck, MissionCount, MissionCurrent, MissionItemInt, ParamValue, Source
from apf_companion.outbox import Outbox
from apf_companion.planning import in_keepout, inside_area

VERTEX_IN = mavlink.MAV_CMD_NAV_FENCE_POLYGON_VERTEX_INCLUSION
VERTEX_OUT = mavlink.MAV_CMD_NAV_FENCE_POLYGON_VERTEX_EXCLUSION
CIRCLE_IN = mavlink.MAV_CMD_NAV_FENCE_CIRCLE_INCLUSION
CIRCLE_OUT = mavlink.MAV_CMD_NAV_FENCE_CIRCLE_EXCLUSION
RETURN = mavlink.MAV_CMD_NAV_FENCE_RETURN_POINT
FENCE = mavlink.MAV_MISSION_TYPE_FENCE

#: The vehicle at (10, 5, -5) local NED, at Canberra's SITL home.
REF = GlobalReference(
    lat_deg=-35.363262, lon_deg=149.165237, alt_amsl_m=589.0, alt_rel_m=5.0, pos_ned_m=(10.0, 5.0, -5.0)
)
#: A rectangle from 2 m north of the vehicle: it overlaps a 5 m circle round the vehicle, not the vehicle.
NORTH_OF_VEHICLE = ((12.0, -9.0), (30.0, -9.0), (30.0, 19.0), (12.0, 19.0))
L_SHAPE = ((-3.0, -3.0), (23.0, -3.0), (23.0, 6.0), (9.0, 6.0), (9.0, 23.0), (-3.0, 23.0))


def _latlon_e7(north: float, east: float) -> tuple[int, int]:
    """Local NED -> latitude/longitude [1e-7 deg] around ``REF`` (the inverse of ``goal.ne_from_global``)."""
    dn, de = north - REF.pos_ned_m[0], east - REF.pos_ned_m[1]
    lat = REF.lat_deg + math.degrees(dn / EARTH_RADIUS_M)
    lon = REF.lon_deg + math.degrees(de / (EARTH_RADIUS_M * math.cos(math.radians(REF.lat_deg))))
    return round(lat * 1e7), round(lon * 1e7)


def _polygon(vertices: tuple[tuple[float, float], ...], command: int = VERTEX_IN, first: int = 0) -> list[FenceItem]:
    return [
        FenceItem(seq=first + i, command=command, param1=float(len(vertices)), x=x, y=y)
        for i, (x, y) in enumerate(_latlon_e7(n, e) for n, e in vertices)
    ]


def _circle(north: float, east: float, radius_m: float, command: int, seq: int = 0) -> FenceItem:
    x, y = _latlon_e7(north, east)
    return FenceItem(seq=seq, command=command, param1=radius_m, x=x, y=y)


def test_one_inclusion_polygon_is_the_area_to_a_centimetre() -> None:
    items = [FenceItem(seq=0, command=RETURN, param1=0.0, x=_latlon_e7(0, 0)[0], y=_latlon_e7(0, 0)[1])]
    items += _polygon(L_SHAPE, first=1)
    area = fence_area(items, REF, (10.0, 5.0))
    assert area.outcome is FenceOutcome.USED and area.note == "inclusion polygon of 6 vertices"
    assert area.polygon_ne_m is not None and len(area.polygon_ne_m) == 6
    for (n, e), (n0, e0) in zip(area.polygon_ne_m, L_SHAPE, strict=True):
        assert abs(n - n0) < 0.01 and abs(e - e0) < 0.01  # 1e-7 deg is 1.1 cm


def test_circles_become_polygons_that_never_let_the_vehicle_where_the_fence_would_not() -> None:
    """An inclusion circle: its inscribed 32-gon (inside the circle). An exclusion circle: its circumscribed 32-gon
    (around the circle). Exclusion polygons are kept as they are. All exclusion zones become keep-out zones."""
    items = [_circle(10.0, 5.0, 20.0, CIRCLE_IN), _circle(15.0, 5.0, 2.0, CIRCLE_OUT, seq=1)]
    items += _polygon(((0.0, 10.0), (2.0, 10.0), (2.0, 12.0)), VERTEX_OUT, first=2)
    area = fence_area(items, REF, (10.0, 5.0))
    assert area.outcome is FenceOutcome.USED
    assert area.note == "inclusion circle of 32 vertices; 2 exclusion zones as keep-out zones"
    assert area.polygon_ne_m is not None and len(area.polygon_ne_m) == CIRCLE_VERTICES
    radii = [math.hypot(n - 10.0, e - 5.0) for n, e in area.polygon_ne_m]
    assert all(abs(r - 20.0) < 0.02 for r in radii)  # vertices on the circle: the polygon lies inside it
    assert not inside_area(area.polygon_ne_m, 10.0 + 19.9, 5.0 + 0.5 * 20.0 * math.tau / CIRCLE_VERTICES)
    circle, triangle = area.keepouts_ne_m
    outer = 2.0 / math.cos(math.pi / CIRCLE_VERTICES)
    assert all(abs(math.hypot(n - 15.0, e - 5.0) - outer) < 0.02 for n, e in circle)
    turns = np.arange(50) / 50 * math.tau
    ring_n, ring_e = 15.0 + 1.98 * np.cos(turns), 5.0 + 1.98 * np.sin(turns)  # 2 cm in: the 1e-7 deg rounding
    assert in_keepout((circle,), ring_n, ring_e).all()  # the whole circle is kept out
    assert all(
        abs(n - n0) < 0.01 and abs(e - e0) < 0.01
        for (n, e), (n0, e0) in zip(triangle, ((0, 10), (2, 10), (2, 12)), strict=True)
    )


def test_a_fence_of_exclusion_zones_only_gives_keep_out_zones_and_no_area() -> None:
    area = fence_area(_polygon(((0.0, 0.0), (5.0, 0.0), (5.0, 5.0)), VERTEX_OUT), REF, (10.0, 5.0))
    assert area.outcome is FenceOutcome.USED and area.note == "1 exclusion zone as keep-out zone"
    assert area.polygon_ne_m is None and len(area.keepouts_ne_m) == 1


@pytest.mark.parametrize(
    ("items", "outcome", "note"),
    [
        ([], FenceOutcome.NO_FENCE, "the autopilot has no fence"),
        (
            [*_polygon(L_SHAPE), *_polygon(((0.0, 0.0), (5.0, 5.0), (5.0, 0.0), (0.0, 5.0)), VERTEX_OUT, first=6)],
            FenceOutcome.NOT_USED,
            "an exclusion zone is not a polygon with an area",
        ),
        (
            [_circle(10.0, 5.0, 5.0, CIRCLE_IN), _circle(40.0, 5.0, 5.0, CIRCLE_IN, seq=1)],
            FenceOutcome.NOT_USED,
            "the inclusion zones do not overlap",
        ),
        (
            [_circle(10.0, 5.0, 5.0, CIRCLE_IN), *_polygon(NORTH_OF_VEHICLE, first=1)],
            FenceOutcome.NOT_USED,
            "the vehicle is outside the inclusion zones' intersection",
        ),
        (_polygon(((40.0, 40.0), (60.0, 40.0), (60.0, 60.0))), FenceOutcome.NOT_USED, "the vehicle is outside"),
        (_polygon(L_SHAPE)[:4], FenceOutcome.NOT_USED, "fence item 0: a polygon of 6.0 vertices"),  # cut short
        (
            [FenceItem(seq=i, command=VERTEX_IN, param1=math.nan, x=0, y=0) for i in range(3)],
            FenceOutcome.NOT_USED,
            "fence item 0: a polygon of nan",
        ),
        ([_circle(10.0, 5.0, -1.0, CIRCLE_IN)], FenceOutcome.NOT_USED, "fence item 0: circle radius -1.0"),
        ([FenceItem(seq=0, command=16, param1=0.0, x=0, y=0)], FenceOutcome.NOT_USED, "command 16 is no fence item"),
        (
            [FenceItem(seq=0, command=CIRCLE_IN, param1=5.0, x=2_000_000_000, y=0)],
            FenceOutcome.NOT_USED,
            "out of range",
        ),
        (_polygon(((0.0, 0.0), (20.0, 20.0), (20.0, 0.0), (0.0, 25.0))), FenceOutcome.NOT_USED, "edges do not cross"),
    ],
    ids=[
        "none",
        "only-exclusion",
        "apart",
        "beside",
        "elsewhere",
        "short",
        "nan-count",
        "radius",
        "command",
        "lat",
        "bow",
    ],
)
def test_fences_that_are_no_single_zone_around_the_vehicle_are_not_used(
    items: list[FenceItem], outcome: FenceOutcome, note: str
) -> None:
    area = fence_area(items, REF, (10.0, 5.0))
    assert area.outcome is outcome and area.polygon_ne_m is None
    assert note in area.note


def _inside_all(zones: list[tuple[tuple[float, float], ...]], north: np.ndarray, east: np.ndarray) -> np.ndarray:
    inside: np.ndarray = np.logical_and.reduce([inside_area(z, north, east) for z in zones])
    return inside


def _far_from_edges(zones: list[tuple[tuple[float, float], ...]], pts: np.ndarray, d: float) -> np.ndarray:
    """Points farther than ``d`` from every edge of ``zones`` (where float rounding cannot flip a side)."""
    far = np.ones(len(pts), dtype=bool)
    for zone in zones:
        v = np.array(zone)
        a, b = v, np.roll(v, -1, axis=0)
        ab = b - a
        t = np.clip(((pts[:, None, :] - a) * ab).sum(-1) / (ab * ab).sum(-1), 0.0, 1.0)
        dist = np.linalg.norm(pts[:, None, :] - (a + t[..., None] * ab), axis=-1).min(axis=1)
        far &= dist > d
    return far


def test_several_inclusion_zones_become_their_intersection_round_the_vehicle() -> None:
    """The L and a 12 m circle round the vehicle: the area is exactly where both are (sampled away from the
    edges), said as an intersection; a triangle that cuts the L's two arms apart gives the piece with the
    vehicle."""
    items = [_circle(10.0, 5.0, 12.0, CIRCLE_IN), *_polygon(L_SHAPE, first=1)]
    area = fence_area(items, REF, (10.0, 5.0))
    assert area.outcome is FenceOutcome.USED and area.polygon_ne_m is not None
    assert area.note.startswith("intersection of 2 inclusion zones, ")
    zones = [fence_area(part, REF, (10.0, 5.0)).polygon_ne_m for part in (items[:1], items[1:])]
    assert zones[0] is not None and zones[1] is not None
    pts = np.random.default_rng(4).uniform(-5.0, 25.0, size=(20_000, 2))
    pts = pts[_far_from_edges([*zones, area.polygon_ne_m], pts, 0.01)]  # type: ignore[list-item]
    got = inside_area(area.polygon_ne_m, pts[:, 0], pts[:, 1])
    np.testing.assert_array_equal(got, _inside_all(zones, pts[:, 0], pts[:, 1]))  # type: ignore[arg-type]
    assert got.sum() > 3000  # a real area was sampled
    triangle = ((20.0, 2.0), (2.0, 20.0), (30.0, 30.0))
    apart = fence_area([*_polygon(L_SHAPE), *_polygon(triangle, first=6)], REF, (19.0, 4.0))
    assert apart.outcome is FenceOutcome.USED and apart.polygon_ne_m is not None
    piece = np.array(apart.polygon_ne_m)
    assert piece[:, 1].max() <= 6.0 + 1e-6 and piece[:, 0].min() >= 16.0 - 1e-6  # the south-west arm's piece only


def _regular(n: int, radius_m: float, turn: float) -> tuple[tuple[float, float], ...]:
    """A regular ``n``-gon about the vehicle (10, 5), turned by ``turn`` of a step."""
    angles = [(k + turn) * math.tau / n for k in range(n)]
    return tuple((10.0 + radius_m * math.cos(a), 5.0 + radius_m * math.sin(a)) for a in angles)


def test_an_intersection_of_too_many_vertices_is_fitted_inside_it() -> None:
    """Two 60-gons about the vehicle, one turned by half a step: their intersection has 120 vertices, so the area
    is shrunk and simplified to at most 64, stays inside both zones and round the vehicle, and loses little."""
    zones = [_regular(60, 10.0, 0.0), _regular(60, 10.0, 0.5)]
    area = fence_area([*_polygon(zones[0]), *_polygon(zones[1], first=60)], REF, (10.0, 5.0))
    assert area.outcome is FenceOutcome.USED and area.polygon_ne_m is not None
    assert area.note.startswith("intersection of 2 inclusion zones, ") and 3 <= len(area.polygon_ne_m) <= 64
    placed = [fence_area(_polygon(z), REF, (10.0, 5.0)).polygon_ne_m for z in zones]
    pts = np.random.default_rng(5).uniform(-1.0, 21.0, size=(40_000, 2))
    both = _inside_all(placed, pts[:, 0], pts[:, 1])  # type: ignore[arg-type]
    got = inside_area(area.polygon_ne_m, pts[:, 0], pts[:, 1])
    assert not (got & ~both).any() and got.sum() >= 0.97 * both.sum()
    v = np.array(area.polygon_ne_m)
    assert _far_from_edges(placed, v, 0.01).all() and _inside_all(placed, v[:, 0], v[:, 1]).all()  # type: ignore[arg-type]


def test_the_download_keeps_the_plan_id_of_its_count_until_it_starts_again() -> None:
    d = FenceDownload()
    d.start()
    d.on_count(0, 0xDEADBEEF)
    assert d.stage is FenceStage.DONE and d.plan_id == 0xDEADBEEF
    d.on_count(2, 7)  # a stray count: counted, the id stays
    assert d.unexpected == 1 and d.plan_id == 0xDEADBEEF
    d.rest()
    assert d.plan_id == 0xDEADBEEF  # kept after the end is taken
    d.start()
    assert d.plan_id == 0  # a new download has no id until its count


def test_the_download_asks_repeats_and_acks() -> None:
    d = FenceDownload(timeout_s=1.0, retries=2)
    assert d.due(0.0) is None  # not started
    d.start()
    assert d.due(0.0) == FenceSend(seq=None)  # MISSION_REQUEST_LIST
    assert d.due(0.5) is None  # within the timeout
    assert d.due(1.0) == FenceSend(seq=None)  # repeated
    d.on_count(3)
    assert d.stage is FenceStage.ITEMS
    assert d.due(1.1) == FenceSend(seq=0)  # at once, not after the timeout
    items = _polygon(((0.0, 0.0), (5.0, 0.0), (5.0, 5.0)))
    d.on_item(items[1])  # out of order: dropped and counted
    assert d.unexpected == 1 and d.items == []
    d.on_item(items[0])
    assert d.due(1.2) == FenceSend(seq=1)
    d.on_item(items[1])
    d.on_item(items[1])  # a repeat (the request was repeated): dropped
    assert d.unexpected == 2
    assert d.due(1.3) == FenceSend(seq=2)
    d.on_item(items[2])
    assert _stage(d) is FenceStage.DONE and d.items == items
    assert d.due(1.4) == FenceSend(ack=True)  # the closing MISSION_ACK, once
    assert d.due(9.0) is None
    d.on_count(3)  # a late count: counted, nothing restarts
    assert d.unexpected == 3 and _stage(d) is FenceStage.DONE


def test_the_download_gives_up_after_its_retries_and_on_a_refusal() -> None:
    d = FenceDownload(timeout_s=1.0, retries=2)
    d.start()
    sends = [d.due(float(t)) for t in range(5)]
    assert sends[:3] == [FenceSend(seq=None)] * 3 and sends[3:] == [None, None]
    assert d.stage is FenceStage.FAILED and d.reason == "no MISSION_COUNT after 3 requests"
    d.start()
    assert d.due(10.0) == FenceSend(seq=None)
    d.on_count(2)
    d.on_ack(mavlink.MAV_MISSION_DENIED)  # a ground station is uploading
    assert d.stage is FenceStage.FAILED and d.reason == "the autopilot answered MISSION_ACK MAV_MISSION_DENIED"
    d.start()
    d.on_count(100_000)
    assert d.stage is FenceStage.FAILED and "100000 items" in d.reason
    d.start()
    d.on_count(0)
    # An empty fence is acked too (PX4's mavlink_mission.cpp keeps its one transfer state until the ack or 5 s).
    assert _stage(d) is FenceStage.DONE and d.due(20.0) == FenceSend(ack=True) and d.due(20.1) is None


def test_the_reader_takes_only_fence_answers_addressed_to_it() -> None:
    results: list[FenceArea] = []
    outbox = Outbox(None, dry_run=False, target_system=1, target_component=1, now_s=lambda: 0.0)
    reader = FenceReader(
        FenceReaderParams(our_system=1, our_component=191, autopilot=Source(1, 1)),
        outbox=outbox,
        reference=lambda: (REF, (10.0, 5.0)),
        on_area=results.append,
    )
    ap = Source(1, 1)
    assert reader.due(0.0) == pytest.approx(0.1)
    assert _stage(reader.download) is FenceStage.IDLE  # the fence parameters first
    _give_params(reader, ENFORCED)
    reader.due(0.05)
    assert _stage(reader.download) is FenceStage.COUNT
    reader.on_record(MissionCount(src=ap, target_system=255, target_component=190, count=6, mission_type=FENCE))
    reader.on_record(MissionCount(src=ap, target_system=1, target_component=191, count=6, mission_type=0))
    assert reader.ignored == 2 and reader.download.stage is FenceStage.COUNT  # a GCS's download; a mission
    reader.on_record(MissionCount(src=ap, target_system=1, target_component=191, count=6, mission_type=FENCE))
    for item in _polygon(L_SHAPE):
        reader.due(0.2)
        reader.on_record(
            MissionItemInt(
                src=ap, target_system=1, target_component=191, seq=item.seq, frame=mavlink.MAV_FRAME_GLOBAL,
                command=item.command, param1=item.param1, x=item.x, y=item.y, mission_type=FENCE,
            )
        )  # fmt: skip
    reader.due(0.3)  # the closing ack
    assert results == []
    reader.due(0.4)
    assert len(results) == 1 and results[0].outcome is FenceOutcome.USED and reader.result is results[0]
    reader.on_record(MissionAck(src=ap, target_system=1, target_component=191, type=0, mission_type=FENCE))
    assert reader.ignored == 3 and reader.due(0.5) == pytest.approx(1.5)  # idle: it looks again within 1 s
    assert reader.due(5.4) == pytest.approx(5.5)  # poll_s after the end: the parameters asked for again
    assert reader.param_read.stage is ReadStage.RUNNING and _stage(reader.download) is FenceStage.IDLE


AP = Source(1, 1)
#: ArduPilot's (4.6) fence parameters with the uploaded zones enforced and nothing else (no margin, circle,
#: ceiling, union).
ENFORCED = {
    "FENCE_ENABLE": 1.0,
    "FENCE_TYPE": 4.0,
    "FENCE_RADIUS": 300.0,
    "FENCE_ALT_MAX": 100.0,
    "FENCE_MARGIN": 0.0,
    "FENCE_MARGIN_XY": 0.0,
    "FENCE_OPTIONS": 0.0,
    "FENCE_ALT_MIN": -10.0,
}


def _give_params(reader: FenceReader, values: dict[str, float]) -> None:
    """The autopilot's PARAM_VALUEs of ``values`` (REAL32, as ArduPilot casts them)."""
    for name, value in values.items():
        reader.on_record(ParamValue(src=AP, param_id=name, param_value=value, param_type=REAL32))


REAL32 = mavlink.MAV_PARAM_TYPE_REAL32


def _reader(poll_s: float, results: list[FenceArea], where: list[tuple[float, float]] | None = None) -> FenceReader:
    """A reader whose vehicle is at ``where[0]`` (north, east) [m] (default: (10, 5), inside the L)."""
    at = [(10.0, 5.0)] if where is None else where
    outbox = Outbox(None, dry_run=False, target_system=1, target_component=1, now_s=lambda: 0.0)
    return FenceReader(
        FenceReaderParams(our_system=1, our_component=191, autopilot=AP, poll_s=poll_s),
        outbox=outbox,
        reference=lambda: (REF, at[0]),
        on_area=results.append,
    )


def _answer(
    reader: FenceReader,
    items: list[FenceItem] | None,
    t: float,
    params: dict[str, float] | None = None,
    plan_id: int = 0,
) -> float:
    """One read from ``t`` [s]: the fence parameters (``params``, default ``ENFORCED``), then the download, each
    request answered at once with ``items`` (None: refused, DENIED, as while a ground station uploads) and their
    ``plan_id`` in MISSION_COUNT; the time after it has ended."""
    reader.due(t)
    _give_params(reader, ENFORCED if params is None else params)
    t += 0.05
    reader.due(t)
    return _download(reader, items, t, plan_id)


def _download(reader: FenceReader, items: list[FenceItem] | None, t: float, plan_id: int = 0) -> float:
    """The download part of ``_answer``, from ``t`` [s] with the parameters read; the time after it has ended."""
    assert reader.download.stage is FenceStage.COUNT
    if items is None:
        reader.on_record(MissionAck(src=AP, target_system=1, target_component=191, type=DENIED, mission_type=FENCE))
    else:
        count = len(items)
        reader.on_record(
            MissionCount(
                src=AP, target_system=1, target_component=191, count=count, mission_type=FENCE, opaque_id=plan_id
            )
        )
    for item in items or []:
        t += 0.1
        reader.due(t)
        reader.on_record(
            MissionItemInt(
                src=AP, target_system=1, target_component=191, seq=item.seq, frame=mavlink.MAV_FRAME_GLOBAL,
                command=item.command, param1=item.param1, x=item.x, y=item.y, mission_type=FENCE,
            )
        )  # fmt: skip
    for _ in range(2):  # the closing ack, then the end
        t += 0.1
        reader.due(t)
    assert _stage(reader.download) is FenceStage.IDLE
    return t


DENIED = mavlink.MAV_MISSION_DENIED
SQUARE = ((0.0, 0.0), (20.0, 0.0), (20.0, 20.0), (0.0, 20.0))


def test_the_fence_is_read_again_every_poll_s_and_only_a_change_is_told() -> None:
    """A fence changed on the ground station in flight: read again poll_s after each read; the same items tell
    nothing, new items are told, a refused read keeps what was told, a fence removed is told."""
    results: list[FenceArea] = []
    reader = _reader(5.0, results)
    t = _answer(reader, _polygon(L_SHAPE), 0.0)
    assert [r.outcome for r in results] == [FenceOutcome.USED] and reader.result is results[0]
    assert reader.due(t + 1.0) == pytest.approx(t + 2.0)  # nothing before the next read: no request
    assert reader.download.stage is FenceStage.IDLE
    t = _answer(reader, _polygon(L_SHAPE), t + 5.0)
    assert len(results) == 1 and (reader.reads, reader.changes) == (2, 0)  # the same fence: nothing told
    t = _answer(reader, _polygon(SQUARE), t + 5.0)
    assert len(results) == 2 and reader.changes == 1
    assert results[1].polygon_ne_m is not None and len(results[1].polygon_ne_m) == 4
    t = _answer(reader, None, t + 5.0)  # a ground station uploading: DENIED
    assert len(results) == 2 and reader.failures == 1 and reader.result is results[1]  # kept
    t = _answer(reader, [], t + 5.0)
    assert results[-1].outcome is FenceOutcome.NO_FENCE and reader.changes == 2
    stray = MissionCount(src=AP, target_system=1, target_component=191, count=4, mission_type=FENCE)
    reader.on_record(stray)  # no download running: dropped
    assert reader.ignored == 1


def _params_only(reader: FenceReader, t: float, params: dict[str, float] | None = None) -> None:
    """A read from ``t`` [s] that the fence id spares its download: the parameters, and no download starts."""
    reader.due(t)
    _give_params(reader, ENFORCED if params is None else params)
    reader.due(t + 0.05)
    assert reader.download.stage is FenceStage.IDLE and reader.param_read.stage is ReadStage.IDLE


def test_a_fence_id_that_has_not_changed_spares_the_download_and_any_other_does_not() -> None:
    """PX4 gives its fence plan an id (MISSION_CURRENT fence_id, MISSION_COUNT opaque_id): while it is the id of
    the items in service, a read takes the parameters only; a new id, no id heard since the last read, or id 0
    (no fence, or an autopilot without ids) downloads."""
    results: list[FenceArea] = []
    reader = _reader(5.0, results)
    t = _answer(reader, _polygon(L_SHAPE), 0.0, plan_id=111)
    reader.on_record(MissionCurrent(src=AP, fence_id=111))
    _params_only(reader, t + 5.0)
    assert (reader.reads, reader.skipped, len(results)) == (2, 1, 1)
    t += 5.1
    reader.due(t + 5.0)  # no MISSION_CURRENT since that read: download
    _give_params(reader, ENFORCED)
    reader.due(t + 5.05)
    t = _download(reader, _polygon(L_SHAPE), t + 5.05, plan_id=111)
    assert (reader.reads, reader.skipped, len(results)) == (3, 1, 1)
    reader.on_record(MissionCurrent(src=AP, fence_id=111))
    _params_only(reader, t + 5.0, {**ENFORCED, "FENCE_MARGIN": 2.0})  # the parameters still count
    assert len(results) == 2 and reader.changes == 1 and reader.skipped == 2
    assert "FENCE_MARGIN 2 m" in results[1].note
    t += 5.1
    reader.on_record(MissionCurrent(src=AP, fence_id=222))  # a ground station's upload
    t = _answer(reader, _polygon(SQUARE), t + 5.0, plan_id=222)
    assert len(results) == 3 and results[2].polygon_ne_m is not None and len(results[2].polygon_ne_m) == 4
    reader.on_record(MissionCurrent(src=AP, fence_id=0))  # cleared
    t = _answer(reader, [], t + 5.0)
    assert results[-1].outcome is FenceOutcome.NO_FENCE
    reader.on_record(MissionCurrent(src=AP, fence_id=0))  # id 0 vouches for nothing
    _answer(reader, [], t + 5.0)
    assert reader.skipped == 2 and reader.summary()["skipped"] == 2


def test_a_new_fence_id_starts_a_read_at_once_and_only_once() -> None:
    """PX4 sends MISSION_CURRENT at 1 Hz: an id other than the one in service (an upload, a clear) starts a read
    before ``poll_s``; once per id, so an autopilot whose MISSION_COUNT omits the id is not read every second.
    ``poll_s`` 0 reads once, whatever the id."""
    results: list[FenceArea] = []
    reader = _reader(5.0, results)
    t = _answer(reader, _polygon(L_SHAPE), 0.0, plan_id=111)
    reader.on_record(MissionCurrent(src=AP, fence_id=111))
    assert reader.due(t + 1.0) == pytest.approx(t + 2.0) and reader.param_read.stage is ReadStage.IDLE
    reader.on_record(MissionCurrent(src=AP, fence_id=222))  # an upload
    t = _answer(reader, _polygon(SQUARE), t + 1.5, plan_id=222)  # 1.5 s after the last read, not 5
    assert reader.early == 1 and len(results) == 2 and reader.summary()["early"] == 1
    reader.on_record(MissionCurrent(src=AP, fence_id=222))
    reader.due(t + 1.0)
    assert reader.param_read.stage is ReadStage.IDLE  # the id in service: nothing until the poll
    reader.on_record(MissionCurrent(src=AP, fence_id=333))  # an upload, on an autopilot without MISSION_COUNT ids
    t = _answer(reader, _polygon(L_SHAPE), t + 1.5, plan_id=0)
    reader.on_record(MissionCurrent(src=AP, fence_id=333))
    reader.due(t + 1.0)
    assert reader.param_read.stage is ReadStage.IDLE and reader.early == 2  # read once for that id
    t = _answer(reader, _polygon(L_SHAPE), t + 5.0)  # the poll downloads (no id in service to vouch)
    assert reader.skipped == 0 and reader.early == 2
    once: list[FenceArea] = []
    reader = _reader(0.0, once)
    t = _answer(reader, _polygon(L_SHAPE), 0.0, plan_id=111)
    reader.on_record(MissionCurrent(src=AP, fence_id=222))
    reader.due(t + 1.0)
    assert reader.param_read.stage is ReadStage.IDLE and reader.early == 0


def test_a_fence_the_vehicle_was_outside_of_is_used_once_it_has_flown_in() -> None:
    results: list[FenceArea] = []
    where = [(15.0, 15.0)]  # in the L's notch: outside it
    reader = _reader(5.0, results, where)
    t = _answer(reader, _polygon(L_SHAPE), 0.0)
    assert [r.note for r in results] == ["the vehicle is outside the inclusion zone"]
    t = _answer(reader, _polygon(L_SHAPE), t + 5.0)
    assert len(results) == 1  # still outside: nothing new to tell
    where[0] = (10.0, 5.0)
    _answer(reader, _polygon(L_SHAPE), t + 5.0)
    assert results[-1].outcome is FenceOutcome.USED and len(results) == 2 and reader.changes == 1


def test_a_first_read_that_fails_is_told_and_read_again_and_poll_s_0_reads_once() -> None:
    results: list[FenceArea] = []
    reader = _reader(5.0, results)
    t = _answer(reader, None, 0.0)
    assert [r.outcome for r in results] == [FenceOutcome.FAILED]
    assert results[0].note == "download failed: the autopilot answered MISSION_ACK MAV_MISSION_DENIED"
    _answer(reader, _polygon(L_SHAPE), t + 5.0)
    assert results[-1].outcome is FenceOutcome.USED and reader.changes == 0  # the first whole read
    once: list[FenceArea] = []
    reader = _reader(0.0, once)
    t = _answer(reader, _polygon(L_SHAPE), 0.0)
    reader.due(t + 100.0)
    assert reader.download.stage is FenceStage.IDLE and len(once) == 1  # read once
    reader.params = dataclasses.replace(reader.params, poll_s=5.0)  # APF_FENCE_POLL set to 5: reads again
    reader.due(t + 101.0)
    assert reader.param_read.stage is ReadStage.RUNNING


def _stage(d: FenceDownload) -> FenceStage:
    """The stage as the download has it now (mypy narrows ``d.stage`` across the calls that change it)."""
    return d.stage


def test_a_geos_failure_leaves_the_fence_unused_with_the_reason(monkeypatch: pytest.MonkeyPatch) -> None:
    """GEOS 3.14's overlay took every degenerate zone tried here (spikes, folds, repeated vertices), so its
    TopologyException is raised by a stand-in: the fence is then not used, and the reason says why."""
    import shapely

    def fail(_geoms: object) -> object:
        raise shapely.errors.GEOSException("TopologyException: side location conflict")

    monkeypatch.setattr(shapely, "intersection_all", fail)
    items = [_circle(10.0, 5.0, 12.0, CIRCLE_IN), *_polygon(L_SHAPE, first=1)]
    area = fence_area(items, REF, (10.0, 5.0))
    assert area.outcome is FenceOutcome.NOT_USED
    assert area.note == "the inclusion zones cannot be intersected (TopologyException: side location conflict)"
