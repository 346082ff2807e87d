"""Goals and routes: from the config, the command line, a route file, zenoh, or a ground station.

A ``Route`` is one or more waypoints in local NED; ``down`` may be NaN, meaning "keep the altitude the vehicle
has when that leg starts". A new goal from any source replaces the whole active route.

Ground stations send MAV_CMD_DO_REPOSITION (192) as COMMAND_INT addressed to the companion's component.
Interpretation by ``frame`` (decided here, documented in docs/service.md):

- MAV_FRAME_LOCAL_NED (1): ``x``, ``y`` are int32 north/east in metres * 1e4 (MAVLink's scaling of local
  positions in COMMAND_INT), ``z`` is down in metres (float). NaN ``z`` keeps the altitude.
- MAV_FRAME_GLOBAL (0), GLOBAL_INT (5): ``x``, ``y`` latitude/longitude in degE7, ``z`` altitude AMSL [m];
  MAV_FRAME_GLOBAL_RELATIVE_ALT (3), GLOBAL_RELATIVE_ALT_INT (6): ``z`` above home [m]. Converted to local NED
  about the vehicle's latest GLOBAL_POSITION_INT / LOCAL_POSITION_NED pair (flat earth; fine within a few km).
- Other frames: MAV_RESULT_UNSUPPORTED. No global reference yet: MAV_RESULT_TEMPORARILY_REJECTED.
  Coordinates no goal can have (z = +-inf, latitude/longitude out of range, a waypoint more than ``MAX_LOCAL_M``
  from the origin: ``Route``): MAV_RESULT_DENIED. COMMAND_LONG DO_REPOSITION: MAV_RESULT_COMMAND_INT_ONLY.
  A goal that is a place but lies outside the limits (``route_outside_limits``, checked by goal admission) is
  answered TEMPORARILY_REJECTED by the handlers (docs/hardening.md, Goals).
"""

from __future__ import annotations

import csv
import io
import math
import tomllib
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import numpy.typing as npt
from pymavlink.dialects.v20 import ardupilotmega as mavlink

from apf_companion.errors import ConfigError, ProtocolError
from apf_companion.planning.area import FlyingArea, KeepOuts, area_text, zone_conflict

__all__ = [
    "EARTH_RADIUS_M",
    "GlobalReference",
    "RepositionError",
    "Route",
    "load_route",
    "local_goal_from_reposition",
    "ne_from_global",
    "parse_goal_text",
    "route_check_waits",
    "route_outside_limits",
]

FloatArray = npt.NDArray[np.float64]
EARTH_RADIUS_M = 6_378_137.0  # WGS-84 equatorial radius, for the flat-earth conversion
MAX_LOCAL_M = 100_000.0  # goals farther than this from the origin are refused as absurd

MAV_FRAME_GLOBAL = mavlink.MAV_FRAME_GLOBAL
MAV_FRAME_LOCAL_NED = mavlink.MAV_FRAME_LOCAL_NED
MAV_FRAME_GLOBAL_RELATIVE_ALT = mavlink.MAV_FRAME_GLOBAL_RELATIVE_ALT
MAV_FRAME_GLOBAL_INT = mavlink.MAV_FRAME_GLOBAL_INT
MAV_FRAME_GLOBAL_RELATIVE_ALT_INT = mavlink.MAV_FRAME_GLOBAL_RELATIVE_ALT_INT
_GLOBAL_AMSL = (MAV_FRAME_GLOBAL, MAV_FRAME_GLOBAL_INT)
_GLOBAL_REL = (MAV_FRAME_GLOBAL_RELATIVE_ALT, MAV_FRAME_GLOBAL_RELATIVE_ALT_INT)


