"""The autopilot's fence parameters: which of its fences are configured and switched on, how far its own planners
keep from them, its circle round home, its ceiling and how its inclusion zones combine. Read over
PARAM_REQUEST_READ (``ParamRead``, a state machine on an injected clock) and turned into ``FenceLimits``
(``fence_limits``), which ``apf_companion.fence`` applies to the zones.

ArduPilot (``libraries/AC_Fence/AC_Fence.cpp``):
- ``FENCE_TYPE`` (bitmask) says which fences are configured: 1 maximum altitude, 2 a circle of ``FENCE_RADIUS``
  [m] round home, 4 the uploaded inclusion/exclusion polygons and circles, 8 minimum altitude (``FENCE_ALT_MIN``
  [m above home]: goals below it plus the margin, ``get_safe_alt_min_m``, are refused).
- The uploaded zones are used whenever FENCE_TYPE configures them, whatever ``FENCE_ENABLE`` says: the user
  drew them, and since ArduPilot 4.6 a fence is also switched on at run time without that parameter changing
  (an RC switch, MAV_CMD_DO_FENCE_ENABLE, ``FENCE_AUTOENABLE`` on arming: "these changes are not persisted").
  Planning inside a fence that is not switched on is never unsafe.
- The circle round home, the ceiling (``FENCE_ALT_MAX`` [m above home]) and the floor are used only while the fence is
  switched on: ``FENCE_ENABLE`` 1, or SYS_STATUS's GEOFENCE bit enabled (``libraries/GCS_MAVLink/GCS.cpp``
  ``update_sensor_status_flags``: configured, switched on at run time, FENCE_ACTION not report-only). Every Copter
  has them configured by default (FENCE_TYPE 7, 300 m, 100 m), so with the fence off they say nothing about this
  flight, and a 1 km transect with the fence off must not be refused.
- ``FENCE_MARGIN`` [m]: how far the autopilot's planners keep from every fence (the path's distance to a polygon
  minus the margin, ``libraries/AC_Avoidance/AP_OABendyRuler.cpp``; the ceiling less the margin,
  ``get_safe_alt_max``). ``FENCE_MARGIN_XY`` (4.6+, read when the autopilot has it) replaces it horizontally when
  positive (``get_margin_ne_m``). bapf-nav keeps the same: the zones' edges move in by the part of the margin that
  its own clearance C does not already keep.
- ``FENCE_OPTIONS`` bit 1 (read when the autopilot has it): the allowed area is the union of the inclusion zones
  instead of their intersection (``AC_PolyFence_loader.cpp``); the circle round home still bounds it.
PX4 (``src/modules/navigator/geofence_params.c``):
- ``GF_MAX_HOR_DIST`` [m from home] and ``GF_MAX_VER_DIST`` [m above home], 0 = off (the default), used while
  ``GF_ACTION`` is not 0 (None): PX4 checks for a breach only then (``geofence_breach_check``, navigator), as
  ArduPilot's circle and ceiling count only while its fence is on. The uploaded zones are always used. PX4 has no
  margin parameter: the zones keep bapf-nav's clearance C only.

The parameters are read again at every fence read (``planner.fence_poll_s``). Values come as floats; ArduPilot
casts integer parameters to float, PX4 sends an INT32's bytes in the float
(MAV_PROTOCOL_CAPABILITY_PARAM_ENCODE_BYTEWISE): ``param_float`` undoes that.
"""

from __future__ import annotations

import enum
import math
import struct
from collections.abc import Mapping
from dataclasses import dataclass

from pymavlink.dialects.v20 import ardupilotmega as mavlink

from apf_companion.autopilot import Autopilot

__all__ = ["FENCE_PARAMS", "OPTIONAL_PARAMS", "FenceLimits", "ParamRead", "ReadStage", "fence_limits", "param_float"]

#: The parameters read, per autopilot: the ones the read needs, and ones an autopilot may not have (newer
#: firmware): those that stay unanswered are taken as absent.
FENCE_PARAMS: dict[Autopilot, tuple[str, ...]] = {
    Autopilot.ARDUPILOT: ("FENCE_ENABLE", "FENCE_TYPE", "FENCE_RADIUS", "FENCE_ALT_MAX", "FENCE_MARGIN"),
    Autopilot.PX4: ("GF_ACTION", "GF_MAX_HOR_DIST", "GF_MAX_VER_DIST"),
}
OPTIONAL_PARAMS: dict[Autopilot, tuple[str, ...]] = {
    Autopilot.ARDUPILOT: ("FENCE_MARGIN_XY", "FENCE_OPTIONS", "FENCE_ALT_MIN"),
    Autopilot.PX4: (),
}

