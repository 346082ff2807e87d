"""The autopilot's geofence as bapf-nav's flying area: its download (the MAVLink mission protocol for
MAV_MISSION_TYPE_FENCE, a state machine on an injected clock) and its items as a polygon in local NED.

A fence is a list of mission items (common.xml, MAV_CMD_NAV_FENCE_*): polygon vertices of inclusion or exclusion
zones (``param1`` = the polygon's vertex count, on each vertex), circles (``param1`` = radius) and a return
point; ``x``/``y`` are latitude/longitude in 1e-7 degrees. ArduPilot keeps the vehicle inside every inclusion
zone (their intersection, unless FENCE_OPTIONS asks for the union) and outside every exclusion zone
(``libraries/AC_Fence/AC_PolyFence_loader.cpp``, ``breached``); PX4 takes the same items and keeps the vehicle
inside every inclusion zone too (``src/modules/navigator/geofence.cpp``).

The flying area is one polygon (``planning.area``), so its inclusion zone, if the fence has one, becomes that
polygon, or a circle's inscribed 32-gon (inside the circle: never wider than the fence). Two or more inclusion
zones become the piece of their intersection that holds the vehicle (``apf_companion.fenceclip``). Every exclusion
zone becomes a keep-out zone (``nav_keepout_ne_m``): its polygon, or a circle's circumscribed 32-gon (around the
circle: never narrower than the fence). Anything else (a malformed polygon; inclusion zones that do not overlap;
the vehicle outside them) leaves the planner as configured, with the reason.

The fence's parameters (``apf_companion.fencelimits``) shape this: which zones are used, the union instead of the
intersection, the circle round home (it clips the inclusion zones, or is the area when there are none), the
ceiling and the floor (goals beyond them are refused: ``FenceBounds``), and the margin, by which every edge moves
as far as the planner's clearance C does not already keep it (inclusion zones in, exclusion zones out; a vehicle
already within it gets the zone as uploaded, ``provisional``, until a later read).

The download is driven by ``due`` (what to send now) and the ``on_*`` answers; each request is repeated after
``timeout_s``, at most ``retries`` times, then the download fails with its reason.
"""

from __future__ import annotations

import dataclasses
import enum
import math
from collections.abc import Sequence
from dataclasses import dataclass, field

from pymavlink.dialects.v20 import ardupilotmega as mavlink

from apf_companion.fenceclip import grown_keepout, inclusion_area
from apf_companion.fencelimits import FenceLimits
from apf_companion.goal import FenceBounds, GlobalReference, ne_from_global
from apf_companion.planning import KeepOuts, PolygonNE, inside_area, polygon_problem

__all__ = ["FenceArea", "FenceDownload", "FenceItem", "FenceOutcome", "FenceSend", "FenceStage", "fence_area"]

#: Vertices of the polygon that stands for an inclusion circle (inscribed: inside the circle).
CIRCLE_VERTICES = 32
#: Fence items the download accepts, at most (ArduPilot keeps about 84 on a Pixhawk, more on an SD card).
MAX_FENCE_ITEMS = 512

_VERTEX_IN = mavlink.MAV_CMD_NAV_FENCE_POLYGON_VERTEX_INCLUSION
_VERTEX_OUT = mavlink.MAV_CMD_NAV_FENCE_POLYGON_VERTEX_EXCLUSION
_CIRCLE_IN = mavlink.MAV_CMD_NAV_FENCE_CIRCLE_INCLUSION
_CIRCLE_OUT = mavlink.MAV_CMD_NAV_FENCE_CIRCLE_EXCLUSION
_RETURN = mavlink.MAV_CMD_NAV_FENCE_RETURN_POINT
_DEG_E7 = 1e-7


@dataclass(frozen=True, slots=True, kw_only=True)
class FenceItem:
    """One fence item (MISSION_ITEM_INT with mission_type FENCE): its command, param1 (vertex count or radius
    [m]) and position (latitude, longitude in 1e-7 degrees)."""

    seq: int
    command: int  # MAV_CMD_NAV_FENCE_*
    param1: float
    x: int  # latitude [1e-7 deg]
    y: int  # longitude [1e-7 deg]


class FenceStage(enum.Enum):
    """Where a fence download is."""

    IDLE = "idle"
    COUNT = "count"  # MISSION_REQUEST_LIST sent, waiting for MISSION_COUNT
    ITEMS = "items"  # MISSION_REQUEST_INT sent, waiting for that MISSION_ITEM_INT
    DONE = "done"
    FAILED = "failed"


@dataclass(frozen=True, slots=True)
class FenceSend:
    """What the download sends now: the list request (``seq`` None), one item's request, or the closing ack."""

    seq: int | None = None
    ack: bool = False