@dataclass(frozen=True, slots=True, kw_only=True, eq=False)
class Route:
    """Waypoints to fly in order.

    Attributes:
        waypoints_ned_m: (W, 3) float64 local NED [m], W >= 1; NaN down = keep the altitude of that leg's start.
        source: Where it came from ("config", "cli", "zenoh", "mavlink:255/190", ...), for logs and status.
    """

    waypoints_ned_m: FloatArray
    source: str = "config"

    def __post_init__(self) -> None:
        arr = np.array(self.waypoints_ned_m, dtype=np.float64, copy=True)
        if arr.ndim == 1:
            arr = arr[None, :]
        if arr.ndim != 2 or arr.shape[1] != 3 or arr.shape[0] == 0:
            msg = f"waypoints_ned_m must have shape (W, 3) with W >= 1, got {arr.shape}"
            raise ConfigError(msg)
        if not np.all(np.isfinite(arr[:, :2])) or np.any(np.isinf(arr[:, 2])):
            msg = "waypoint north/east must be finite and down finite or NaN (keep altitude)"
            raise ConfigError(msg)
        if np.any(np.abs(np.nan_to_num(arr)) > MAX_LOCAL_M):
            msg = f"waypoints must lie within {MAX_LOCAL_M:g} m of the origin"
            raise ConfigError(msg)
        arr.setflags(write=False)
        object.__setattr__(self, "waypoints_ned_m", arr)

    @classmethod
    def point(cls, north_m: float, east_m: float, down_m: float | None = None, *, source: str) -> Route:
        """A one-leg route; ``down_m`` None keeps the altitude."""
        down = math.nan if down_m is None else down_m
        return cls(waypoints_ned_m=np.array([[north_m, east_m, down]]), source=source)

    def __len__(self) -> int:
        return int(self.waypoints_ned_m.shape[0])

    def to_json_list(self) -> list[list[float | None]]:
        """Waypoints as JSON-friendly lists (NaN down as null)."""
        return [[None if math.isnan(v) else float(v) for v in row] for row in self.waypoints_ned_m]


def parse_goal_text(text: str, *, source: str = "cli") -> Route:
    """Parse ``"N,E"`` or ``"N,E,D"`` (metres, local NED) from the command line.

    Raises:
        ConfigError: not two or three finite numbers.
    """
    parts = [p.strip() for p in text.replace(";", ",").split(",") if p.strip()]
    try:
        values = [float(p) for p in parts]
    except ValueError as err:
        msg = f"--goal must be 'NORTH,EAST[,DOWN]' in metres, got {text!r}"
        raise ConfigError(msg) from err
    if len(values) not in (2, 3) or not all(math.isfinite(v) for v in values):
        msg = f"--goal must be 'NORTH,EAST[,DOWN]' in metres (finite), got {text!r}"
        raise ConfigError(msg)
    return Route.point(values[0], values[1], values[2] if len(values) == 3 else None, source=source)


def _waypoint_from_table(i: int, table: Any) -> list[float]:
    if not isinstance(table, dict):
        msg = f"waypoint[{i}] must be a table with north_m, east_m[, down_m]"
        raise ConfigError(msg)
    unknown = set(table) - {"north_m", "east_m", "down_m"}
    if unknown:
        msg = f"waypoint[{i}] has unknown keys {sorted(unknown)} (allowed: north_m, east_m, down_m)"
        raise ConfigError(msg)
    row: list[float] = []
    for key in ("north_m", "east_m", "down_m"):
        value = table.get(key, math.nan if key == "down_m" else None)
        if value is None or isinstance(value, bool) or not isinstance(value, int | float):
            msg = f"waypoint[{i}].{key} must be a number, got {value!r}"
            raise ConfigError(msg)
        row.append(float(value))
    return row


def load_route(path: Path | str, *, source: str = "route") -> Route:
    """Read a route file: TOML with ``[[waypoint]]`` tables (``north_m``, ``east_m``, optional ``down_m``), or
    CSV / plain text with one ``north,east[,down]`` per line (``#`` comments and a header line allowed).

    Raises:
        ConfigError: unreadable file, bad format, or no waypoint.
    """
    p = Path(path)
    try:
        text = p.read_text(encoding="utf-8")
    except OSError as err:
        msg = f"cannot read route file {p}: {err.strerror}"
        raise ConfigError(msg) from err
    rows: list[list[float]] = []
    if p.suffix.lower() == ".toml":
        try:
            data = tomllib.loads(text)
        except tomllib.TOMLDecodeError as err:
            msg = f"route file {p} is not valid TOML: {err}"
            raise ConfigError(msg) from err
        unknown = set(data) - {"waypoint"}
        if unknown:
            msg = f"route file {p}: unknown keys {sorted(unknown)} (expected [[waypoint]] tables)"
            raise ConfigError(msg)
        tables = data.get("waypoint", [])
        if not isinstance(tables, list):
            msg = f"route file {p}: 'waypoint' must be an array of tables ([[waypoint]])"
            raise ConfigError(msg)
        rows = [_waypoint_from_table(i, t) for i, t in enumerate(tables)]
    else:
        for lineno, raw in enumerate(csv.reader(io.StringIO(text)), start=1):
            cells = [c.strip() for c in raw]
            if not cells or not cells[0] or cells[0].startswith("#"):
                continue
            try:
                values = [float(c) for c in cells if c]
            except ValueError as err:
                if not rows and lineno == 1:
                    continue  # a header line
                msg = f"route file {p}, line {lineno}: expected 'north,east[,down]' numbers, got {raw}"
                raise ConfigError(msg) from err
            if len(values) not in (2, 3):
                msg = f"route file {p}, line {lineno}: expected 2 or 3 numbers, got {len(values)}"
                raise ConfigError(msg)
            rows.append([*values, math.nan] if len(values) == 2 else values)
    if not rows:
        msg = f"route file {p} has no waypoint"
        raise ConfigError(msg)
    return Route(waypoints_ned_m=np.array(rows, dtype=np.float64), source=source)