# AC_Fence.h: the FENCE_TYPE bits
_TYPE_ALT_MAX = 1
_TYPE_CIRCLE = 2
_TYPE_POLYGON = 4
_TYPE_ALT_MIN = 8
_OPTION_UNION = 2  # FENCE_OPTIONS bit 1

_INT_TYPES = (
    mavlink.MAV_PARAM_TYPE_INT8,
    mavlink.MAV_PARAM_TYPE_UINT8,
    mavlink.MAV_PARAM_TYPE_INT16,
    mavlink.MAV_PARAM_TYPE_UINT16,
    mavlink.MAV_PARAM_TYPE_INT32,
    mavlink.MAV_PARAM_TYPE_UINT32,
)


def param_float(value: float, param_type: int, profile: Autopilot) -> float:
    """A PARAM_VALUE's value as a number: PX4 puts an integer's bytes in the float (its INT32 parameters)."""
    if profile is Autopilot.PX4 and param_type in _INT_TYPES:
        signed = param_type in (mavlink.MAV_PARAM_TYPE_INT8, mavlink.MAV_PARAM_TYPE_INT16, mavlink.MAV_PARAM_TYPE_INT32)
        return float(struct.unpack("<i" if signed else "<I", struct.pack("<f", value))[0])
    return float(value)


@dataclass(frozen=True, slots=True)
class FenceLimits:
    """What the autopilot enforces of its fence, as the planner takes it.

    Attributes:
        zones: the uploaded zones (polygons and circles) are configured.
        margin_m: the autopilot's planners keep this far from every fence edge [m] (0 on PX4).
        home_radius_m: a circle of this radius round home bounds the flight [m] (moved in by the margin as every
            zone edge is, ``apf_companion.fence``), or None.
        ceiling_m: the highest goal above home [m] (already less the margin), or None.
        floor_m: the lowest goal above home [m] (FENCE_ALT_MIN plus the margin), or None.
        union: the inclusion zones' union is allowed (ArduPilot FENCE_OPTIONS bit 1), not their intersection.
        note: what was read, said with the fence's outcome.
    """

    zones: bool
    margin_m: float
    home_radius_m: float | None
    ceiling_m: float | None
    note: str
    union: bool = False
    floor_m: float | None = None

    @property
    def enforced(self) -> bool:
        return self.zones or any(x is not None for x in (self.home_radius_m, self.ceiling_m, self.floor_m))

    def inset_m(self, clearance_m: float) -> float:
        """How far every zone edge moves: the part of the margin that the planner's clearance C does not keep."""
        return max(self.margin_m - clearance_m, 0.0)


def fence_limits(profile: Autopilot, values: Mapping[str, float], *, switched_on: bool = False) -> FenceLimits | str:
    """The limits of the values of ``FENCE_PARAMS[profile]`` and those of ``OPTIONAL_PARAMS[profile]`` that the
    autopilot has (module docstring), or why they are unusable. ``switched_on``: ArduPilot's SYS_STATUS says its
    fence is on (GEOFENCE enabled), whatever FENCE_ENABLE says."""
    bad = [name for name in FENCE_PARAMS[profile] if not math.isfinite(values.get(name, math.nan))]
    bad += [name for name in OPTIONAL_PARAMS[profile] if name in values and not math.isfinite(values[name])]
    if bad:
        return f"{bad[0]} is {values.get(bad[0])!r}"
    if profile is Autopilot.PX4:
        return _px4_limits(values["GF_ACTION"] != 0.0, values["GF_MAX_HOR_DIST"], values["GF_MAX_VER_DIST"])
    kinds, on = int(values["FENCE_TYPE"]), values["FENCE_ENABLE"] != 0.0 or switched_on
    margin_xy, margin_z = values.get("FENCE_MARGIN_XY", 0.0), max(values["FENCE_MARGIN"], 0.0)
    margin = margin_xy if margin_xy > 0.0 else margin_z
    radius = values["FENCE_RADIUS"]
    home_radius = radius if on and kinds & _TYPE_CIRCLE and radius > 0.0 else None
    ceiling = values["FENCE_ALT_MAX"] - margin_z if on and kinds & _TYPE_ALT_MAX else None
    union = bool(int(values.get("FENCE_OPTIONS", 0.0)) & _OPTION_UNION)
    has_floor = on and kinds & _TYPE_ALT_MIN and "FENCE_ALT_MIN" in values
    floor = values["FENCE_ALT_MIN"] + margin_z if has_floor else None
    said = [f"FENCE_MARGIN{'_XY' if margin_xy > 0.0 else ''} {margin:g} m"]
    if switched_on and values["FENCE_ENABLE"] == 0.0:
        said.append("switched on (SYS_STATUS)")
    if home_radius is not None:
        said.append(f"circle of {radius:g} m round home")
    if ceiling is not None:
        said.append(f"ceiling {values['FENCE_ALT_MAX']:g} m")
    if floor is not None:
        said.append(f"floor {values['FENCE_ALT_MIN']:g} m")
    if not on and kinds & (_TYPE_CIRCLE | _TYPE_ALT_MAX | _TYPE_ALT_MIN):
        off = "circle round home, ceiling or floor" if kinds & _TYPE_ALT_MIN else "circle round home or ceiling"
        said.append(f"FENCE_ENABLE 0: no {off}")
    if not kinds & _TYPE_POLYGON:
        said.append("FENCE_TYPE without polygons: uploaded zones not used")
    if union:
        said.append("FENCE_OPTIONS union of inclusion zones")
    return FenceLimits(bool(kinds & _TYPE_POLYGON), margin, home_radius, ceiling, ", ".join(said), union, floor)


