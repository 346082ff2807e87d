"""The simulated autopilot and vehicle as pure logic on a simulated clock: no sockets, no wall time.

``VehicleEngine`` takes decoded MAVLink messages (``handle``) and advances in fixed physics steps (``step``);
everything it says goes out through an ``emit(link, msg)`` callback (``link`` None = every link). The async
``Simulator`` (sim/vehicle/simulator.py) feeds it from real sockets; tests can drive it directly.

The engine owns the vehicle (state, armed, mode and the mode's phase) and wires the parts, each in its own module
(docs/simulator.md has the map):

- ``profiles``: ArduCopter and PX4 rules (modes, command results, setpoint acceptance), one class each;
- ``gcs`` / ``commands`` / ``param_protocol``: incoming messages, MAV_CMDs and PARAM_*, one handler each;
- ``guided``: the external setpoint; ``flight_modes``: what each mode asks of the position controller;
- ``dynamics``: the point-mass vehicle; ``telemetry``: one builder per message and the per-link scheduler;
- ``ranging``: the range sensor; ``recorder``: trajectory, path length, clearance.
"""

from __future__ import annotations

import logging
import math
from collections.abc import Callable
from typing import Any

import numpy as np
from pymavlink.dialects.v20 import ardupilotmega as mavlink

from apf_companion.autopilot import Autopilot
from apf_companion.errors import ConfigError
from apf_companion.outbox import statustext_chunks
from sim.vehicle.config import (
    DEFAULT_RATES_HZ,
    Dynamics,
    EngineConfig,
    HomeConfig,
    SpawnConfig,
    StatusText,
    VehicleSnapshot,
)
from sim.vehicle.dynamics import (
    CRASH_IMPACT_M_S,
    Controller,
    ControlTarget,
    Limits,
    VehicleState,
    step_dynamics,
    wrap_pi,
)
from sim.vehicle.ekfreset import EstimatorFrame
from sim.vehicle.fence import FenceStore
from sim.vehicle.fenceswitch import FenceSwitch
from sim.vehicle.flight_modes import choose_target
from sim.vehicle.gcs import COMPID, SYSID, handle_message
from sim.vehicle.guided import GuidedState
from sim.vehicle.params import ParamTable
from sim.vehicle.poscontrol import ArduCopterPosControl
from sim.vehicle.profiles import PROFILES, AutopilotProfile, Behaviour
from sim.vehicle.proximity import Proximity
from sim.vehicle.ranging import RangeSensorDriver
from sim.vehicle.reboot import BootPhase, BootState, reboot_engine
from sim.vehicle.recorder import FlightRecorder, flight_result
from sim.vehicle.sensor import Scan
from sim.vehicle.startup import EkfStartup
from sim.vehicle.telemetry import TelemetryScheduler
from sim.world.model import FloatArray

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

Emit = Callable[[int | None, Any], None]
WARN_INTERVAL_S = 1.0  # a repeated warning (same reason) goes out at most this often