class FenceDownload:
    """The fence download's state (module docstring); ``timeout_s`` [s] between repeats, ``retries`` repeats."""

    def __init__(self, timeout_s: float = 1.0, retries: int = 5) -> None:
        self.timeout_s = timeout_s
        self.retries = retries
        self.stage = FenceStage.IDLE
        #: Why the download failed ("" unless FAILED).
        self.reason = ""
        self.items: list[FenceItem] = []
        #: The plan id the count came with (MISSION_COUNT ``opaque_id``; 0: none, or no count yet).
        self.plan_id = 0
        #: Answers that were not the one awaited (a repeated item, a stray count): counted, dropped.
        self.unexpected = 0
        self._count = 0
        self._sent_at = -math.inf
        self._tries = 0
        self._ack_due = False

    def start(self) -> None:
        """Begin (again): ask for the count at the next ``due``."""
        self.stage, self.reason, self.items, self.plan_id = FenceStage.COUNT, "", [], 0
        self._sent_at, self._tries, self._ack_due = -math.inf, 0, False

    def rest(self) -> None:
        """Its end has been taken: IDLE until the next ``start`` (the items are kept)."""
        self.stage, self._ack_due = FenceStage.IDLE, False

    def due(self, now_s: float) -> FenceSend | None:
        """What to send at ``now_s``, if anything: a request when its answer is overdue (or not yet asked)."""
        if self._ack_due:
            self._ack_due = False
            return FenceSend(ack=True)
        if self.stage not in (FenceStage.COUNT, FenceStage.ITEMS) or now_s - self._sent_at < self.timeout_s:
            return None
        if self._tries > self.retries:
            what = "MISSION_COUNT" if self.stage is FenceStage.COUNT else f"fence item {len(self.items)}"
            self._fail(f"no {what} after {self.retries + 1} requests")
            return None
        self._tries += 1
        self._sent_at = now_s
        return FenceSend(seq=None if self.stage is FenceStage.COUNT else len(self.items))

    def on_count(self, count: int, plan_id: int = 0) -> None:
        """MISSION_COUNT (fence) from the autopilot, with its plan id (``opaque_id``; 0: none)."""
        if self.stage is not FenceStage.COUNT:
            self.unexpected += 1
            return
        if not 0 <= count <= MAX_FENCE_ITEMS:
            self._fail(f"the fence has {count} items (at most {MAX_FENCE_ITEMS} are read)")
            return
        self._count, self.plan_id = count, plan_id
        self._sent_at, self._tries = -math.inf, 0
        if count == 0:  # an empty fence is acked too: PX4 holds its one transfer state until the ack (or 5 s)
            self.stage, self._ack_due = FenceStage.DONE, True
        else:
            self.stage = FenceStage.ITEMS

    def on_item(self, item: FenceItem) -> None:
        """MISSION_ITEM_INT (fence): the awaited one is kept, any other counted and dropped."""
        if self.stage is not FenceStage.ITEMS or item.seq != len(self.items):
            self.unexpected += 1
            return
        self.items.append(item)
        self._sent_at, self._tries = -math.inf, 0
        if len(self.items) == self._count:
            self.stage, self._ack_due = FenceStage.DONE, True

    def on_ack(self, result: int) -> None:
        """MISSION_ACK (fence) during the download: the autopilot refuses (no fence support, busy)."""
        if self.stage in (FenceStage.COUNT, FenceStage.ITEMS) and result != mavlink.MAV_MISSION_ACCEPTED:
            self._fail(f"the autopilot answered MISSION_ACK {_enum_name('MAV_MISSION_RESULT', result)}")

    def _fail(self, reason: str) -> None:
        self.stage, self.reason = FenceStage.FAILED, reason


class FenceOutcome(enum.Enum):
    """What became of the autopilot's fence."""

    USED = "used"  # its zones (or its ceiling) bound the plan
    NO_FENCE = "no fence"  # the autopilot has none (count 0, no circle round home, no ceiling)
    NOT_USED = "not used"  # it has one that is not enforced, or no single inclusion zone around the vehicle
    FAILED = "failed"  # the download did not finish


@dataclass(frozen=True, slots=True)
class FenceArea:
    """A fence read as a flying area: the polygon (local NED north/east [m]) when USED, the keep-out zones, the
    bounds for goals (its ceiling, its circle round home: goals beyond them are refused) and what was done.
    ``provisional``: a part could not be applied yet (no HOME_POSITION for the circle round home, the vehicle
    within the margin of an edge); the next read tries again although the fence is the same."""

    outcome: FenceOutcome
    note: str
    polygon_ne_m: PolygonNE | None = None
    keepouts_ne_m: KeepOuts = ()
    bounds: FenceBounds = field(default_factory=FenceBounds)
    provisional: bool = False


