"""What the pure engine is configured with, and the records it hands out (status texts, snapshots)."""

from __future__ import annotations

import enum
from dataclasses import dataclass, field

from apf_companion.autopilot import Autopilot
from apf_companion.errors import ConfigError
from apf_companion.planning import FlyingArea, KeepOuts
from sim.vehicle.sensor import RangeSensorConfig
from sim.world.model import FloatArray, World

__all__ = [
    "AUTO_DYNAMICS",
    "DEFAULT_RATES_HZ",
    "Dynamics",
    "EngineConfig",
    "HomeConfig",
    "SpawnConfig",
    "StatusText",
    "VehicleSnapshot",
]

# Telemetry streamed by default [Hz], by message name; SET_MESSAGE_INTERVAL changes them per link. A rate of 0 is
# a message sent only when requested (SET_MESSAGE_INTERVAL, REQUEST_MESSAGE).
DEFAULT_RATES_HZ: dict[str, float] = {
    "HEARTBEAT": 1.0,
    "SYS_STATUS": 1.0,
    "LOCAL_POSITION_NED": 10.0,
    "GLOBAL_POSITION_INT": 5.0,
    "ATTITUDE": 10.0,
    "EXTENDED_SYS_STATE": 1.0,
    "HOME_POSITION": 0.5,
    "POSITION_TARGET_LOCAL_NED": 5.0,
    "POSITION_TARGET_GLOBAL_INT": 0.0,  # ArduPilot profile, guided position-only targets: when requested
    "VFR_HUD": 4.0,
    "SYSTEM_TIME": 0.0,
    "AUTOPILOT_VERSION": 0.0,
    "GPS_RAW_INT": 0.0,
    "DISTANCE_SENSOR": 0.0,
    "EKF_STATUS_REPORT": 0.0,
    "MISSION_CURRENT": 1.0,  # PX4 sends it on every link from boot; ArduPilot when asked
    "ODOMETRY": 0.0,  # PX4's onboard mode streams it at 30 Hz (mavlink_main.cpp); here when asked
}


class Dynamics(enum.Enum):
    """How the vehicle responds to its position controller's targets."""

    SIMPLE = "simple"  # square-root position loop, velocity loop, limited acceleration (no jerk limit, no lag)
    ARDUCOPTER = "arducopter"  # AC_PosControl's jerk-limited shaping, tracking loops, attitude lag, spool-up


AUTO_DYNAMICS = "auto"  # SimConfig / CLI: the profile's own vehicle (arducopter for ardupilot, simple for px4)


@dataclass(frozen=True, slots=True, kw_only=True)
class HomeConfig:
    """Home = EKF origin = world origin (0, 0, 0) local NED, at this geodetic position."""

    lat_deg: float = -35.363262
    lon_deg: float = 149.165237
    alt_amsl_m: float = 584.0


@dataclass(frozen=True, slots=True, kw_only=True)
class SpawnConfig:
    """Where and how the vehicle starts.

    Attributes:
        pos_ne_m: start (north, east) [m]; None = the world's start, else (0, 0).
        yaw_deg: heading [deg], 0 = north, clockwise.
        airborne: start flying (armed, hovering at ``alt_m``) instead of landed and disarmed.
        alt_m: hover height when airborne [m].
        mode: starting mode name (``GUIDED``, ``LOITER``, ``OFFBOARD``, ``AUTO.LOITER``, ...). None = the
            profile's default: ArduPilot STABILIZE on the ground, GUIDED in the air; PX4 AUTO.LOITER (Hold).
    """

    pos_ne_m: tuple[float, float] | None = None
    yaw_deg: float = 0.0
    airborne: bool = False
    alt_m: float = 5.0
    mode: str | None = None


@dataclass(frozen=True, slots=True, kw_only=True)
class EngineConfig:
    """Everything the pure engine needs (the async Simulator adds links, speed-up, recording)."""

    profile: Autopilot = Autopilot.ARDUPILOT
    world: World = field(default_factory=World.empty)
    seed: int = 0
    params: dict[str, float] = field(default_factory=dict)
    sensor: RangeSensorConfig = field(default_factory=RangeSensorConfig)
    spawn: SpawnConfig = field(default_factory=SpawnConfig)
    home: HomeConfig = field(default_factory=HomeConfig)
    physics_rate_hz: float = 100.0
    rates_hz: dict[str, float] = field(default_factory=dict)
    trajectory_rate_hz: float = 10.0
    dynamics: Dynamics = Dynamics.SIMPLE
    fast_start: bool = False  # the EKF origin is set at boot (skips the profile's SIM_EKF_ORIGIN_S wait)
    fence: FlyingArea | None = None  # served as the fence's one inclusion polygon (sim.vehicle.fence); None: none
    fence_keepouts: KeepOuts = ()  # served as the fence's exclusion polygons
    unasked_streams: bool | None = None  # stream DEFAULT_RATES_HZ unasked; None = the profile's habit

    def __post_init__(self) -> None:
        if self.dynamics is Dynamics.ARDUCOPTER and self.profile is not Autopilot.ARDUPILOT:
            msg = "dynamics 'arducopter' needs the ardupilot profile"
            raise ConfigError(msg)
        if not 10.0 <= self.physics_rate_hz <= 2000.0:
            msg = f"physics_rate_hz must be in [10, 2000], got {self.physics_rate_hz}"
            raise ConfigError(msg)
        if not 0.1 <= self.trajectory_rate_hz <= self.physics_rate_hz:
            msg = f"trajectory_rate_hz must be in [0.1, physics_rate_hz], got {self.trajectory_rate_hz}"
            raise ConfigError(msg)
        for name, rate in self.rates_hz.items():
            if name not in DEFAULT_RATES_HZ or not 0.0 <= rate <= 1000.0:
                msg = f"rates_hz: {name!r} must be one of {sorted(DEFAULT_RATES_HZ)} with a rate in [0, 1000]"
                raise ConfigError(msg)
        if self.seed < 0:
            msg = f"seed must be >= 0, got {self.seed}"
            raise ConfigError(msg)


@dataclass(frozen=True, slots=True)
class StatusText:
    t_s: float
    severity: int
    text: str


@dataclass(frozen=True, slots=True, kw_only=True, eq=False)
class VehicleSnapshot:
    """The vehicle as it is now (a copy; safe to keep)."""

    t_s: float
    pos_ned_m: FloatArray
    vel_ned_m_s: FloatArray
    yaw_rad: float
    mode: str
    custom_mode: int
    armed: bool
    crashed: bool
    on_ground: bool
    min_clearance_m: float