class VehicleEngine:
    """The simulated autopilot + vehicle + range sensor on a simulated clock (``t_s`` since start; ``boot_s`` since
    the last reboot, the autopilot's own clock)."""

    def __init__(self, cfg: EngineConfig, *, n_links: int, emit: Emit) -> None:
        self.cfg = cfg
        self.profile = cfg.profile
        self.profile_rules: AutopilotProfile = PROFILES[cfg.profile]
        self.world = cfg.world
        self.params = ParamTable(cfg.profile, cfg.params)
        self.controller: Controller | None = (
            ArduCopterPosControl(self.params) if cfg.dynamics is Dynamics.ARDUCOPTER else None
        )
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
        self._statustext_id = 0  # id of the last chunked STATUSTEXT
        self.scan_listeners: list[Callable[[Scan], None]] = []
        self.crash_listeners: list[Callable[[], None]] = []
        self.last_scan: Scan | None = None
        self._last_warn: dict[str, float] = {}
        unasked = self.profile_rules.unasked_streams if cfg.unasked_streams is None else cfg.unasked_streams
        self.telemetry = TelemetryScheduler(n_links, cfg.rates_hz, min_interval_s=self.dt, unasked=unasked)
        self.telemetry.boot_stream_rates(dict(self.params.items()))  # SRn_* (ArduPilot profile)
        # A flying vehicle already has its origin; fast_start skips the wait at every boot (tests).
        self.startup = EkfStartup(skip=cfg.fast_start or cfg.spawn.airborne)
        self.ranging = RangeSensorDriver()
        self.recorder = FlightRecorder(cfg.trajectory_rate_hz)
        self.guided = GuidedState()
        self.boot = BootState()
        self.own_id_drops = 0  # messages from our own sysid/compid, dropped (ArduPilot profile)
        #: The fence held, served and uploaded over the mission protocol (sim.vehicle.fence).
        self.fence = FenceStore.of_zones(cfg.fence, cfg.fence_keepouts, cfg.home, FenceSwitch.at_boot(self.params))
        self.proximity = Proximity.at_boot(self.params)
        #: The estimator's local frame against the truth: moved by ``estimator_position_reset`` (PX4 profile).
        self.estimator = EstimatorFrame()
        self._next_noise_t = 0.0
        self._noise_vel = np.zeros(2)
        self._spawn(cfg.spawn)
        self._update_clearance()
        self.recorder.record(self.t_s, self.state.pos_ned_m, force=True)

    def _spawn(self, spawn: SpawnConfig) -> None:
        start = spawn.pos_ne_m or self.cfg.world.start_ne_m or (0.0, 0.0)
        self.state = VehicleState()
        self.state.pos_ned_m[:2] = start
        self.state.yaw_rad = wrap_pi(math.radians(spawn.yaw_deg))
        self.armed = False
        self.crashed = False
        self.crash_info: dict[str, Any] | None = None
        self.target = ControlTarget()
        self.hold_pos_ned_m: FloatArray = self.state.pos_ned_m.copy()
        self.takeoff_alt_m: float | None = None  # a takeoff is climbing to this altitude above home [m]
        self.takeoff_t_s = self.armed_t_s = -math.inf  # when the takeoff was commanded, when the vehicle armed
        self.rtl_phase = 0  # 0 not started, 1 climb and return, 2 land
        self.rtl_alt_m = 0.0
        self.landed_since_s: float | None = None
        self.failsafe = False
        # PX4: the failsafe mode is the offboard-loss fallback; the user's intended mode is still OFFBOARD
        self.offboard_fallback = False
        self.custom_mode = self._initial_mode(spawn)
        if spawn.airborne:
            if not spawn.alt_m > 0:
                msg = f"spawn.alt_m must be > 0 for an airborne start, got {spawn.alt_m}"
                raise ConfigError(msg)
            self.state.pos_ned_m[2] = -spawn.alt_m
            self.state.on_ground = False
            self.armed = True
            self._enter_hold()
            self.profile_rules.spawn_in_air(self)

    # --------------------------------------------------------------------------------------------- modes
    def _initial_mode(self, spawn: SpawnConfig) -> int:
        if spawn.mode is None:
            return self.profile_rules.initial_mode(spawn.airborne)
        mode = self.parse_mode(spawn.mode)
        if mode is None:
            msg = f"spawn.mode {spawn.mode!r} is not a mode of the {self.profile.value} profile"
            raise ConfigError(msg)
        return mode

    def parse_mode(self, name: str) -> int | None:
        """A mode name (``GUIDED``, ``OFFBOARD``, ``AUTO.LOITER``, ``HOLD``, ...) as this profile's custom_mode."""
        return self.profile_rules.parse_mode(name.strip().upper())

    def mode_name(self, custom_mode: int | None = None) -> str:
        return self.profile_rules.mode_name(self.custom_mode if custom_mode is None else custom_mode)

    def behaviour(self) -> Behaviour:
        """What the current mode makes the vehicle do."""
        return self.profile_rules.behaviour(self.custom_mode)

    def _enter_hold(self) -> None:
        self.hold_pos_ned_m = self.state.pos_ned_m.copy()
        if not self.state.on_ground:
            # stop where braking at the acceleration limit ends, not where the mode changed
            v = self.state.vel_ned_m_s
            a = self.limits().accel_h_m_s2
            self.hold_pos_ned_m[:2] += v[:2] * np.hypot(*v[:2]) / (2 * a)

    def set_mode(self, custom_mode: int, reason: str = "") -> None:
        """Enter a mode (no checks: the profile's ``request_mode`` decides whether a request may)."""
        if custom_mode == self.custom_mode:
            return
        old = self.mode_name()
        self.custom_mode = custom_mode
        self.failsafe = False
        self.offboard_fallback = False
        self.takeoff_alt_m = None
        self.rtl_phase = 0
        self.guided.timed_out = False
        self.guided.fixed_yaw_rad = None
        if not self.profile_rules.keeps_setpoint_on_mode_change:
            self.guided.sp = None
        self._enter_hold()
        log.info("sim.mode", extra={"from": old, "to": self.mode_name(), "reason": reason})

    def disarm(self, text: str) -> None:
        self.armed = False
        self.takeoff_alt_m = None
        self.landed_since_s = None
        self.statustext(mavlink.MAV_SEVERITY_INFO, text)

    def limits(self) -> Limits:
        return self.profile_rules.limits(self.params)

    # --------------------------------------------------------------------------------------------- output
    def emit(self, link: int | None, msg: Any) -> None:
        """Send ``msg`` on link ``link`` (None = every link)."""
        self._emit(link, msg)

    def statustext(self, severity: int, text: str) -> None:
        """STATUSTEXT on every link; a long text in MAVLink 2 chunks (id / chunk_seq), as the companion sends."""
        self.statustexts.append(StatusText(self.t_s, severity, text))
        for chunk_id, seq, part in statustext_chunks(text, self._statustext_id):
            self._statustext_id = chunk_id or self._statustext_id
            self._emit(None, self.mav.statustext_encode(severity, part, chunk_id, seq))

    def warn_once_per_s(self, key: str, severity: int, text: str) -> None:
        last = self._last_warn.get(key)
        if last is None or self.t_s - last >= WARN_INTERVAL_S:
            self._last_warn[key] = self.t_s
            self.statustext(severity, text)

    def ack(self, link: int, msg: Any, command: int, result: int) -> None:
        """COMMAND_ACK to the sender of ``msg``."""
        ack = self.mav.command_ack_encode(
            command, result, 0, 0, target_system=msg.get_srcSystem(), target_component=msg.get_srcComponent()
        )
        self._emit(link, ack)

    @property
    def last_setpoint_t_s(self) -> float | None:
        """Simulated time of the last SET_POSITION_TARGET_* addressed to us (PX4 proof of life), or None."""
        return self.guided.last_t_s

    @property
    def boot_s(self) -> float:
        """Simulated seconds since the last (re)boot: the autopilot's own clock (``time_boot_ms``)."""
        return self.t_s - self.boot.boot_t_s

    @property
    def time_boot_ms(self) -> int:
        return int(self.boot_s * 1000.0) & 0xFFFFFFFF

    def reboot(self) -> None:
        """MAV_CMD_PREFLIGHT_REBOOT_SHUTDOWN was accepted (and ACKed): restart the autopilot (sim/vehicle/reboot.py)."""
        reboot_engine(self)

    # --------------------------------------------------------------------------------------------- input
    def handle(self, msg: Any, link: int) -> None:
        """Process one received message (from link index ``link``) at the current simulated time."""
        if self.boot.phase(self.t_s) is BootPhase.RUNNING:  # a rebooting autopilot reads nothing
            handle_message(self, msg, link)

    def estimator_position_reset(self, delta_ne_m: tuple[float, float]) -> None:
        """PX4 EKF2 resets its horizontal position by ``delta_ne_m`` [m] (sim.vehicle.ekfreset): the reported local
        position jumps, ODOMETRY's reset counter moves on, the vehicle stays where it is. PX4 profile only."""
        if self.profile is not Autopilot.PX4:
            msg = "estimator_position_reset models PX4's EKF2 (the PX4 profile)"
            raise ValueError(msg)
        self.estimator.reset_position(delta_ne_m)

    # --------------------------------------------------------------------------------------------- step
    def step(self) -> None:
        """Advance one physics step: rules, dynamics, collisions, sensor, telemetry."""
        self._steps += 1
        self.t_s = self._steps * self.dt
        self.startup.tick(self)
        if not self.crashed:
            self.profile_rules.check_failsafes(self)
            self.target, limits = choose_target(self, self.limits())
            prev = self.state.pos_ned_m.copy()
            was_flying = not self.state.on_ground
            impact = step_dynamics(
                self.state,
                self.target,
                limits,
                self.dt,
                armed=self.armed,
                disturbance_vel_ne_m_s=self._noise(),
                controller=self.controller,
            )
            self.recorder.moved(prev, self.state.pos_ned_m)
            if impact > 0 and was_flying:
                self._touchdown(impact)
            self._update_clearance()
            self._auto_disarm()
        self.recorder.record(self.t_s, self.state.pos_ned_m)
        phase = self.boot.phase(self.t_s)
        if phase is BootPhase.RUNNING:
            self.ranging.tick(self)
            self.telemetry.tick(self, self._emit)
        elif phase is BootPhase.BOOTING:
            self.boot.tick_booting(self)

    def _noise(self) -> FloatArray | None:
        sd = self.params["SIM_POS_NOISE"]
        if sd <= 0 or self.state.on_ground or not self.armed:
            return None
        if self.t_s >= self._next_noise_t:
            period = self.params["SIM_NOISE_PER"]
            self._noise_vel = self.rng_actuation.normal(0.0, sd, 2) / period
            self._next_noise_t = self.t_s + period
        return self._noise_vel

    def _touchdown(self, impact_m_s: float) -> None:
        if impact_m_s > CRASH_IMPACT_M_S:
            self._crash(f"Crash: ground impact at {impact_m_s:.1f} m/s", -1)
            return
        self.landed_since_s = self.t_s
        if self.armed and self.behaviour() in (Behaviour.LAND, Behaviour.RTL):
            self.disarm(self.profile_rules.texts.land_complete)

    def _auto_disarm(self) -> None:
        if not self.armed or not self.state.on_ground or self.landed_since_s is None:
            return
        if self.profile_rules.disarm_timer_held(self):
            self.landed_since_s = self.t_s
            return
        delay = self.profile_rules.disarm_delay_s(self.params)
        if delay > 0 and self.t_s - self.landed_since_s >= delay:
            self.disarm(self.profile_rules.texts.auto_disarm)

    def _update_clearance(self) -> None:
        if self.world.n_obstacles == 0:
            return
        d = self.world.surface_distances_m(self.state.pos_ned_m[:2], self.state.alt_m)
        i = int(np.argmin(d))
        clearance = float(d[i])
        self.recorder.clearance(clearance)
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
        self.recorder.record(self.t_s, self.state.pos_ned_m, force=True)
        for fn in self.crash_listeners:
            fn()

    # --------------------------------------------------------------------------------------------- views
    @property
    def trajectory_t_s(self) -> list[float]:
        return self.recorder.trajectory_t_s

    @property
    def trajectory_ned_m(self) -> list[list[float]]:
        return self.recorder.trajectory_ned_m

    @property
    def path_length_m(self) -> float:
        return self.recorder.path_length_m

    @property
    def min_clearance_m(self) -> float:
        return self.recorder.min_clearance_m

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
        """The flight result (JSON-ready); the format is documented in docs/simulator.md."""
        return flight_result(self)