def fence_area(
    items: Sequence[FenceItem],
    reference: GlobalReference,
    vehicle_ne_m: tuple[float, float],
    limits: FenceLimits | None = None,
    home: tuple[int, int] | None = None,
    clearance_m: float = 0.0,
) -> FenceArea:
    """The flying area of a downloaded fence (module docstring). ``reference`` places latitude/longitude in local
    NED; the vehicle at ``vehicle_ne_m`` must lie in the zone (a fence stored for another field is not used).
    ``limits``: what the autopilot enforces (``apf_companion.fencelimits``; None: its parameters were not read,
    every uploaded zone is used). ``home``: HOME_POSITION's latitude, longitude [1e-7 deg] for the circle round
    home. ``clearance_m``: the planner's clearance C, which already keeps that much of the fence's margin."""
    zones = _zones(items)
    if isinstance(zones, str):
        return _not_used(zones)
    if limits is not None and not limits.enforced:  # a fence switched off is none; one uploaded is worth a word
        return _not_used(limits.note) if items else FenceArea(FenceOutcome.NO_FENCE, limits.note)
    notes, provisional = [] if limits is None else [limits.note], False
    if limits is not None and not limits.zones:
        zones = []
    inset = 0.0 if limits is None else limits.inset_m(clearance_m)
    circle, bound = None, None
    if limits is not None and limits.home_radius_m is not None:
        if home is None:
            notes.append("no HOME_POSITION yet to place the circle round home")
            provisional = True
        else:
            centre = FenceItem(seq=-1, command=_CIRCLE_IN, param1=limits.home_radius_m, x=home[0], y=home[1])
            north, east = ne_from_global(reference, home[0] * _DEG_E7, home[1] * _DEG_E7)
            circle = (north, east, limits.home_radius_m - inset)
            if any(z.inclusion for z in zones):  # it clips them (ArduPilot checks it apart: under a union too)
                bound = _Zone(True, True, (centre,)).polygon(reference)
            else:  # it is the area (600 m across by default: on bapf-nav's moving grid)
                zones.append(_Zone(True, True, (centre,)))
    ceiling = None if limits is None else limits.ceiling_m
    floor = None if limits is None else limits.floor_m
    if not zones and ceiling is None and circle is None and floor is None:
        note = "; ".join(["the autopilot has no fence", *notes])
        return FenceArea(FenceOutcome.NO_FENCE, note, provisional=provisional)
    union = limits is not None and limits.union
    area = _used(zones, reference, vehicle_ne_m, _Combine(inset, union, bound), notes, provisional)
    if area.outcome is not FenceOutcome.USED:
        return area
    return dataclasses.replace(area, bounds=FenceBounds(ceiling, circle, floor))


@dataclass(frozen=True, slots=True)
class _Combine:
    """How the inclusion zones make the area: moved in by ``inset_m`` [m], their ``union`` (else intersection),
    clipped to ``bound`` (the circle round home's 32-gon) when there is one."""

    inset_m: float = 0.0
    union: bool = False
    bound: PolygonNE | None = None


def _used(
    zones: list[_Zone],
    reference: GlobalReference,
    vehicle_ne_m: tuple[float, float],
    how: _Combine,
    notes: list[str],
    provisional: bool,
) -> FenceArea:
    """The area of fence zones that are enforced, moved in (keep-outs out) by the margin's inset, or why it is
    not used."""
    inclusions = [z for z in zones if z.inclusion]
    exclusions = [z.polygon(reference) for z in zones if not z.inclusion]
    problems = [p for p in map(polygon_problem, exclusions) if p is not None]
    if problems:
        return _not_used(f"an exclusion zone is not {problems[0]}")
    plural = "s" if len(exclusions) != 1 else ""
    said = [f"{len(exclusions)} exclusion zone{plural} as keep-out zone{plural}"] if exclusions else []
    keepouts, kept = _grown(exclusions, how.inset_m, vehicle_ne_m)
    if not kept:
        said.append("an exclusion zone's margin not kept yet (the vehicle is within it)")
    polygon = None
    if inclusions:
        area = _inclusion_area(inclusions, reference, vehicle_ne_m, how)
        if isinstance(area, str):
            return _not_used(area)
        polygon, note, kept_in = area
        said.insert(0, note)
        kept = kept and kept_in
    return FenceArea(
        FenceOutcome.USED,
        "; ".join([*said, *notes]),
        polygon,
        tuple(keepouts),
        provisional=provisional or not kept,
    )


def _grown(zones: list[PolygonNE], grow_m: float, vehicle_ne_m: tuple[float, float]) -> tuple[list[PolygonNE], bool]:
    """The exclusion zones grown by the margin, and whether every one could be: a zone whose grown form holds the
    vehicle (it is within the margin) or that GEOS cannot grow stays as uploaded."""
    if grow_m <= 0.0:
        return zones, True
    out, kept = [], True
    for zone in zones:
        grown = grown_keepout(zone, grow_m)
        if grown is None or inside_area(grown, *vehicle_ne_m):
            out.append(zone)
            kept = False
        else:
            out.append(grown)
    return out, kept