@dataclass(frozen=True, slots=True, kw_only=True)
class GlobalReference:
    """The vehicle at one moment in both frames: lets global goals become local NED ones.

    Attributes:
        lat_deg, lon_deg: From GLOBAL_POSITION_INT [deg].
        alt_amsl_m: GLOBAL_POSITION_INT.alt [m].
        alt_rel_m: GLOBAL_POSITION_INT.relative_alt (above home) [m].
        pos_ned_m: LOCAL_POSITION_NED at (about) the same time, (x, y, z) [m].
    """

    lat_deg: float
    lon_deg: float
    alt_amsl_m: float
    alt_rel_m: float
    pos_ned_m: tuple[float, float, float]


def ne_from_global(reference: GlobalReference, lat_deg: float, lon_deg: float) -> tuple[float, float]:
    """A latitude/longitude [deg] as local NED (north, east) [m]: flat earth around the reference (the areas flown
    are tens of metres across, where the error is millimetres)."""
    dn = math.radians(lat_deg - reference.lat_deg) * EARTH_RADIUS_M
    de = math.radians(lon_deg - reference.lon_deg) * EARTH_RADIUS_M * math.cos(math.radians(reference.lat_deg))
    return reference.pos_ned_m[0] + dn, reference.pos_ned_m[1] + de


class RepositionError(ProtocolError):
    """A DO_REPOSITION that cannot be turned into a goal; ``result`` is the MAV_RESULT to answer with."""

    def __init__(self, result: int, reason: str) -> None:
        self.result = result
        super().__init__(reason)


def local_goal_from_reposition(
    *, frame: int, x: int, y: int, z: float, reference: GlobalReference | None, source: str
) -> Route:
    """Turn COMMAND_INT DO_REPOSITION (frame, x, y, z) into a one-leg Route (see the module docstring).

    Raises:
        RepositionError: with the MAV_RESULT to answer (UNSUPPORTED=3, DENIED=2, TEMPORARILY_REJECTED=1).
    """
    if math.isinf(z):
        # MAV_CMD_DO_REPOSITION (common.xml): only NaN means "keep the current altitude"; +-inf is not a height.
        raise RepositionError(
            mavlink.MAV_RESULT_DENIED, f"DO_REPOSITION altitude {z} is not a number (NaN keeps the altitude)"
        )
    z_keep = math.isnan(z)
    if frame == MAV_FRAME_LOCAL_NED:
        north_m, east_m = x * 1e-4, y * 1e-4
        down_m = None if z_keep else float(z)
    elif frame in _GLOBAL_AMSL or frame in _GLOBAL_REL:
        if reference is None:
            raise RepositionError(
                mavlink.MAV_RESULT_TEMPORARILY_REJECTED, "no GLOBAL_POSITION_INT yet: cannot place a global goal"
            )
        lat_deg, lon_deg = x * 1e-7, y * 1e-7
        if not (-90.0 <= lat_deg <= 90.0 and -180.0 <= lon_deg <= 180.0):
            raise RepositionError(mavlink.MAV_RESULT_DENIED, f"latitude/longitude out of range: {lat_deg}, {lon_deg}")
        north_m, east_m = ne_from_global(reference, lat_deg, lon_deg)
        if z_keep:
            down_m = None
        else:
            now_alt = reference.alt_amsl_m if frame in _GLOBAL_AMSL else reference.alt_rel_m
            down_m = reference.pos_ned_m[2] - (float(z) - now_alt)
    else:
        raise RepositionError(
            mavlink.MAV_RESULT_UNSUPPORTED, f"DO_REPOSITION frame {frame} unsupported (use LOCAL_NED or a GLOBAL frame)"
        )
    try:
        return Route.point(north_m, east_m, down_m, source=source)
    except ConfigError as err:
        raise RepositionError(mavlink.MAV_RESULT_DENIED, str(err)) from err


@dataclass(frozen=True, slots=True)
class FenceBounds:
    """What the autopilot's fence allows a goal besides the planner's zones: its ceiling (the highest goal above
    home [m], its altitude limit less its margin) and its circle round home (north, east, radius [m] in local NED,
    the radius less the margin), each None when the fence has none (``apf_companion.fence``)."""

    ceiling_m: float | None = None
    home_circle: tuple[float, float, float] | None = None
    #: The lowest goal above home [m] (its minimum altitude plus its margin), or None.
    floor_m: float | None = None