def _px4_limits(on: bool, radius: float, ceiling: float) -> FenceLimits:
    """PX4's circle round home and ceiling (0: none), used while its breach action is not None (``on``)."""
    has_circle, has_ceiling = radius > 0.0, ceiling > 0.0
    if not on and (has_circle or has_ceiling):
        off = " or ".join(name for name, has in (("circle round home", has_circle), ("ceiling", has_ceiling)) if has)
        return FenceLimits(True, 0.0, None, None, f"GF_ACTION 0 (none): no {off}")
    said = [f"circle of {radius:g} m round home"] if has_circle else []
    said += [f"ceiling {ceiling:g} m"] if has_ceiling else []
    note = ", ".join(said) or "no circle, no ceiling"
    return FenceLimits(True, 0.0, radius if has_circle else None, ceiling if has_ceiling else None, note)


class ReadStage(enum.Enum):
    """Where a parameter read is."""

    IDLE = "idle"
    RUNNING = "running"
    DONE = "done"
    FAILED = "failed"


class ParamRead:
    """Reads ``names`` and ``optional`` names by PARAM_REQUEST_READ: all asked at once, the unanswered ones again
    after ``timeout_s``. An autopilot stays silent about a name it does not have: a needed name unanswered after
    ``retries`` repeats ends the read FAILED; an optional one, after ``optional_retries``, is taken as absent."""

    def __init__(
        self,
        names: tuple[str, ...],
        timeout_s: float = 1.0,
        retries: int = 5,
        optional: tuple[str, ...] = (),
        optional_retries: int = 1,
    ) -> None:
        self.names = names
        self.optional = optional
        self.timeout_s = timeout_s
        self.retries = retries
        self.optional_retries = optional_retries
        self.stage = ReadStage.IDLE
        self.values: dict[str, float] = {}
        self.reason = ""
        self._sent_at = -math.inf
        self._tries = 0

    def start(self) -> None:
        self.stage, self.values, self.reason = ReadStage.RUNNING, {}, ""
        self._sent_at, self._tries = -math.inf, 0

    def rest(self) -> None:
        """Its end has been taken: IDLE until the next ``start`` (the values are kept)."""
        self.stage = ReadStage.IDLE

    def due(self, now_s: float) -> tuple[str, ...]:
        """The names to ask for at ``now_s``: the unanswered ones, when their answers are overdue."""
        if self.stage is not ReadStage.RUNNING or now_s - self._sent_at < self.timeout_s:
            return ()
        missing = tuple(n for n in self.names if n not in self.values)
        asking = self._tries <= self.optional_retries
        optional = tuple(n for n in self.optional if n not in self.values) if asking else ()
        if not missing and not optional:  # the optional ones unanswered: absent
            self.stage = ReadStage.DONE
            return ()
        if missing and self._tries > self.retries:
            self.stage, self.reason = ReadStage.FAILED, f"no {missing[0]} after {self.retries + 1} requests"
            return ()
        self._tries += 1
        self._sent_at = now_s
        return missing + optional

    def on_value(self, name: str, value: float) -> None:
        """A PARAM_VALUE from the autopilot (any asker's: the value is the same); other names are not ours."""
        if self.stage is ReadStage.RUNNING and (name in self.names or name in self.optional):
            self.values[name] = value
            if all(n in self.values for n in (*self.names, *self.optional)):
                self.stage = ReadStage.DONE
