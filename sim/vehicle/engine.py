"""The simulated autopilot and vehicle as pure logic on a simulated clock: no sockets, no wall time.

``VehicleEngine`` takes decoded MAVLink messages (``handle``) and advances in fixed physics steps (``step``);
everything it says goes out through an ``emit(link, msg)`` callback (``link`` None = every link). The async
``Simulator`` (sim/vehicle/simulator.py) feeds it from real sockets; tests can drive it directly.

Rules modelled (sources: ArduCopter GCS_Mavlink.cpp / mode_guided.cpp, PX4 commander, mavlink common.xml; see
/work/shared/background/anchors.md sections 3.3, 3.4, 3.7):

- ArduPilot profile: HEARTBEAT autopilot ARDUPILOTMEGA, custom_mode = ArduCopter mode number. GUIDED accepts
  SET_POSITION_TARGET_*; takeoff only with NAV_TAKEOFF (armed, GUIDED, landed); a velocity or acceleration
  target is zeroed after GUID_TIMEOUT (3 s) without an update; a position target is held indefinitely.
- PX4 profile: HEARTBEAT autopilot PX4, custom_mode = main mode << 16 | sub mode << 24. Switching to OFFBOARD
  is refused (TEMPORARILY_REJECTED) unless setpoints have streamed for >= 1 s with no gap >= 0.5 s (> 2 Hz);
  in OFFBOARD, no setpoint for COM_OF_LOSS_T (1 s) triggers the failsafe (COM_OBL_RC_ACT; without RC: Hold =
  AUTO.LOITER) and a STATUSTEXT. OFFBOARD can take off from the ground when armed and the setpoint climbs.
- type_mask (both profiles, ArduCopter's rules): position, velocity and acceleration each given for all three
  axes or ignored for all three; accepted: position, velocity, position+velocity, position+velocity+
  acceleration, velocity+acceleration, acceleration, each with yaw or yaw rate; FORCE_SET only with
  acceleration ignored. Anything else (partial axes, yaw alone, position+acceleration, unknown frame) is
  ignored and reported with a STATUSTEXT (at most one per second per reason).
- Frames: LOCAL_NED (origin), LOCAL_OFFSET_NED (position relative to the vehicle), BODY_NED and
  BODY_OFFSET_NED (position relative to the vehicle and rotated by its heading; velocity, acceleration and
  yaw relative to its heading), and the GLOBAL_* frames of SET_POSITION_TARGET_GLOBAL_INT.
"""

from __future__ import annotations

import logging
import math
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any, ClassVar

import numpy as np
from pymavlink.dialects.v20 import ardupilotmega as mavlink

from apf_companion.autopilot import (
    ACC_IGNORE,
    POS_IGNORE,
    PX4_HOLD,
    PX4_LAND,
    PX4_OFFBOARD,
    PX4_TAKEOFF,
    VEL_IGNORE,
    Autopilot,
    CopterMode,
    Px4AutoSubMode,
    Px4MainMode,
    Px4Mode,
    TypeMask,
)
from apf_companion.errors import ConfigError
from sim.vehicle.dynamics import (
    CRASH_IMPACT_M_S,
    ControlTarget,
    Limits,
    TargetKind,
    VehicleState,
    step_dynamics,
    wrap_pi,
)
from sim.vehicle.params import ParamTable
from sim.vehicle.sensor import (
    RangeSensorConfig,
    Scan,
    distance_sensor_msgs,
    obstacle_distance_3d_msgs,
    obstacle_distance_msg,
    scan_world,
)
from sim.world.model import FloatArray, World

log = logging.getLogger(__name__)

__all__ = [
    "DEFAULT_RATES_HZ",
    "EngineConfig",
    "HomeConfig",
    "SpawnConfig",
    "StatusText",
    "VehicleEngine",
    "VehicleSnapshot",
]

SYSID = 1
COMPID = 1
EARTH_RADIUS_M = 6378137.0
PX4_RTL = Px4Mode(Px4MainMode.AUTO, Px4AutoSubMode.RTL)
PX4_POSCTL = Px4Mode(Px4MainMode.POSCTL)
UNSUPPORTED_CMD_LONG_ONLY = {mavlink.MAV_CMD_DO_REPOSITION}

# Telemetry streamed by default [Hz]; SET_MESSAGE_INTERVAL changes them per link.
DEFAULT_RATES_HZ: dict[str, float] = {
    "HEARTBEAT": 1.0,
    "SYS_STATUS": 1.0,
    "LOCAL_POSITION_NED": 10.0,
    "GLOBAL_POSITION_INT": 5.0,
    "ATTITUDE": 10.0,
    "EXTENDED_SYS_STATE": 1.0,
    "HOME_POSITION": 0.5,
    "POSITION_TARGET_LOCAL_NED": 5.0,
    "VFR_HUD": 4.0,
    "SYSTEM_TIME": 0.0,
    "AUTOPILOT_VERSION": 0.0,
}
_STREAM_IDS: dict[int, str] = {getattr(mavlink, f"MAVLINK_MSG_ID_{name}"): name for name in DEFAULT_RATES_HZ}

_VALID_LOCAL_FRAMES = {
    mavlink.MAV_FRAME_LOCAL_NED,
    mavlink.MAV_FRAME_LOCAL_OFFSET_NED,
    mavlink.MAV_FRAME_BODY_NED,
    mavlink.MAV_FRAME_BODY_OFFSET_NED,
}
_BODY_FRAMES = {mavlink.MAV_FRAME_BODY_NED, mavlink.MAV_FRAME_BODY_OFFSET_NED}
_GLOBAL_FRAMES_AMSL = {mavlink.MAV_FRAME_GLOBAL, mavlink.MAV_FRAME_GLOBAL_INT}
_GLOBAL_FRAMES_REL = {
    mavlink.MAV_FRAME_GLOBAL_RELATIVE_ALT,
    mavlink.MAV_FRAME_GLOBAL_RELATIVE_ALT_INT,
    mavlink.MAV_FRAME_GLOBAL_TERRAIN_ALT,
    mavlink.MAV_FRAME_GLOBAL_TERRAIN_ALT_INT,
}

AP_MODES_OK = {
    CopterMode.STABILIZE,
    CopterMode.ALT_HOLD,
    CopterMode.LOITER,
    CopterMode.POSHOLD,
    CopterMode.BRAKE,
    CopterMode.GUIDED,
    CopterMode.LAND,
    CopterMode.RTL,
}
AP_MODES_NO_ARM = {CopterMode.LAND, CopterMode.RTL, CopterMode.BRAKE}
PX4_MODES_OK = {PX4_HOLD, PX4_TAKEOFF, PX4_LAND, PX4_RTL, PX4_OFFBOARD}

_PX4_NAMES = {
    PX4_HOLD: "AUTO.LOITER",
    PX4_TAKEOFF: "AUTO.TAKEOFF",
    PX4_LAND: "AUTO.LAND",
    PX4_RTL: "AUTO.RTL",
    PX4_OFFBOARD: "OFFBOARD",
    PX4_POSCTL: "POSCTL",
}


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

    def __post_init__(self) -> None:
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


@dataclass(slots=True)
class _Setpoint:
    kind: TargetKind
    type_mask: int
    t_rx: float
    pos: FloatArray | None
    vel: FloatArray | None
    acc: FloatArray | None
    yaw: float | None
    yaw_rate: float | None


