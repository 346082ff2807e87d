"""The simulated autopilot enforces its fence: a breach, and the autopilot's action on it.

ArduPilot (``libraries/AC_Fence/AC_Fence.cpp`` ``check``, ``ArduCopter/fence.cpp`` ``fence_check``): while the fence
is switched on (``sim.vehicle.fenceswitch``), the fences ``FENCE_TYPE`` configures are checked: the ceiling (bit 1:
height above home >= ``FENCE_ALT_MAX``), the circle round home (bit 2: distance >= ``FENCE_RADIUS``) and the
uploaded zones (bit 4: outside an inclusion zone, all of them or, with ``FENCE_OPTIONS`` bit 1, any; or inside an
exclusion zone). ``FENCE_ENABLE`` does not switch the floor on (``enabled_fences = configured & ~ALT_MIN``): not
modelled. A fence newly breached while armed and flying says ``"<Polygon> fence breached"`` (NOTICE) and, unless
``FENCE_ACTION`` is 0 (report only), changes mode: 2 (always land) and 5 (SmartRTL or land) LAND, 4 BRAKE, the
others RTL (SmartRTL is not simulated: 3 falls back to RTL, as ArduCopter does when SmartRTL cannot start); more than
100 m out (``AC_FENCE_GIVE_UP_DISTANCE``) it lands. The breach clears when the vehicle is back inside; SYS_STATUS's
GEOFENCE health bit is clear while it lasts.

PX4 (``src/modules/navigator/geofence.cpp``, ``navigator_main.cpp``): while ``GF_ACTION`` is not 0 (None), the
circle round home (``GF_MAX_HOR_DIST``), the ceiling (``GF_MAX_VER_DIST``) and the uploaded zones (inside one
inclusion zone at least, no exclusion zone) are checked. A new breach says "Geofence violation" (CRITICAL);
``GF_ACTION`` 1 only warns, 2 Hold, 3 Return, 5 Land; 4 (Terminate) is flown as Land here: flight termination
(motors off) is not simulated.

Both refuse to arm while a fence is breached (``arming_refusal``). Not modelled: the backup fences 20 m further out
that repeat the action, ArduPilot's manual recovery, and FENCE_ACTION 6/7 (GUIDED to the return point: RTL here).
"""

from __future__ import annotations

import enum
import math
from collections.abc import Callable
from dataclasses import dataclass
from typing import TYPE_CHECKING

import shapely
from pymavlink.dialects.v20 import ardupilotmega as mavlink

from apf_companion.autopilot import PX4_HOLD, Autopilot, CopterMode
from sim.vehicle.geo import latlon_to_ne
from sim.vehicle.missionwire import FenceItemRaw

if TYPE_CHECKING:
    from sim.vehicle.config import HomeConfig
    from sim.vehicle.engine import VehicleEngine

__all__ = ["FenceGuard", "FenceKind", "arming_refusal", "check_fence", "fence_names", "fence_zones"]

#: ``AC_FENCE_GIVE_UP_DISTANCE``: a breach further out than this lands instead of returning [m].
GIVE_UP_M = 100.0
_UNION = 2  # FENCE_OPTIONS bit 1
_CIRCLE_SEGMENTS = 16  # quarter-circle segments of a circular zone (shapely's buffer)


class FenceKind(enum.IntFlag):
    """``AC_Fence.h`` ``AC_FENCE_TYPE_*``, in the order of ArduPilot's fence names."""

    ALT_MAX = 1
    CIRCLE = 2
    POLYGON = 4


NO_BREACH = FenceKind(0)
_NAMES = {FenceKind.ALT_MAX: "Max Alt", FenceKind.CIRCLE: "Circle", FenceKind.POLYGON: "Polygon"}


@dataclass(frozen=True, slots=True)
class Zones:
    """The uploaded zones in local NED north/east about home [m], as shapely geometries."""

    inclusion: tuple[shapely.Geometry, ...]
    exclusion: tuple[shapely.Geometry, ...]


@dataclass(slots=True)
class FenceGuard:
    """The fences breached now and how many new breaches there were; the zones of the items last checked."""

    breached: FenceKind = NO_BREACH
    breaches: int = 0
    _items: list[FenceItemRaw] | None = None
    _zones: Zones = Zones((), ())

    def zones(self, items: list[FenceItemRaw], home: HomeConfig) -> Zones:
        if items is not self._items:  # an upload replaces the list: built again
            self._items, self._zones = items, fence_zones(items, home)
        return self._zones


