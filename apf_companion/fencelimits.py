"""The autopilot's fence parameters: whether it enforces its fence, how far its own planners keep from it, its
circle round home and its ceiling. Read over PARAM_REQUEST_READ (``ParamRead``, a state machine on an injected
clock) and turned into ``FenceLimits`` (``fence_limits``), which ``apf_companion.fence`` applies to the zones.

ArduPilot (``libraries/AC_Fence/AC_Fence.cpp``):
- ``FENCE_ENABLE`` is the master switch: while it is 0, ``get_enabled_fences`` gives no fence, and ArduPilot's own
  path planners plan without one (``libraries/AC_Avoidance/AP_OABendyRuler.cpp``, ``calc_margin_from_*``). So does
  bapf-nav. The parameters are read again at every fence read (``planner.fence_poll_s``), so a fence switched on
  in flight (a switch, or auto-enable after takeoff) is in service within one poll.
- ``FENCE_TYPE`` (bitmask): 1 maximum altitude, 2 a circle centred on home, 4 the uploaded inclusion/exclusion
  polygons and circles, 8 minimum altitude (not used: the planner does not descend).
- ``FENCE_RADIUS`` [m]: the circle round home. ``FENCE_ALT_MAX`` [m above home]: the ceiling.
- ``FENCE_MARGIN`` [m]: how far the autopilot's planners keep from every fence edge (the path's distance to a
  polygon minus the margin, ``AP_OABendyRuler.cpp``; the circle's radius minus the margin; the ceiling minus the
  margin, ``get_safe_alt_max``). bapf-nav keeps the same: the zones' edges move in by the part of the margin
  that its own clearance C does not already keep.
PX4 (``src/modules/navigator/geofence_params.c``):
- ``GF_ACTION`` 0 (None): a breach does nothing, so the fence is not enforced.
- ``GF_MAX_HOR_DIST`` [m from home] and ``GF_MAX_VER_DIST`` [m above home]: 0 = off.
- PX4 has no margin parameter: the zones keep bapf-nav's clearance C only.

Values come as floats; ArduPilot casts integer parameters to float, PX4 sends an INT32's bytes in the float
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

__all__ = ["FENCE_PARAMS", "FenceLimits", "ParamRead", "ReadStage", "fence_limits", "param_float"]

#: The parameters read, per autopilot.
FENCE_PARAMS: dict[Autopilot, tuple[str, ...]] = {
    Autopilot.ARDUPILOT: ("FENCE_ENABLE", "FENCE_TYPE", "FENCE_RADIUS", "FENCE_ALT_MAX", "FENCE_MARGIN"),
    Autopilot.PX4: ("GF_ACTION", "GF_MAX_HOR_DIST", "GF_MAX_VER_DIST"),
}

# AC_Fence.h: the FENCE_TYPE bits
_TYPE_ALT_MAX = 1
_TYPE_CIRCLE = 2
_TYPE_POLYGON = 4

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
        zones: the uploaded zones (polygons and circles) are enforced.
        margin_m: the autopilot's planners keep this far from every fence edge [m] (0 on PX4).
        home_radius_m: a circle of this radius round home is enforced [m] (moved in by the margin as every zone
            edge is, ``apf_companion.fence``), or None.
        ceiling_m: the highest goal above home [m] (already less the margin), or None.
        note: what was read, said with the fence's outcome.
    """

    zones: bool
    margin_m: float
    home_radius_m: float | None
    ceiling_m: float | None
    note: str

    @property
    def enforced(self) -> bool:
        return self.zones or self.home_radius_m is not None or self.ceiling_m is not None


def fence_limits(profile: Autopilot, values: Mapping[str, float]) -> FenceLimits | str:
    """The limits of the values of ``FENCE_PARAMS[profile]`` (module docstring), or why they are unusable."""
    bad = [name for name in FENCE_PARAMS[profile] if not math.isfinite(values.get(name, math.nan))]
    if bad:
        return f"{bad[0]} is {values.get(bad[0])!r}"
    if profile is Autopilot.PX4:
        if values["GF_ACTION"] == 0:
            return FenceLimits(False, 0.0, None, None, "GF_ACTION 0: PX4 does not enforce its fence")
        hor, ver = values["GF_MAX_HOR_DIST"], values["GF_MAX_VER_DIST"]
        return FenceLimits(True, 0.0, hor if hor > 0.0 else None, ver if ver > 0.0 else None, _px4_note(hor, ver))
    if values["FENCE_ENABLE"] == 0:
        return FenceLimits(False, 0.0, None, None, "FENCE_ENABLE 0: ArduPilot does not enforce its fence")
    kinds, margin = int(values["FENCE_TYPE"]), max(values["FENCE_MARGIN"], 0.0)
    radius: float | None = values["FENCE_RADIUS"] if kinds & _TYPE_CIRCLE and values["FENCE_RADIUS"] > 0.0 else None
    ceiling: float | None = values["FENCE_ALT_MAX"] - margin if kinds & _TYPE_ALT_MAX else None
    said = [f"FENCE_MARGIN {margin:g} m"]
    if radius is not None:
        said.append(f"circle of {values['FENCE_RADIUS']:g} m round home")
    if ceiling is not None:
        said.append(f"ceiling {values['FENCE_ALT_MAX']:g} m")
    if not kinds & _TYPE_POLYGON:
        said.append("FENCE_TYPE without polygons: uploaded zones not enforced")
    return FenceLimits(bool(kinds & _TYPE_POLYGON), margin, radius, ceiling, ", ".join(said))


def _px4_note(radius: float, ceiling: float) -> str:
    said = [f"circle of {radius:g} m round home"] if radius > 0.0 else []
    said += [f"ceiling {ceiling:g} m"] if ceiling > 0.0 else []
    return ", ".join(said) or "no circle, no ceiling"


class ReadStage(enum.Enum):
    """Where a parameter read is."""

    IDLE = "idle"
    RUNNING = "running"
    DONE = "done"
    FAILED = "failed"


class ParamRead:
    """Reads ``names`` by PARAM_REQUEST_READ: all asked at once, the unanswered ones again after ``timeout_s``, at
    most ``retries`` times; an autopilot stays silent about a name it does not have, so that ends in FAILED."""

    def __init__(self, names: tuple[str, ...], timeout_s: float = 1.0, retries: int = 5) -> None:
        self.names = names
        self.timeout_s = timeout_s
        self.retries = retries
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
        if self._tries > self.retries:
            self.stage, self.reason = ReadStage.FAILED, f"no {missing[0]} after {self.retries + 1} requests"
            return ()
        self._tries += 1
        self._sent_at = now_s
        return missing

    def on_value(self, name: str, value: float) -> None:
        """A PARAM_VALUE from the autopilot (any asker's: the value is the same); other names are not ours."""
        if self.stage is ReadStage.RUNNING and name in self.names:
            self.values[name] = value
            if len(self.values) == len(self.names):
                self.stage = ReadStage.DONE