@dataclass(slots=True)
class _Stream:
    interval_s: float  # 0 = off
    next_t: float


Emit = Callable[[int | None, Any], None]


class VehicleEngine:
    """The simulated autopilot + vehicle + range sensor on a simulated clock (``t_s`` since boot)."""

    def __init__(self, cfg: EngineConfig, *, n_links: int, emit: Emit) -> None:
        self.cfg = cfg
        self.profile = cfg.profile
        self.px4 = cfg.profile is Autopilot.PX4
        self.world = cfg.world
        self.params = ParamTable(cfg.profile, cfg.params)
        self.n_links = n_links
        self._emit = emit
        self.mav = mavlink.MAVLink(None, srcSystem=SYSID, srcComponent=COMPID)
        seeds = np.random.SeedSequence(cfg.seed).spawn(2)
        self.rng_actuation = np.random.default_rng(seeds[0])
        self.rng_sensor = np.random.default_rng(seeds[1])
        self.dt = 1.0 / cfg.physics_rate_hz
        self.t_s = 0.0
        self._steps = 0
        self.statustexts: list[StatusText] = []
        self.scan_listeners: list[Callable[[Scan], None]] = []
        self.crash_listeners: list[Callable[[], None]] = []
        self.last_scan: Scan | None = None
        # vehicle
        spawn = cfg.spawn
        start = spawn.pos_ne_m or cfg.world.start_ne_m or (0.0, 0.0)
        self.state = VehicleState()
        self.state.pos_ned_m[:2] = start
        self.state.yaw_rad = wrap_pi(math.radians(spawn.yaw_deg))
        self.armed = False
        self.crashed = False
        self.crash_info: dict[str, Any] | None = None
        self.target = ControlTarget()
        self._hold_pos: FloatArray = self.state.pos_ned_m.copy()
        self._sp: _Setpoint | None = None
        self._sp_times: list[float] = []  # recent setpoint arrival times (PX4's proof of life)
        self._takeoff_alt: float | None = None
        self._rtl_phase = 0
        self._rtl_alt = 0.0
        self._landed_since: float | None = None
        self._failsafe = False
        self._guided_timed_out = False
        self._last_warn: dict[str, float] = {}
        # streams per link
        rates = {**DEFAULT_RATES_HZ, **cfg.rates_hz}
        self._default_intervals = {name: (1.0 / r if r > 0 else 0.0) for name, r in rates.items()}
        self._streams: list[dict[str, _Stream]] = [
            {name: _Stream(iv, 0.0) for name, iv in self._default_intervals.items()} for _ in range(n_links)
        ]
        self._next_scan_t = 0.0
        self._next_noise_t = 0.0
        self._noise_vel = np.zeros(2)
        self._next_traj_t = 0.0
        self.trajectory_t_s: list[float] = []
        self.trajectory_ned_m: list[list[float]] = []
        self.path_length_m = 0.0
        self.min_clearance_m = math.inf
        self.custom_mode = self._initial_mode(spawn)
        if spawn.airborne:
            if not spawn.alt_m > 0:
                msg = f"spawn.alt_m must be > 0 for an airborne start, got {spawn.alt_m}"
                raise ConfigError(msg)
            self.state.pos_ned_m[2] = -spawn.alt_m
            self.state.on_ground = False
            self.armed = True
            self._enter_hold()
            if self.px4 and self.custom_mode == PX4_OFFBOARD.to_custom_mode():
                self._sp_times = [-1.5 + 0.1 * i for i in range(15)]  # as if a stream had been running
        self._update_clearance()
        self._record_trajectory(force=True)

    # --------------------------------------------------------------------------------------------- modes
    def _initial_mode(self, spawn: SpawnConfig) -> int:
        if spawn.mode is not None:
            mode = self.parse_mode(spawn.mode)
            if mode is None:
                msg = f"spawn.mode {spawn.mode!r} is not a mode of the {self.profile.value} profile"
                raise ConfigError(msg)
            return mode
        if self.px4:
            return PX4_HOLD.to_custom_mode()
        return int(CopterMode.GUIDED if spawn.airborne else CopterMode.STABILIZE)

    def parse_mode(self, name: str) -> int | None:
        """A mode name (``GUIDED``, ``OFFBOARD``, ``AUTO.LOITER``, ``HOLD``, ...) as this profile's custom_mode."""
        key = name.strip().upper()
        if self.px4:
            aliases = {"HOLD": PX4_HOLD, "LOITER": PX4_HOLD, "TAKEOFF": PX4_TAKEOFF, "LAND": PX4_LAND, "RTL": PX4_RTL}
            if key in aliases:
                return aliases[key].to_custom_mode()
            for mode, mname in _PX4_NAMES.items():
                if mname == key:
                    return mode.to_custom_mode()
            return None
        try:
            return int(CopterMode[key])
        except KeyError:
            return None

    def mode_name(self, custom_mode: int | None = None) -> str:
        cm = self.custom_mode if custom_mode is None else custom_mode
        if self.px4:
            mode = Px4Mode.from_custom_mode(cm)
            return _PX4_NAMES.get(mode, f"PX4({mode.main},{mode.sub})")
        try:
            return CopterMode(cm).name
        except ValueError:
            return f"MODE{cm}"

    def _behaviour(self) -> str:
        """guided | hold | land | rtl | takeoff."""
        if self.px4:
            mode = Px4Mode.from_custom_mode(self.custom_mode)
            return {
                PX4_OFFBOARD: "guided",
                PX4_LAND: "land",
                PX4_RTL: "rtl",
                PX4_TAKEOFF: "takeoff",
            }.get(mode, "hold")
        return {int(CopterMode.GUIDED): "guided", int(CopterMode.LAND): "land", int(CopterMode.RTL): "rtl"}.get(
            self.custom_mode, "hold"
        )

    def _enter_hold(self) -> None:
        self._hold_pos = self.state.pos_ned_m.copy()
        if not self.state.on_ground:
            # stop where braking at the acceleration limit ends, not where the mode changed
            v = self.state.vel_ned_m_s
            a = self._limits().accel_h_m_s2
            self._hold_pos[:2] += v[:2] * np.hypot(*v[:2]) / (2 * a)

    def _set_mode(self, custom_mode: int, reason: str = "") -> None:
        if custom_mode == self.custom_mode:
            return
        old = self.mode_name()
        self.custom_mode = custom_mode
        self._failsafe = False
        self._takeoff_alt = None
        self._rtl_phase = 0
        self._guided_timed_out = False
        if not self.px4:
            self._sp = None  # ArduCopter re-initialises GUIDED on entry: no stale target
        self._enter_hold()
        log.info("sim.mode", extra={"from": old, "to": self.mode_name(), "reason": reason})

    # --------------------------------------------------------------------------------------------- output
    def statustext(self, severity: int, text: str) -> None:
        self.statustexts.append(StatusText(self.t_s, severity, text))
        self._emit(None, self.mav.statustext_encode(severity, text.encode()[:50]))

    def _warn_once_per_s(self, key: str, severity: int, text: str) -> None:
        last = self._last_warn.get(key)
        if last is None or self.t_s - last >= 1.0:
            self._last_warn[key] = self.t_s
            self.statustext(severity, text)

    def _ack(self, link: int, msg: Any, command: int, result: int) -> None:
        self._emit(
            link,
            self.mav.command_ack_encode(
                command, result, 0, 0, target_system=msg.get_srcSystem(), target_component=msg.get_srcComponent()
            ),
        )

    @property
    def last_setpoint_t_s(self) -> float | None:
        """Simulated time of the last SET_POSITION_TARGET_* addressed to us (PX4 proof of life), or None."""
        return self._sp_times[-1] if self._sp_times else None

    @property
    def time_boot_ms(self) -> int:
        return int(self.t_s * 1000.0) & 0xFFFFFFFF

    # --------------------------------------------------------------------------------------------- input
    def handle(self, msg: Any, link: int) -> None:
        """Process one received message (from link index ``link``) at the current simulated time."""
        mtype = msg.get_type()
        handler = self._HANDLERS.get(mtype)
        if handler is not None:
            handler(self, msg, link)

    def _addressed_to_us(self, msg: Any) -> bool:
        ts = getattr(msg, "target_system", 0)
        tc = getattr(msg, "target_component", 0)
        return ts in (0, SYSID) and tc in (0, COMPID)

    def _on_command_long(self, msg: Any, link: int) -> None:
        if not self._addressed_to_us(msg):
            return
        p = (msg.param1, msg.param2, msg.param3, msg.param4, msg.param5, msg.param6, msg.param7)
        if msg.command in UNSUPPORTED_CMD_LONG_ONLY:
            self._ack(link, msg, msg.command, mavlink.MAV_RESULT_UNSUPPORTED)
            return
        self._command(msg, link, msg.command, p, frame=None)

    def _on_command_int(self, msg: Any, link: int) -> None:
        if not self._addressed_to_us(msg):
            return
        p = (msg.param1, msg.param2, msg.param3, msg.param4, float(msg.x), float(msg.y), msg.z)
        self._command(msg, link, msg.command, p, frame=msg.frame)

    def _command(self, msg: Any, link: int, cmd: int, p: tuple[float, ...], frame: int | None) -> None:
        fn = self._COMMANDS.get(cmd)
        result = mavlink.MAV_RESULT_UNSUPPORTED if fn is None else fn(self, msg, link, p, frame)
        if result is not None:
            self._ack(link, msg, cmd, result)

    def _fail(self) -> int:
        """The result real autopilots give when a command is understood but cannot be done now."""
        return int(mavlink.MAV_RESULT_TEMPORARILY_REJECTED if self.px4 else mavlink.MAV_RESULT_FAILED)

    # -- arming
    def _cmd_arm(self, msg: Any, link: int, p: tuple[float, ...], frame: int | None) -> int:
        force = round(p[1]) == 21196
        if p[0] >= 0.5:
            if self.armed:
                return int(mavlink.MAV_RESULT_ACCEPTED)
            if self.crashed:
                self.statustext(mavlink.MAV_SEVERITY_CRITICAL, "Arm: vehicle crashed")
                return self._fail()
            if not self.px4 and self.custom_mode in AP_MODES_NO_ARM and not force:
                self.statustext(mavlink.MAV_SEVERITY_CRITICAL, "Arm: Mode not armable")
                return self._fail()
            if self.px4 and self.custom_mode == PX4_OFFBOARD.to_custom_mode() and not self._px4_stream_ok():
                self.statustext(mavlink.MAV_SEVERITY_CRITICAL, "Arming denied: no offboard setpoints")
                return self._fail()
            self.armed = True
            self._landed_since = self.t_s
            self.statustext(mavlink.MAV_SEVERITY_INFO, "Arming motors" if not self.px4 else "Armed by external command")
            return int(mavlink.MAV_RESULT_ACCEPTED)
        if not self.armed:
            return int(mavlink.MAV_RESULT_ACCEPTED)
        if not self.state.on_ground and not force:
            self.statustext(mavlink.MAV_SEVERITY_CRITICAL, "Disarm refused: vehicle in the air")
            return self._fail()
        self._disarm("Disarming motors" if not self.px4 else "Disarmed by external command")
        return int(mavlink.MAV_RESULT_ACCEPTED)

    def _disarm(self, text: str) -> None:
        self.armed = False
        self._takeoff_alt = None
        self._landed_since = None
        self.statustext(mavlink.MAV_SEVERITY_INFO, text)

    # -- modes
    def _cmd_set_mode(self, msg: Any, link: int, p: tuple[float, ...], frame: int | None) -> int:
        base = round(p[0])
        if not base & mavlink.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED:
            return int(mavlink.MAV_RESULT_UNSUPPORTED if not self.px4 else mavlink.MAV_RESULT_DENIED)
        custom = Px4Mode(round(p[1]), round(p[2])).to_custom_mode() if self.px4 else round(p[1])
        return self._request_mode(custom)

    def _on_set_mode(self, msg: Any, link: int) -> None:
        if msg.target_system not in (0, SYSID):
            return
        if not msg.base_mode & mavlink.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED:
            result = int(mavlink.MAV_RESULT_UNSUPPORTED if not self.px4 else mavlink.MAV_RESULT_DENIED)
        else:
            result = self._request_mode(int(msg.custom_mode))
        # ArduPilot answers SET_MODE with a COMMAND_ACK for message id 11; PX4 turns it into DO_SET_MODE.
        command = mavlink.MAV_CMD_DO_SET_MODE if self.px4 else mavlink.MAVLINK_MSG_ID_SET_MODE
        self._ack(link, msg, command, result)

    def _request_mode(self, custom: int) -> int:
        if self.px4:
            mode = Px4Mode.from_custom_mode(custom)
            if mode.main != Px4MainMode.AUTO:
                mode = Px4Mode(mode.main, 0)
            if mode not in PX4_MODES_OK:
                self.statustext(
                    mavlink.MAV_SEVERITY_CRITICAL, f"Switching to {self.mode_name(custom)} is currently not available"
                )
                return self._fail()
            if mode == PX4_OFFBOARD and not self._px4_stream_ok():
                self.statustext(mavlink.MAV_SEVERITY_CRITICAL, "Switching to Offboard is currently not available")
                return self._fail()
            if self.crashed:
                return self._fail()
            self._set_mode(mode.to_custom_mode(), "command")
            return int(mavlink.MAV_RESULT_ACCEPTED)
        if custom not in {int(m) for m in AP_MODES_OK}:
            self.statustext(mavlink.MAV_SEVERITY_WARNING, f"Flight mode change failed {self.mode_name(custom)}")
            return self._fail()
        if self.crashed:
            return self._fail()
        self._set_mode(custom, "command")
        return int(mavlink.MAV_RESULT_ACCEPTED)

    # -- takeoff / land / rtl
    def _cmd_takeoff(self, msg: Any, link: int, p: tuple[float, ...], frame: int | None) -> int:
        if self.crashed:
            return self._fail()
        if self.px4:
            if not self.state.on_ground:
                return self._fail()
            # param7 is an AMSL altitude on PX4 (NaN = MIS_TAKEOFF_ALT above home); like PX4's Takeoff mode,
            # a target below home + MIS_TAKEOFF_ALT is raised to it, and it says so
            minimum = self.params["MIS_TAKEOFF_ALT"]
            alt = minimum if math.isnan(p[6]) else p[6] - self.cfg.home.alt_amsl_m
            if not alt >= minimum:
                if not math.isnan(p[6]):
                    self.statustext(mavlink.MAV_SEVERITY_CRITICAL, f"Using minimum takeoff altitude: {minimum:.2f} m")
                alt = minimum
            self._set_mode(PX4_TAKEOFF.to_custom_mode(), "takeoff")
            self._takeoff_alt = alt
            return int(mavlink.MAV_RESULT_ACCEPTED)
        if self.custom_mode != CopterMode.GUIDED or not self.armed or not self.state.on_ground or not p[6] > 0:
            return int(mavlink.MAV_RESULT_FAILED)
        self._takeoff_alt = float(p[6])
        self._hold_pos = self.state.pos_ned_m.copy()
        self._sp = None
        return int(mavlink.MAV_RESULT_ACCEPTED)

    def _cmd_land(self, msg: Any, link: int, p: tuple[float, ...], frame: int | None) -> int:
        if self.crashed:
            return self._fail()
        self._set_mode(PX4_LAND.to_custom_mode() if self.px4 else int(CopterMode.LAND), "land command")
        return int(mavlink.MAV_RESULT_ACCEPTED)

    def _cmd_rtl(self, msg: Any, link: int, p: tuple[float, ...], frame: int | None) -> int:
        if self.crashed:
            return self._fail()
        self._set_mode(PX4_RTL.to_custom_mode() if self.px4 else int(CopterMode.RTL), "rtl command")
        return int(mavlink.MAV_RESULT_ACCEPTED)

    def _cmd_reposition(self, msg: Any, link: int, p: tuple[float, ...], frame: int | None) -> int:
        if frame is None or frame not in _GLOBAL_FRAMES_AMSL | _GLOBAL_FRAMES_REL or self.crashed:
            return int(mavlink.MAV_RESULT_UNSUPPORTED if frame is None else self._fail())
        if self.state.on_ground:
            return self._fail()
        if self.px4:
            self._set_mode(PX4_HOLD.to_custom_mode(), "reposition")
        elif self.custom_mode != CopterMode.GUIDED:
            if not round(p[1]) & mavlink.MAV_DO_REPOSITION_FLAGS_CHANGE_MODE:
                return int(mavlink.MAV_RESULT_FAILED)
            self._set_mode(int(CopterMode.GUIDED), "reposition")
        n, e = self._latlon_to_ne(p[4] * 1e-7, p[5] * 1e-7)
        down = -(p[6] - self.cfg.home.alt_amsl_m) if frame in _GLOBAL_FRAMES_AMSL else -p[6]
        target = np.array([n, e, down])
        if self.px4:
            self._hold_pos = target
        else:
            self._sp = _Setpoint(TargetKind.POSITION, 0x0DF8, self.t_s, target, None, None, None, None)
        return int(mavlink.MAV_RESULT_ACCEPTED)

    # -- message requests
    def _cmd_set_interval(self, msg: Any, link: int, p: tuple[float, ...], frame: int | None) -> int:
        name = _STREAM_IDS.get(round(p[0]))
        if name is None:
            return int(mavlink.MAV_RESULT_FAILED)
        interval_us = p[1]
        stream = self._streams[link][name]
        if interval_us == 0:
            stream.interval_s = self._default_intervals[name]
        elif interval_us < 0:
            stream.interval_s = 0.0
        else:
            stream.interval_s = max(interval_us * 1e-6, self.dt)
        stream.next_t = self.t_s
        return int(mavlink.MAV_RESULT_ACCEPTED)

    def _cmd_get_interval(self, msg: Any, link: int, p: tuple[float, ...], frame: int | None) -> int | None:
        msg_id = round(p[0])
        name = _STREAM_IDS.get(msg_id)
        if name is None:
            interval = 0
        else:
            iv = self._streams[link][name].interval_s
            interval = round(iv * 1e6) if iv > 0 else -1
        self._ack(link, msg, msg.command, mavlink.MAV_RESULT_ACCEPTED)
        self._emit(link, self.mav.message_interval_encode(msg_id, interval))
        return None

    def _cmd_request_message(self, msg: Any, link: int, p: tuple[float, ...], frame: int | None) -> int | None:
        name = _STREAM_IDS.get(round(p[0]))
        if name is None:
            return int(mavlink.MAV_RESULT_FAILED)
        out = self._build(name)
        if out is None:
            return int(mavlink.MAV_RESULT_FAILED)
        self._ack(link, msg, msg.command, mavlink.MAV_RESULT_ACCEPTED)
        self._emit(link, out)
        return None

    def _cmd_capabilities(self, msg: Any, link: int, p: tuple[float, ...], frame: int | None) -> int | None:
        self._ack(link, msg, msg.command, mavlink.MAV_RESULT_ACCEPTED)
        self._emit(link, self._build("AUTOPILOT_VERSION"))
        return None

    def _cmd_get_home(self, msg: Any, link: int, p: tuple[float, ...], frame: int | None) -> int | None:
        self._ack(link, msg, msg.command, mavlink.MAV_RESULT_ACCEPTED)
        self._emit(link, self._build("HOME_POSITION"))
        return None

    def _cmd_change_speed(self, msg: Any, link: int, p: tuple[float, ...], frame: int | None) -> int:
        speed = p[1]
        if not speed > 0:
            return self._fail()
        if self.px4:
            err = self.params.set("MPC_XY_CRUISE", min(speed, self.params["MPC_XY_VEL_MAX"]))
        else:
            err = self.params.set("WPNAV_SPEED", speed * 100.0)
        return int(mavlink.MAV_RESULT_ACCEPTED if err is None else mavlink.MAV_RESULT_DENIED)

    # -- parameters
    def _param_value(self, name: str) -> Any:
        return self.mav.param_value_encode(
            name.encode(), self.params[name], mavlink.MAV_PARAM_TYPE_REAL32, len(self.params), self.params.index(name)
        )

    def _on_param_request_list(self, msg: Any, link: int) -> None:
        if not self._addressed_to_us(msg):
            return
        for name, _ in self.params.items():
            self._emit(link, self._param_value(name))

    def _on_param_request_read(self, msg: Any, link: int) -> None:
        if not self._addressed_to_us(msg):
            return
        name = self.params.name_at(msg.param_index) if msg.param_index >= 0 else _param_id(msg.param_id)
        if name is not None and name in self.params:
            self._emit(link, self._param_value(name))

    def _on_param_set(self, msg: Any, link: int) -> None:
        if not self._addressed_to_us(msg):
            return
        name = _param_id(msg.param_id)
        if name not in self.params:
            return  # ArduPilot and PX4 stay silent about unknown parameters
        err = self.params.set(name, float(msg.param_value))
        if err is not None:
            self.statustext(mavlink.MAV_SEVERITY_WARNING, err[:50])
        self._emit(None, self._param_value(name))

    def _on_timesync(self, msg: Any, link: int) -> None:
        # A request has tc1 == 0: answer with our clock (simulated ns since boot) and echo ts1.
        if msg.tc1 == 0:
            self._emit(link, self.mav.timesync_encode(int(self.t_s * 1e9), msg.ts1))

    def _on_mission_request_list(self, msg: Any, link: int) -> None:
        if not self._addressed_to_us(msg):
            return
        self._emit(
            link,
            self.mav.mission_count_encode(
                msg.get_srcSystem(), msg.get_srcComponent(), 0, mission_type=getattr(msg, "mission_type", 0)
            ),
        )

    # -- setpoints
    def _on_set_position_target_local_ned(self, msg: Any, link: int) -> None:
        if not self._addressed_to_us(msg):
            return
        self._setpoint_received()
        frame = msg.coordinate_frame
        if frame not in _VALID_LOCAL_FRAMES:
            self._warn_once_per_s("frame", mavlink.MAV_SEVERITY_WARNING, f"Setpoint ignored: frame {frame} unsupported")
            return
        self._apply_setpoint(msg, frame, np.array([msg.x, msg.y, msg.z], dtype=np.float64))

    def _on_set_position_target_global_int(self, msg: Any, link: int) -> None:
        if not self._addressed_to_us(msg):
            return
        self._setpoint_received()
        frame = msg.coordinate_frame
        if frame not in _GLOBAL_FRAMES_AMSL | _GLOBAL_FRAMES_REL:
            self._warn_once_per_s("frame", mavlink.MAV_SEVERITY_WARNING, f"Setpoint ignored: frame {frame} unsupported")
            return
        n, e = self._latlon_to_ne(msg.lat_int * 1e-7, msg.lon_int * 1e-7)
        down = -(msg.alt - self.cfg.home.alt_amsl_m) if frame in _GLOBAL_FRAMES_AMSL else -msg.alt
        self._apply_setpoint(msg, mavlink.MAV_FRAME_LOCAL_NED, np.array([n, e, down], dtype=np.float64))

    def _setpoint_received(self) -> None:
        self._sp_times.append(self.t_s)
        if len(self._sp_times) > 200:
            del self._sp_times[:100]

    def _apply_setpoint(self, msg: Any, frame: int, pos_in: FloatArray) -> None:
        mask = int(msg.type_mask)
        kind, reason = _classify_mask(mask)
        if kind is None:
            self._warn_once_per_s(
                f"mask{mask}", mavlink.MAV_SEVERITY_WARNING, f"Setpoint ignored: type_mask 0x{mask:04X} {reason}"
            )
            return
        if not self.px4 and (
            self.custom_mode != CopterMode.GUIDED or self._takeoff_alt is not None or self.state.on_ground
        ):
            # ArduCopter uses setpoints only in GUIDED, not on the ground or during takeoff; PX4 keeps the
            # latest for when OFFBOARD engages
            return
        yaw_now = self.state.yaw_rad
        c, s = math.cos(yaw_now), math.sin(yaw_now)
        body = frame in _BODY_FRAMES

        def rot(v: FloatArray) -> FloatArray:
            return np.array([c * v[0] - s * v[1], s * v[0] + c * v[1], v[2]]) if body else v

        pos = vel = acc = None
        if not mask & POS_IGNORE:
            pos = rot(pos_in)
            if frame != mavlink.MAV_FRAME_LOCAL_NED:
                pos = pos + self.state.pos_ned_m
        if not mask & VEL_IGNORE:
            vel = rot(np.array([msg.vx, msg.vy, msg.vz], dtype=np.float64))
        if not mask & ACC_IGNORE:
            acc = rot(np.array([msg.afx, msg.afy, msg.afz], dtype=np.float64))
        yaw = None if mask & TypeMask.YAW_IGNORE else wrap_pi(msg.yaw + (yaw_now if body else 0.0))
        yaw_rate = None if mask & TypeMask.YAW_RATE_IGNORE else float(msg.yaw_rate)
        values = [v for v in (pos, vel, acc) if v is not None]
        if not all(np.all(np.isfinite(v)) for v in values) or (yaw is not None and not math.isfinite(yaw)):
            self._warn_once_per_s("nan", mavlink.MAV_SEVERITY_WARNING, "Setpoint ignored: not finite")
            return
        self._sp = _Setpoint(kind, mask, self.t_s, pos, vel, acc, yaw, yaw_rate)
        self._guided_timed_out = False

    # --------------------------------------------------------------------------------------------- step
    def _limits(self) -> Limits:
        if self.px4:
            return Limits(
                speed_h_m_s=self.params["MPC_XY_VEL_MAX"],
                speed_up_m_s=self.params["MPC_Z_VEL_MAX_UP"],
                speed_down_m_s=self.params["MPC_Z_VEL_MAX_DN"],
                accel_h_m_s2=self.params["MPC_ACC_HOR"],
            )
        return Limits(
            speed_h_m_s=self.params["WPNAV_SPEED"] / 100.0,
            speed_up_m_s=self.params["WPNAV_SPEED_UP"] / 100.0,
            speed_down_m_s=self.params["WPNAV_SPEED_DN"] / 100.0,
            accel_h_m_s2=self.params["WPNAV_ACCEL"] / 100.0,
        )

    def _cruise(self) -> float:
        return self.params["MPC_XY_CRUISE"] if self.px4 else self.params["WPNAV_SPEED"] / 100.0

    def _px4_stream_ok(self) -> bool:
        """PX4: setpoints have arrived for >= 1 s with every gap < 0.5 s (> 2 Hz), the last < 0.5 s ago."""
        times = self._sp_times
        if not times or self.t_s - times[-1] >= 0.5:
            return False
        start = times[-1]
        for earlier in reversed(times[:-1]):
            if start - earlier >= 0.5:
                break
            start = earlier
        return self.t_s - start >= 1.0 - 1e-9

    def _choose_target(self, limits: Limits) -> tuple[ControlTarget, Limits]:
        st = self.state
        if not self.armed:
            return ControlTarget(kind=TargetKind.GROUND), limits
        behaviour = self._behaviour()
        face = not self.px4 and self.params["WP_YAW_BEHAVIOR"] > 0
        if behaviour == "land" or (behaviour == "rtl" and self._rtl_phase >= 2):
            if st.on_ground:
                return ControlTarget(kind=TargetKind.GROUND), limits
            land_speed = self.params["MPC_LAND_SPEED"] if self.px4 else self.params["LAND_SPEED"] / 100.0
            hold = self._hold_pos.copy()
            hold[2] = 1.0  # below the ground: keep descending until touchdown
            return ControlTarget(kind=TargetKind.POSITION, pos_ned_m=hold), _replace_limits(
                limits, speed_down_m_s=land_speed if st.alt_m < 10.0 else limits.speed_down_m_s
            )
        if behaviour == "rtl":
            rtl_alt = self.params["RTL_RETURN_ALT"] if self.px4 else self.params["RTL_ALT"] / 100.0
            alt = max(rtl_alt, st.alt_m)
            if self._rtl_phase == 0:
                self._rtl_alt = alt
                self._rtl_phase = 1
            goal = np.array([0.0, 0.0, -self._rtl_alt])
            if self._rtl_phase == 1 and st.alt_m < self._rtl_alt - 0.5:
                climb = st.pos_ned_m.copy()
                climb[2] = -self._rtl_alt
                return ControlTarget(kind=TargetKind.POSITION, pos_ned_m=climb), limits
            if float(np.hypot(*st.pos_ned_m[:2])) < 0.5:
                self._rtl_phase = 2
                self._hold_pos = np.array([0.0, 0.0, 0.0])
            return ControlTarget(
                kind=TargetKind.POSITION, pos_ned_m=goal, face_travel=face, speed_h_m_s=self._cruise()
            ), limits
        if behaviour == "takeoff" or (self._takeoff_alt is not None and not self.px4):
            alt = self._takeoff_alt if self._takeoff_alt is not None else self.params["MIS_TAKEOFF_ALT"]
            speed_up = self.params["MPC_TKO_SPEED"] if self.px4 else limits.speed_up_m_s
            tgt = self._hold_pos.copy()
            tgt[2] = -alt
            if st.alt_m >= alt - 0.1:
                self._takeoff_alt = None
                self._hold_pos = tgt
                if self.px4:
                    self._set_mode(PX4_HOLD.to_custom_mode(), "takeoff complete")
                    self._hold_pos = tgt
                else:
                    self._sp = _Setpoint(TargetKind.POSITION, 0x0DF8, self.t_s, tgt, None, None, None, None)
            return ControlTarget(kind=TargetKind.POSITION, pos_ned_m=tgt), _replace_limits(
                limits, speed_up_m_s=speed_up
            )
        if behaviour == "guided":
            sp = self._sp
            if sp is None:
                if st.on_ground:
                    return ControlTarget(kind=TargetKind.GROUND), limits
                return ControlTarget(kind=TargetKind.HOLD, pos_ned_m=self._hold_pos, face_travel=False), limits
            if self.px4 and st.on_ground:
                # OFFBOARD lifts off only for a setpoint that climbs
                climbing = (sp.pos is not None and sp.pos[2] < -0.3) or (sp.vel is not None and sp.vel[2] < -0.1)
                if not climbing:
                    return ControlTarget(kind=TargetKind.GROUND), limits
            expired = not self.px4 and self.t_s - sp.t_rx > self.params["GUID_TIMEOUT"]
            if not self.px4 and sp.kind in (TargetKind.VELOCITY, TargetKind.ACCELERATION) and expired:
                if not self._guided_timed_out:
                    self._guided_timed_out = True
                    log.info("sim.guided_timeout", extra={"t_s": self.t_s})
                return ControlTarget(kind=TargetKind.VELOCITY, vel_ned_m_s=np.zeros(3)), limits
            vel, acc = sp.vel, sp.acc
            if not self.px4 and sp.kind is TargetKind.POSITION and expired:
                vel = acc = None  # the feed-forward expires; the position is held
            return (
                ControlTarget(
                    kind=sp.kind,
                    pos_ned_m=sp.pos,
                    vel_ned_m_s=vel,
                    acc_ned_m_s2=acc,
                    yaw_rad=sp.yaw,
                    yaw_rate_rad_s=sp.yaw_rate,
                    face_travel=face,
                    speed_h_m_s=self._cruise() if vel is None else None,
                ),
                limits,
            )
        # hold-type modes (LOITER, BRAKE, POSHOLD, STABILIZE/ALT_HOLD without RC, PX4 Hold)
        if st.on_ground:
            return ControlTarget(kind=TargetKind.GROUND), limits
        return ControlTarget(kind=TargetKind.HOLD, pos_ned_m=self._hold_pos, speed_h_m_s=self._cruise()), limits

    def step(self) -> None:
        """Advance one physics step: rules, dynamics, collisions, sensor, telemetry."""
        self._steps += 1
        self.t_s = self._steps * self.dt
        if not self.crashed:
            self._check_failsafes()
            limits = self._limits()
            self.target, limits = self._choose_target(limits)
            prev = self.state.pos_ned_m.copy()
            was_flying = not self.state.on_ground
            impact = step_dynamics(
                self.state,
                self.target,
                limits,
                self.dt,
                armed=self.armed,
                disturbance_vel_ne_m_s=self._noise(),
            )
            d = self.state.pos_ned_m - prev
            self.path_length_m += math.sqrt(float(d[0] * d[0] + d[1] * d[1] + d[2] * d[2]))
            if impact > 0 and was_flying:
                self._touchdown(impact)
            self._update_clearance()
            self._auto_disarm()
        self._record_trajectory()
        self._sense()
        self._telemetry()

    def _noise(self) -> FloatArray | None:
        sd = self.params["SIM_POS_NOISE"]
        if sd <= 0 or self.state.on_ground or not self.armed:
            return None
        if self.t_s >= self._next_noise_t:
            period = self.params["SIM_NOISE_PER"]
            self._noise_vel = self.rng_actuation.normal(0.0, sd, 2) / period
            self._next_noise_t = self.t_s + period
        return self._noise_vel

    def _check_failsafes(self) -> None:
        if not self.px4 or self.custom_mode != PX4_OFFBOARD.to_custom_mode():
            return
        last = self._sp_times[-1] if self._sp_times else -math.inf
        if self.t_s - last <= self.params["COM_OF_LOSS_T"]:
            return
        action = round(self.params["COM_OBL_RC_ACT"])
        if action == 3:
            new, name = PX4_RTL, "Return"
        elif action in (4, 6, 7):
            new, name = PX4_LAND, "Land"
        else:
            new, name = PX4_HOLD, "Hold"
        self.statustext(mavlink.MAV_SEVERITY_CRITICAL, f"Failsafe: offboard signal lost, {name}")
        self._set_mode(new.to_custom_mode(), "offboard loss")
        self._failsafe = True

    def _touchdown(self, impact_m_s: float) -> None:
        if impact_m_s > CRASH_IMPACT_M_S:
            self._crash(f"Crash: ground impact at {impact_m_s:.1f} m/s", -1)
            return
        self._landed_since = self.t_s
        if self.armed and self._behaviour() in ("land", "rtl"):
            self._disarm("Land complete, disarmed" if not self.px4 else "Landing detected, disarmed")

    def _auto_disarm(self) -> None:
        if not self.armed or not self.state.on_ground or self._landed_since is None:
            return
        delay = self.params["COM_DISARM_PRFLT"] if self.px4 else self.params["DISARM_DELAY"]
        if delay > 0 and self.t_s - self._landed_since >= delay:
            self._disarm("Auto disarm: landed" if not self.px4 else "Disarmed: preflight timeout")

    def _update_clearance(self) -> None:
        if self.world.n_obstacles == 0:
            return
        d = self.world.surface_distances_m(self.state.pos_ned_m[:2], self.state.alt_m)
        i = int(np.argmin(d))
        clearance = float(d[i])
        self.min_clearance_m = min(self.min_clearance_m, clearance)
        if clearance < self.params["SIM_VEH_RADIUS"] and not self.crashed:
            kind = "cylinder" if i < self.world.n_circles else "wall"
            self._crash(f"Crash: hit {kind} {i} clearance {clearance:.2f} m", i)

    def _crash(self, text: str, obstacle_id: int) -> None:
        self.crashed = True
        self.armed = False
        self.state.vel_ned_m_s[:] = 0.0
        self.state.acc_ned_m_s2[:] = 0.0
        self.crash_info = {
            "t_s": self.t_s,
            "pos_ned_m": self.state.pos_ned_m.tolist(),
            "obstacle_id": obstacle_id,
            "reason": text,
        }
        self.statustext(mavlink.MAV_SEVERITY_EMERGENCY, text)
        self._record_trajectory(force=True)
        for fn in self.crash_listeners:
            fn()

    def _record_trajectory(self, *, force: bool = False) -> None:
        if force or self.t_s >= self._next_traj_t - 1e-9:
            self.trajectory_t_s.append(round(self.t_s, 6))
            self.trajectory_ned_m.append([round(float(x), 4) for x in self.state.pos_ned_m])
            self._next_traj_t = self.t_s + 1.0 / self.cfg.trajectory_rate_hz

    def _sense(self) -> None:
        rate = self.params["SIM_RNG_RATE"]
        if rate <= 0 or self.t_s < self._next_scan_t - 1e-9:
            return
        self._next_scan_t = max(self._next_scan_t + 1.0 / rate, self.t_s)
        scan = scan_world(
            self.world,
            self.cfg.sensor,
            t_s=self.t_s,
            pos_ned_m=self.state.pos_ned_m,
            yaw_rad=self.state.yaw_rad,
            min_range_m=self.params["SIM_RNG_MIN"],
            max_range_m=self.params["SIM_RNG_MAX"],
            noise_sd_m=self.params["SIM_RNG_NOISE"],
            dropout_prob=self.params["SIM_RNG_DROP"],
            rng=self.rng_sensor,
            octants="distance_sensor" in self.cfg.sensor.messages,
            points="obstacle_distance_3d" in self.cfg.sensor.messages,
        )
        self.last_scan = scan
        msgs: list[Any] = []
        kinds = self.cfg.sensor.messages
        if "obstacle_distance" in kinds:
            msgs.append(obstacle_distance_msg(self.mav, scan, self.cfg.sensor))
        if "distance_sensor" in kinds:
            msgs.extend(distance_sensor_msgs(self.mav, scan))
        if "obstacle_distance_3d" in kinds:
            msgs.extend(obstacle_distance_3d_msgs(self.mav, scan))
        links = self.cfg.sensor.links
        for m in msgs:
            if links is None:
                self._emit(None, m)
            else:
                for i in links:
                    if 0 <= i < self.n_links:
                        self._emit(i, m)
        for fn in self.scan_listeners:
            fn(scan)

    # --------------------------------------------------------------------------------------------- telemetry
    def _telemetry(self) -> None:
        cache: dict[str, Any] = {}
        for link, streams in enumerate(self._streams):
            for name, st in streams.items():
                if st.interval_s <= 0 or self.t_s < st.next_t - 1e-9:
                    continue
                st.next_t = max(st.next_t + st.interval_s, self.t_s + 0.5 * st.interval_s)
                if name not in cache:
                    cache[name] = self._build(name)
                if cache[name] is not None:
                    self._emit(link, cache[name])

    def _base_mode(self) -> int:
        base = mavlink.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED | mavlink.MAV_MODE_FLAG_STABILIZE_ENABLED
        if self._behaviour() in ("guided", "rtl", "land", "takeoff"):
            base |= mavlink.MAV_MODE_FLAG_GUIDED_ENABLED
        if self.armed:
            base |= mavlink.MAV_MODE_FLAG_SAFETY_ARMED
        return int(base)

    def _system_status(self) -> int:
        if self.crashed:
            return int(mavlink.MAV_STATE_EMERGENCY)
        if self._failsafe:
            return int(mavlink.MAV_STATE_CRITICAL)
        return int(mavlink.MAV_STATE_ACTIVE if self.armed else mavlink.MAV_STATE_STANDBY)

    def _build(self, name: str) -> Any:
        st = self.state
        t_ms = self.time_boot_ms
        if name == "HEARTBEAT":
            autopilot = mavlink.MAV_AUTOPILOT_PX4 if self.px4 else mavlink.MAV_AUTOPILOT_ARDUPILOTMEGA
            return self.mav.heartbeat_encode(
                mavlink.MAV_TYPE_QUADROTOR, autopilot, self._base_mode(), self.custom_mode, self._system_status()
            )
        if name == "SYS_STATUS":
            sensors = 0x1 | 0x2 | 0x4 | 0x8 | 0x20 | 0x8000 | 0x200000  # gyro acc mag baro gps motors ahrs
            health = sensors if not self.crashed else 0
            return self.mav.sys_status_encode(sensors, sensors, health, 150, 12600, 500, 90, 0, 0, 0, 0, 0, 0)
        if name == "LOCAL_POSITION_NED":
            p, v = st.pos_ned_m, st.vel_ned_m_s
            return self.mav.local_position_ned_encode(
                t_ms, float(p[0]), float(p[1]), float(p[2]), float(v[0]), float(v[1]), float(v[2])
            )
        if name == "GLOBAL_POSITION_INT":
            lat, lon = self._ne_to_latlon(float(st.pos_ned_m[0]), float(st.pos_ned_m[1]))
            v = st.vel_ned_m_s
            hdg = round(math.degrees(st.yaw_rad) * 100.0) % 36000
            return self.mav.global_position_int_encode(
                t_ms,
                round(lat * 1e7),
                round(lon * 1e7),
                round((self.cfg.home.alt_amsl_m + st.alt_m) * 1000.0),
                round(st.alt_m * 1000.0),
                round(v[0] * 100.0),
                round(v[1] * 100.0),
                round(v[2] * 100.0),
                hdg,
            )
        if name == "ATTITUDE":
            roll, pitch = st.attitude_rad()
            return self.mav.attitude_encode(t_ms, roll, pitch, st.yaw_rad, 0.0, 0.0, st.yaw_rate_rad_s)
        if name == "EXTENDED_SYS_STATE":
            if st.on_ground:
                landed = mavlink.MAV_LANDED_STATE_ON_GROUND
            elif self._behaviour() == "land" or (self._behaviour() == "rtl" and self._rtl_phase >= 2):
                landed = mavlink.MAV_LANDED_STATE_LANDING
            elif self._takeoff_alt is not None:
                landed = mavlink.MAV_LANDED_STATE_TAKEOFF
            else:
                landed = mavlink.MAV_LANDED_STATE_IN_AIR
            return self.mav.extended_sys_state_encode(mavlink.MAV_VTOL_STATE_UNDEFINED, landed)
        if name == "HOME_POSITION":
            h = self.cfg.home
            return self.mav.home_position_encode(
                round(h.lat_deg * 1e7),
                round(h.lon_deg * 1e7),
                round(h.alt_amsl_m * 1000.0),
                0.0,
                0.0,
                0.0,
                [1.0, 0.0, 0.0, 0.0],
                0.0,
                0.0,
                0.0,
                time_usec=int(self.t_s * 1e6),
            )
        if name == "POSITION_TARGET_LOCAL_NED":
            sp = self._sp
            if sp is None or self._behaviour() != "guided":
                return None
            z3 = (0.0, 0.0, 0.0)
            pos = sp.pos if sp.pos is not None else z3
            vel = sp.vel if sp.vel is not None else z3
            acc = sp.acc if sp.acc is not None else z3
            return self.mav.position_target_local_ned_encode(
                t_ms,
                mavlink.MAV_FRAME_LOCAL_NED,
                sp.type_mask,
                *(float(x) for x in pos),
                *(float(x) for x in vel),
                *(float(x) for x in acc),
                float(sp.yaw or 0.0),
                float(sp.yaw_rate or 0.0),
            )
        if name == "VFR_HUD":
            v = st.vel_ned_m_s
            gs = float(np.hypot(v[0], v[1]))
            hdg = round(math.degrees(st.yaw_rad)) % 360
            return self.mav.vfr_hud_encode(gs, gs, hdg, 50 if self.armed else 0, st.alt_m, -float(v[2]))
        if name == "SYSTEM_TIME":
            return self.mav.system_time_encode(0, t_ms)
        if name == "AUTOPILOT_VERSION":
            caps = (
                mavlink.MAV_PROTOCOL_CAPABILITY_MAVLINK2
                | mavlink.MAV_PROTOCOL_CAPABILITY_SET_POSITION_TARGET_LOCAL_NED
                | mavlink.MAV_PROTOCOL_CAPABILITY_SET_POSITION_TARGET_GLOBAL_INT
                | mavlink.MAV_PROTOCOL_CAPABILITY_COMMAND_INT
                | mavlink.MAV_PROTOCOL_CAPABILITY_PARAM_FLOAT
            )
            version = (1 << 24 | 15 << 16 | 0 << 8 | 255) if self.px4 else (4 << 24 | 5 << 16 | 0 << 8 | 255)
            return self.mav.autopilot_version_encode(
                caps, version, 0, 0, 0, [0] * 8, [0] * 8, [0] * 8, 0, 0, 0x53494D0000000001
            )
        return None

    # --------------------------------------------------------------------------------------------- geo
    def _latlon_to_ne(self, lat_deg: float, lon_deg: float) -> tuple[float, float]:
        h = self.cfg.home
        n = math.radians(lat_deg - h.lat_deg) * EARTH_RADIUS_M
        e = math.radians(lon_deg - h.lon_deg) * EARTH_RADIUS_M * math.cos(math.radians(h.lat_deg))
        return n, e

    def _ne_to_latlon(self, n: float, e: float) -> tuple[float, float]:
        h = self.cfg.home
        lat = h.lat_deg + math.degrees(n / EARTH_RADIUS_M)
        lon = h.lon_deg + math.degrees(e / (EARTH_RADIUS_M * math.cos(math.radians(h.lat_deg))))
        return lat, lon

    # --------------------------------------------------------------------------------------------- views
    def snapshot(self) -> VehicleSnapshot:
        st = self.state
        return VehicleSnapshot(
            t_s=self.t_s,
            pos_ned_m=st.pos_ned_m.copy(),
            vel_ned_m_s=st.vel_ned_m_s.copy(),
            yaw_rad=st.yaw_rad,
            mode=self.mode_name(),
            custom_mode=self.custom_mode,
            armed=self.armed,
            crashed=self.crashed,
            on_ground=st.on_ground,
            min_clearance_m=self.min_clearance_m,
        )

    def result(self) -> dict[str, Any]:
        """The flight result (JSON-ready); the format is documented in README, Simulator."""
        return {
            "schema": "apf.sim_result/1",
            "profile": self.profile.value,
            "seed": self.cfg.seed,
            "collided": self.crash_info is not None and self.crash_info["obstacle_id"] >= 0,
            "crashed": self.crashed,
            "crashed_at": self.crash_info,
            "sim_time_s": round(self.t_s, 6),
            "path_length_m": self.path_length_m,
            "min_clearance_m": self.min_clearance_m if math.isfinite(self.min_clearance_m) else None,
            "vehicle_radius_m": self.params["SIM_VEH_RADIUS"],
            "final_pos_ned_m": self.state.pos_ned_m.tolist(),
            "final_mode": self.mode_name(),
            "armed": self.armed,
            "on_ground": self.state.on_ground,
            "trajectory_t_s": list(self.trajectory_t_s),
            "trajectory_ned_m": [list(p) for p in self.trajectory_ned_m],
            "statustexts": [[s.t_s, s.severity, s.text] for s in self.statustexts],
            "params": dict(self.params.items()),
            "world": self.world.describe(),
        }

    _HANDLERS: ClassVar[dict[str, Callable[[VehicleEngine, Any, int], None]]] = {}
    _COMMANDS: ClassVar[dict[int, Callable[[VehicleEngine, Any, int, tuple[float, ...], int | None], int | None]]] = {}