def fence_zones(items: list[FenceItemRaw], home: HomeConfig) -> Zones:
    """The zones of fence items (polygons of ``param1`` vertices, circles of radius ``param1``); return points and
    items that make no zone are left out. The simulator's own reading, not ``apf_companion.fence``'s: the autopilot
    judges the service's flight, so it must not share the service's parsing (a bug there would pass unseen)."""
    inclusion: list[shapely.Geometry] = []
    exclusion: list[shapely.Geometry] = []
    i = 0
    while i < len(items):
        command, param1, lat, lon = items[i]
        if command in _POLYGONS:
            n = max(int(param1), 1)
            ring = [latlon_to_ne(home, it[2] * 1e-7, it[3] * 1e-7) for it in items[i : i + n]]
            zone = shapely.Polygon(ring) if len(ring) >= 3 else None
            i += n
        elif command in _CIRCLES:
            zone = shapely.Point(latlon_to_ne(home, lat * 1e-7, lon * 1e-7)).buffer(param1, _CIRCLE_SEGMENTS)
            i += 1
        else:
            zone, i = None, i + 1
        if zone is not None and zone.is_valid:
            kind = _POLYGONS.get(command, _CIRCLES.get(command))
            (inclusion if kind else exclusion).append(zone)
    return Zones(tuple(inclusion), tuple(exclusion))


_POLYGONS = {
    mavlink.MAV_CMD_NAV_FENCE_POLYGON_VERTEX_INCLUSION: True,
    mavlink.MAV_CMD_NAV_FENCE_POLYGON_VERTEX_EXCLUSION: False,
}
_CIRCLES = {mavlink.MAV_CMD_NAV_FENCE_CIRCLE_INCLUSION: True, mavlink.MAV_CMD_NAV_FENCE_CIRCLE_EXCLUSION: False}


def _zones_breach_m(zones: Zones, north: float, east: float, union: bool) -> float | None:
    """How far [m] the point is outside the zones' allowed area: outside the inclusion zones (one of them; with
    ``union``, all of them) or inside an exclusion zone. None: not outside."""
    p = shapely.Point(north, east)
    beyond: list[float] = []
    if zones.inclusion:
        gaps = [z.distance(p) for z in zones.inclusion]  # 0 inside or on the edge
        gap = min(gaps) if union else max(gaps)
        if gap > 0.0:
            beyond.append(gap)
    beyond += [z.exterior.distance(p) for z in zones.exclusion if z.contains(p)]
    return max(beyond) if beyond else None


@dataclass(frozen=True, slots=True)
class _Limits:
    """What one profile checks now: its ceiling and circle [m] (None: not checked), its zones, their union."""

    ceiling_m: float | None
    radius_m: float | None
    zones: bool
    union: bool


def _ardupilot_limits(v: VehicleEngine) -> _Limits | None:
    """The fences ``FENCE_TYPE`` configures, while the fence is switched on (None: off)."""
    p = v.params
    if not v.fence.switch.follow(p["FENCE_ENABLE"] == 1.0):
        return None
    kinds = int(p["FENCE_TYPE"])
    return _Limits(
        p["FENCE_ALT_MAX"] if kinds & FenceKind.ALT_MAX else None,
        p["FENCE_RADIUS"] if kinds & FenceKind.CIRCLE else None,
        bool(kinds & FenceKind.POLYGON),
        bool(int(p["FENCE_OPTIONS"]) & _UNION),
    )


def _px4_limits(v: VehicleEngine) -> _Limits | None:
    """The circle and ceiling where set (> 0), and the zones, while ``GF_ACTION`` is not None (None: checks off)."""
    p = v.params
    if p["GF_ACTION"] == 0.0:
        return None
    ver, hor = p["GF_MAX_VER_DIST"], p["GF_MAX_HOR_DIST"]
    return _Limits(ver if ver > 0.0 else None, hor if hor > 0.0 else None, zones=True, union=True)