def _inclusion_area(
    inclusions: Sequence[_Zone], reference: GlobalReference, vehicle_ne_m: tuple[float, float], how: _Combine
) -> tuple[PolygonNE, str, bool] | str:
    """The flying area of the inclusion zones, what it is and whether the margin is kept; or why there is none:
    one zone's polygon, or the piece of several zones' intersection (union) that holds the vehicle, clipped to the
    circle round home and moved in by the inset. With the vehicle within the margin of an edge, the area without
    the margin (kept: False)."""
    polygons = [z.polygon(reference) for z in inclusions]
    problems = [p for p in map(polygon_problem, polygons) if p is not None]
    if problems:
        return f"an inclusion zone is not {problems[0]}"
    n = len(polygons) + (how.bound is not None)
    if n == 1:
        what = f"inclusion {inclusions[0].kind}"
    elif how.union and len(polygons) > 1:
        what = f"union of {len(polygons)} inclusion zones{' within the circle round home' if how.bound else ''}"
    else:
        what = f"intersection of {n} inclusion zones"

    def combined(inset_m: float) -> PolygonNE | str:
        return inclusion_area(polygons, vehicle_ne_m, inset_m, union=how.union, bound=how.bound)

    if how.inset_m > 0.0:
        moved = combined(how.inset_m)
        if not isinstance(moved, str):
            return moved, f"{what}, {how.inset_m:.2g} m in from its edges, {len(moved)} vertices", True
    if n > 1:
        clipped = combined(0.0)
        if isinstance(clipped, str):
            return clipped
        return clipped, f"{what}, {len(clipped)} vertices", how.inset_m <= 0.0
    if not inside_area(polygons[0], *vehicle_ne_m):
        return "the vehicle is outside the inclusion zone"
    return polygons[0], f"{what} of {len(polygons[0])} vertices", how.inset_m <= 0.0


def _not_used(reason: str) -> FenceArea:
    return FenceArea(FenceOutcome.NOT_USED, reason)


@dataclass(frozen=True, slots=True)
class _Zone:
    """One fence zone: its items (a polygon's vertices, or one circle)."""

    inclusion: bool
    circle: bool
    items: tuple[FenceItem, ...]

    @property
    def kind(self) -> str:
        return "circle" if self.circle else "polygon"

    def polygon(self, reference: GlobalReference) -> PolygonNE:
        """The zone in local NED [m]: its vertices, or a circle's 32-gon, inscribed for an inclusion zone and
        circumscribed for an exclusion zone (the polygon never lets the vehicle where the fence would not)."""
        if not self.circle:
            return tuple(ne_from_global(reference, it.x * _DEG_E7, it.y * _DEG_E7) for it in self.items)
        centre = self.items[0]
        north, east = ne_from_global(reference, centre.x * _DEG_E7, centre.y * _DEG_E7)
        radius = float(centre.param1) / (1.0 if self.inclusion else math.cos(math.pi / CIRCLE_VERTICES))
        turns = [k * math.tau / CIRCLE_VERTICES for k in range(CIRCLE_VERTICES)]
        return tuple((north + radius * math.cos(a), east + radius * math.sin(a)) for a in turns)


def _zones(items: Sequence[FenceItem]) -> list[_Zone] | str:
    """The items grouped into zones, or why they cannot be (the item and what is wrong with it)."""
    zones: list[_Zone] = []
    i = 0
    while i < len(items):
        it = items[i]
        if not (abs(it.x) <= 900_000_000 and abs(it.y) <= 1_800_000_000):
            return f"fence item {i}: latitude/longitude out of range"
        if it.command == _RETURN:
            i += 1
        elif it.command in (_CIRCLE_IN, _CIRCLE_OUT):
            if not (math.isfinite(it.param1) and it.param1 > 0.0):
                return f"fence item {i}: circle radius {it.param1!r}"
            zones.append(_Zone(it.command == _CIRCLE_IN, True, (it,)))
            i += 1
        elif it.command in (_VERTEX_IN, _VERTEX_OUT):
            count = int(it.param1) if math.isfinite(it.param1) else 0
            group = tuple(items[i : i + count])
            if count < 3 or len(group) < count or any(g.command != it.command for g in group):
                return f"fence item {i}: a polygon of {it.param1!r} vertices that its items do not make"
            zones.append(_Zone(it.command == _VERTEX_IN, False, group))
            i += count
        else:
            return f"fence item {i}: command {it.command} is no fence item"
    return zones


def _enum_name(enum_name: str, value: int) -> str:
    """A MAVLink enum value's name from pymavlink's dialect (the number when unknown)."""
    entry = mavlink.enums.get(enum_name, {}).get(value)
    return entry.name if entry is not None else str(value)
