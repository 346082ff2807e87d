"""Local NED <-> geodetic around home (flat earth: the worlds are tens of metres across), and MAVLink frames."""

from __future__ import annotations

import math

from pymavlink.dialects.v20 import ardupilotmega as mavlink

from sim.vehicle.config import HomeConfig

__all__ = [
    "BODY_FRAMES",
    "GLOBAL_FRAMES",
    "GLOBAL_FRAMES_AMSL",
    "GLOBAL_FRAMES_REL",
    "LOCAL_FRAMES",
    "latlon_to_ne",
    "ne_to_latlon",
]

EARTH_RADIUS_M = 6378137.0

LOCAL_FRAMES = frozenset(
    {
        mavlink.MAV_FRAME_LOCAL_NED,
        mavlink.MAV_FRAME_LOCAL_OFFSET_NED,
        mavlink.MAV_FRAME_BODY_NED,
        mavlink.MAV_FRAME_BODY_OFFSET_NED,
    }
)
BODY_FRAMES = frozenset({mavlink.MAV_FRAME_BODY_NED, mavlink.MAV_FRAME_BODY_OFFSET_NED})
GLOBAL_FRAMES_AMSL = frozenset({mavlink.MAV_FRAME_GLOBAL, mavlink.MAV_FRAME_GLOBAL_INT})
GLOBAL_FRAMES_REL = frozenset(
    {
        mavlink.MAV_FRAME_GLOBAL_RELATIVE_ALT,
        mavlink.MAV_FRAME_GLOBAL_RELATIVE_ALT_INT,
        mavlink.MAV_FRAME_GLOBAL_TERRAIN_ALT,
        mavlink.MAV_FRAME_GLOBAL_TERRAIN_ALT_INT,
    }
)
GLOBAL_FRAMES = GLOBAL_FRAMES_AMSL | GLOBAL_FRAMES_REL


def latlon_to_ne(home: HomeConfig, lat_deg: float, lon_deg: float) -> tuple[float, float]:
    """Geodetic -> (north, east) from home [m]."""
    n = math.radians(lat_deg - home.lat_deg) * EARTH_RADIUS_M
    e = math.radians(lon_deg - home.lon_deg) * EARTH_RADIUS_M * math.cos(math.radians(home.lat_deg))
    return n, e


def ne_to_latlon(home: HomeConfig, n: float, e: float) -> tuple[float, float]:
    """(north, east) from home [m] -> geodetic [deg]."""
    lat = home.lat_deg + math.degrees(n / EARTH_RADIUS_M)
    lon = home.lon_deg + math.degrees(e / (EARTH_RADIUS_M * math.cos(math.radians(home.lat_deg))))
    return lat, lon


def down_from_alt(home: HomeConfig, frame: int, alt_m: float) -> float:
    """A global frame's altitude as local down [m]: AMSL frames relative to home's altitude, the others as is."""
    return -(alt_m - home.alt_amsl_m) if frame in GLOBAL_FRAMES_AMSL else -alt_m