def _breaches(v: VehicleEngine, limits: _Limits) -> dict[FenceKind, float]:
    """The fences breached now and how far out [m]."""
    north, east, down = (float(x) for x in v.state.pos_ned_m)
    out: dict[FenceKind, float] = {}
    if limits.ceiling_m is not None and -down >= limits.ceiling_m:
        out[FenceKind.ALT_MAX] = -down - limits.ceiling_m
    from_home_m = math.hypot(north, east)
    if limits.radius_m is not None and from_home_m >= limits.radius_m:
        out[FenceKind.CIRCLE] = from_home_m - limits.radius_m
    if limits.zones and v.fence.items:
        beyond = _zones_breach_m(v.fence.guard.zones(v.fence.items, v.fence.home), north, east, limits.union)
        if beyond is not None:
            out[FenceKind.POLYGON] = beyond
    return out


def check_fence(v: VehicleEngine) -> None:
    """One fence check (each physics step): a new breach while armed and flying is said and acted on."""
    guard = v.fence.guard
    rules = _RULES[v.profile]
    limits = rules.limits(v)
    now = {} if limits is None else _breaches(v, limits)
    breached = FenceKind(sum(now, NO_BREACH))
    new = breached & ~guard.breached
    guard.breached = breached
    if not new or not v.armed or v.state.on_ground:
        return
    guard.breaches += 1
    rules.act(v, new, max(d for kind, d in now.items() if kind & new))


def fence_names(kinds: FenceKind) -> str:
    """ArduPilot's names of fences (``AC_Fence::get_fence_names``): "Polygon fence", "Max Alt and Circle fences"."""
    names = [name for kind, name in _NAMES.items() if kind & kinds]
    return " and ".join(names) + (" fences" if len(names) > 1 else " fence")


def arming_refusal(v: VehicleEngine) -> str | None:
    """Both autopilots refuse to arm while a fence is breached; None: no breach. ArduPilot: ``AC_Fence::pre_arm_check``
    through ``AP_Arming::fence_checks`` (a forced arm skips it); PX4: the commander's arming check while GF_ACTION
    is not None (``arm_requirements.geofence && geofence_violated``)."""
    breached = v.fence.guard.breached
    return _RULES[v.profile].refusal(breached) if breached else None


def _ardupilot_action(v: VehicleEngine, new: FenceKind, beyond_m: float) -> None:
    v.statustext(mavlink.MAV_SEVERITY_NOTICE, f"{fence_names(new)} breached")
    action = round(v.params["FENCE_ACTION"])
    if action == 0:
        return
    mode = _AP_ACTIONS.get(action, CopterMode.RTL) if beyond_m <= GIVE_UP_M else CopterMode.LAND
    v.set_mode(int(mode), "fence breach")


#: FENCE_ACTION -> the mode ArduCopter enters (``fence_check``; SmartRTL is not simulated, its fallbacks are used).
_AP_ACTIONS = {1: CopterMode.RTL, 2: CopterMode.LAND, 3: CopterMode.RTL, 4: CopterMode.BRAKE, 5: CopterMode.LAND}


def _px4_action(v: VehicleEngine, _new: FenceKind, _beyond_m: float) -> None:
    v.statustext(mavlink.MAV_SEVERITY_CRITICAL, "Geofence violation")
    action = round(v.params["GF_ACTION"])  # 1 (Warning): nothing more; 4 (Terminate): Land here
    rules = v.profile_rules
    mode = {2: PX4_HOLD.to_custom_mode(), 3: rules.rtl_mode, 4: rules.land_mode, 5: rules.land_mode}.get(action)
    if mode is not None:
        v.set_mode(mode, "geofence breach")


@dataclass(frozen=True, slots=True)
class _FenceRules:
    """One profile's fence: what it checks now, what it does on a new breach (the fences newly breached, how far
    out [m]), and its arming refusal while breached."""

    limits: Callable[[VehicleEngine], _Limits | None]
    act: Callable[[VehicleEngine, FenceKind, float], None]
    refusal: Callable[[FenceKind], str]


_RULES = {
    Autopilot.ARDUPILOT: _FenceRules(
        _ardupilot_limits, _ardupilot_action, lambda breached: f"PreArm: Vehicle breaching {fence_names(breached)}"
    ),
    Autopilot.PX4: _FenceRules(_px4_limits, _px4_action, lambda _breached: "Arming denied, vehicle outside geofence"),
}