def _replace_limits(limits: Limits, **changes: float) -> Limits:
    return Limits(**{**{k: getattr(limits, k) for k in Limits.__slots__}, **changes})


def _param_id(raw: Any) -> str:
    if isinstance(raw, bytes):
        raw = raw.decode("ascii", "replace")
    return str(raw).rstrip("\x00")


def _classify_mask(mask: int) -> tuple[TargetKind | None, str]:
    """ArduCopter's accepted type_mask combinations -> the kind of target, or None with the reason."""
    groups = []
    for bits, name in ((POS_IGNORE, "position"), (VEL_IGNORE, "velocity"), (ACC_IGNORE, "acceleration")):
        got = mask & bits
        if got not in (0, bits):
            return None, f"{name} must be given for all 3 axes"
        groups.append(got == 0)
    use_pos, use_vel, use_acc = groups
    if mask & TypeMask.FORCE_SET and use_acc:
        return None, "force setpoints unsupported"
    if use_pos:
        if use_acc and not use_vel:
            return None, "position+acceleration unsupported"
        return TargetKind.POSITION, ""
    if use_vel:
        return TargetKind.VELOCITY, ""
    if use_acc:
        return TargetKind.ACCELERATION, ""
    return None, "no position, velocity or acceleration"


VehicleEngine._HANDLERS = {
    "COMMAND_LONG": VehicleEngine._on_command_long,
    "COMMAND_INT": VehicleEngine._on_command_int,
    "SET_MODE": VehicleEngine._on_set_mode,
    "SET_POSITION_TARGET_LOCAL_NED": VehicleEngine._on_set_position_target_local_ned,
    "SET_POSITION_TARGET_GLOBAL_INT": VehicleEngine._on_set_position_target_global_int,
    "PARAM_REQUEST_LIST": VehicleEngine._on_param_request_list,
    "PARAM_REQUEST_READ": VehicleEngine._on_param_request_read,
    "PARAM_SET": VehicleEngine._on_param_set,
    "MISSION_REQUEST_LIST": VehicleEngine._on_mission_request_list,
    "TIMESYNC": VehicleEngine._on_timesync,
}
VehicleEngine._COMMANDS = {
    mavlink.MAV_CMD_COMPONENT_ARM_DISARM: VehicleEngine._cmd_arm,
    mavlink.MAV_CMD_DO_SET_MODE: VehicleEngine._cmd_set_mode,
    mavlink.MAV_CMD_NAV_TAKEOFF: VehicleEngine._cmd_takeoff,
    mavlink.MAV_CMD_NAV_LAND: VehicleEngine._cmd_land,
    mavlink.MAV_CMD_NAV_RETURN_TO_LAUNCH: VehicleEngine._cmd_rtl,
    mavlink.MAV_CMD_DO_REPOSITION: VehicleEngine._cmd_reposition,
    mavlink.MAV_CMD_DO_CHANGE_SPEED: VehicleEngine._cmd_change_speed,
    mavlink.MAV_CMD_SET_MESSAGE_INTERVAL: VehicleEngine._cmd_set_interval,
    mavlink.MAV_CMD_GET_MESSAGE_INTERVAL: VehicleEngine._cmd_get_interval,
    mavlink.MAV_CMD_REQUEST_MESSAGE: VehicleEngine._cmd_request_message,
    mavlink.MAV_CMD_REQUEST_AUTOPILOT_CAPABILITIES: VehicleEngine._cmd_capabilities,
    mavlink.MAV_CMD_GET_HOME_POSITION: VehicleEngine._cmd_get_home,
}