def route_outside_limits(
    route: Route,
    pos_ned_m: npt.ArrayLike | None,
    *,
    max_altitude_m: float,
    max_distance_m: float,
    min_altitude_m: float | None = None,
    area_ne_m: FlyingArea | None = None,
    keepouts_ne_m: KeepOuts = (),
    fence: FenceBounds = FenceBounds(),
) -> str | None:
    """Why ``route`` is refused, or None: a waypoint more than ``max_altitude_m`` above the EKF origin (home),
    less than ``min_altitude_m`` above it (negative: that far below it), or outside the autopilot's fence
    (``fence``: above its ceiling, below its floor, outside its circle round home), or horizontally more than
    ``max_distance_m`` from the vehicle at ``pos_ned_m`` (local NED; None: not known yet), or outside the planner's
    flying area ``area_ne_m`` (a rectangle or polygon, ``planning.area``) or in one of its keep-out zones
    ``keepouts_ne_m`` (bapf-nav would give up at once). ``max_altitude_m`` / ``max_distance_m`` 0 and
    ``min_altitude_m`` None = no limit; of two ceilings (floors) the lower (higher) one counts. A waypoint that keeps
    the altitude (NaN down) passes the altitude limits. A mistyped or hostile goal is refused, not flown: the fuzz
    sent DO_REPOSITION z = -8576 m, a review z = +1000 m (1 km below home)."""
    wp = route.waypoints_ned_m
    conflict = zone_conflict(area_ne_m, keepouts_ne_m, wp[:, 0], wp[:, 1])
    if conflict is not None:
        i = conflict.index
        point = f"waypoint {i} (north {wp[i, 0]:g} m, east {wp[i, 1]:g} m)"
        if conflict.keepout is None:
            assert area_ne_m is not None  # only an area leaves a point outside
            return f"{point} lies outside the flying area planner.params.nav_area_ne_m = {area_text(area_ne_m)}"
        return f"{point} lies in keep-out zone {conflict.keepout} (planner.params.nav_keepout_ne_m)"
    if fence.home_circle is not None:
        north, east, radius = fence.home_circle
        far = np.flatnonzero(np.hypot(wp[:, 0] - north, wp[:, 1] - east) > radius)
        if far.size:
            i = int(far[0])
            return f"waypoint {i} lies outside the fence's circle round home (radius less its margin {radius:g} m)"
    limits = [(max_altitude_m, "goal.max_altitude_m")] if max_altitude_m > 0.0 else []
    if fence.ceiling_m is not None:
        limits.append((fence.ceiling_m, "the fence's ceiling less its margin"))
    up = -wp[:, 2]
    for limit, name in limits:
        high = np.flatnonzero(np.isfinite(up) & (up > limit))
        if high.size:
            i = int(high[0])
            return f"waypoint {i} is {_height_text(float(up[i]))} ({name} = {limit:g})"
    floors = [(min_altitude_m, "goal.min_altitude_m")] if min_altitude_m is not None else []
    if fence.floor_m is not None:
        floors.append((fence.floor_m, "the fence's floor plus its margin"))
    if floors:
        floor, name = max(floors, key=lambda f: f[0])  # the stricter floor: a waypoint below the other is below it
        low = np.flatnonzero(np.isfinite(up) & (up < floor))
        if low.size:
            i = int(low[0])
            return f"waypoint {i} is {_height_text(float(up[i]))} ({name} = {floor:g})"
    if max_distance_m > 0.0 and pos_ned_m is not None:
        pos = np.asarray(pos_ned_m, dtype=np.float64)
        far = np.flatnonzero(np.hypot(wp[:, 0] - pos[0], wp[:, 1] - pos[1]) > max_distance_m)
        if far.size:
            return f"waypoint {int(far[0])} is more than goal.max_distance_m = {max_distance_m:g} m away"
    return None


def _height_text(up_m: float) -> str:
    """A height relative to home for a refusal: "6 m above home", "30 m below home", to 0.1 m."""
    return f"{round(abs(up_m), 1):g} m {'below' if up_m < 0.0 else 'above'} home"


def route_check_waits(pos_ned_m: npt.ArrayLike | None, *, max_distance_m: float) -> str | None:
    """Why a goal that passed ``route_outside_limits`` cannot be flown yet, or None: its check needs the vehicle's
    position (``max_distance_m`` > 0) and none is known yet (a goal set at the first HEARTBEAT, before any pose).
    Such a goal is held, not flown, and checked again when the position arrives (docs/hardening.md)."""
    if max_distance_m > 0.0 and pos_ned_m is None:
        return "goal waits for a position to check goal.max_distance_m"
    return None
