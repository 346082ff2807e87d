"""The companion service: MAVLink (and zenoh) in, planner cycle, setpoints and status out.

``CompanionService`` wires the pure ``Navigator`` to the links. One ``asyncio.TaskGroup`` owns every task:

- ``_rx``: reads the autopilot link. Messages are accepted only from the configured autopilot
  (sysid/compid); the one exception is COMMAND_INT / COMMAND_LONG addressed to our component from a configured
  ground-station sysid (DO_REPOSITION). Everything else is counted (``foreign_messages``) and dropped.
- ``_cycle_loop``: runs a planning cycle when a new pose arrives (at most ``rate_hz``, so sensor-to-setpoint
  latency is the compute time, not a timer phase), and on a timer one period after the last cycle otherwise (so a
  frozen pose is noticed within one cycle).
- ``_heartbeat_loop``: HEARTBEAT at 1 Hz as MAV_TYPE_ONBOARD_CONTROLLER with the vehicle's sysid, our component
  id and a system_status that reflects health; NAMED_VALUE_FLOAT and the zenoh status at their rates.
- ``_takeover_loop``: switches the autopilot to GUIDED (ArduPilot) / OFFBOARD (PX4, after >= 1 s of streamed
  setpoints), confirms the mode from HEARTBEAT.custom_mode, and arms / takes off when the config asks.
- ``_zenoh_loop``: sensor scans and goal commands from zenoh (when enabled).

Clock: ``ServiceClock`` is monotonic and scaled by ``cycle.time_scale`` (vehicle seconds per wall second), so a
simulated vehicle running N times faster than real time keeps every limit's meaning in vehicle seconds.
"""

from __future__ import annotations

import asyncio
import collections
import contextlib
import dataclasses
import enum
import json
import logging
import math
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from apf_companion.autopilot import (
    PX4_OFFBOARD,
    Autopilot,
    CopterMode,
    Px4MainMode,
    Px4Mode,
)
from apf_companion.config import ServiceConfig
from apf_companion.errors import ApfCompanionError, ConfigError, LinkError, ProtocolError
from apf_companion.goal import GlobalReference, RepositionError, Route, load_route, local_goal_from_reposition
from apf_companion.links import MavlinkLink
from apf_companion.navigator import CycleOutput, Navigator, State
from apf_companion.perception import (
    ObstacleMemory,
    Pose,
    PoseHistory,
    RangeScan,
    decode_goal_json,
    decode_laserscan_cdr,
    decode_scan_json,
    points_from_obstacle_distance_3d,
    scan_from_distance_sensor,
    scan_from_obstacle_distance,
    scan_to_points_ned,
)
from apf_companion.planning import PlannerParams, get_planner
from apf_companion.setpoint import SetpointKind, encode_setpoint
from apf_companion.status import (
    NVF_GOAL_DISTANCE,
    NVF_NEAREST_OBSTACLE,
    encode_status_json,
    severity_for,
    statustext_for,
    system_status_for,
)

__all__ = ["CompanionService", "ServiceClock", "ServiceResult", "build_navigator", "build_planner", "initial_route"]

log = logging.getLogger(__name__)

# MAVLink numbers (common.xml) used here.
MAV_TYPE_ONBOARD_CONTROLLER = 18
SCAN_DEFER_S = 0.25  # a scan newer than the newest pose waits this long at most for the next pose [s]
SCAN_DEFER_MAX = 8  # and at most this many scans wait
MAV_AUTOPILOT_INVALID = 8
MAV_CMD_DO_SET_MODE = 176
MAV_CMD_COMPONENT_ARM_DISARM = 400
MAV_CMD_NAV_TAKEOFF = 22
MAV_CMD_SET_MESSAGE_INTERVAL = 511
MAV_CMD_DO_REPOSITION = 192
MAV_MODE_FLAG_CUSTOM_MODE_ENABLED = 1
MAV_MODE_FLAG_SAFETY_ARMED = 128
MAV_RESULT_ACCEPTED = 0
MAV_RESULT_UNSUPPORTED = 3
MAV_RESULT_COMMAND_INT_ONLY = 7
MSG_ID_ATTITUDE = 30
MSG_ID_LOCAL_POSITION_NED = 32
MSG_ID_GLOBAL_POSITION_INT = 33

LATENCY_WINDOW = 4096  # samples kept for the p50/p99 of the loop latency
COMMAND_RETRY_S = 1.0  # resend an unconfirmed mode/arm command after this long (vehicle seconds)
TAKEOFF_REACHED_FRACTION = 0.9  # takeoff counts as done at this fraction of the target height


class ServiceClock:
    """Monotonic service time in vehicle seconds: wall seconds since creation times ``time_scale``."""

    def __init__(self, time_scale: float = 1.0) -> None:
        self.time_scale = time_scale
        self._t0 = time.monotonic()

    def now(self) -> float:
        return (time.monotonic() - self._t0) * self.time_scale

    def to_wall(self, dt_s: float) -> float:
        """A duration in vehicle seconds as wall seconds."""
        return max(0.0, dt_s) / self.time_scale

    async def sleep(self, dt_s: float) -> None:
        await asyncio.sleep(self.to_wall(dt_s))


@dataclass(slots=True)
class ServiceCounters:
    """Everything counted at the edges (bad input is counted, never fatal)."""

    foreign_messages: int = 0  # not from the autopilot and not a command for us from a GCS
    poses: int = 0
    bad_poses: int = 0  # NaN / non-finite LOCAL_POSITION_NED or ATTITUDE
    stale_poses: int = 0  # time_boot_ms not newer than the last one (frozen or reordered)
    scans: int = 0
    bad_scans: int = 0  # ProtocolError from a decoder (malformed message / payload)
    invalid_sectors: int = 0  # readings classified invalid (below min, zero, out of range)
    unknown_sectors: int = 0
    scans_without_pose: int = 0
    scans_deferred_too_long: int = 0  # placed with the newest pose: more than SCAN_DEFER_MAX scans waited
    goals: int = 0
    bad_goals: int = 0
    commands_for_us: int = 0
    setpoints_sent: int = 0
    statustexts_sent: int = 0
    mode_requests: int = 0


@dataclass(frozen=True, slots=True, kw_only=True)
class ServiceResult:
    """How a run ended (``apf-companion run --result-json``).

    Attributes:
        outcome: "arrived", "stuck", "timeout", "link_lost", "stopped" or "error".
        state: The navigator state at the end.
        steps: Planner steps taken.
        flight_time_s: Vehicle seconds from the first navigation setpoint to the end (0 if none).
        latency_ms_p50, latency_ms_p99: Sensor-to-setpoint latency over the run [ms].
        counters: Service and navigator counters.
        error: Message of the error that ended the run, if any.
    """

    outcome: str
    state: str
    steps: int
    flight_time_s: float
    latency_ms_p50: float | None
    latency_ms_p99: float | None
    counters: dict[str, int] = field(default_factory=dict)
    error: str | None = None

    def to_json(self) -> str:
        return json.dumps(dataclasses.asdict(self), indent=2, allow_nan=False)


def build_navigator(config: ServiceConfig, planner: Any, memory: ObstacleMemory, *, now_s: float) -> Navigator:
    """The decision core for ``planner`` (``build_planner``): its step, and its rho_l as the clearance to keep
    (the bacteria-point guard of CR-BAPF / CR-BAPF*; the slow-down near obstacles for every planner)."""
    rho_l_m = float(planner.params.rho_l_m)
    return Navigator(
        config=config,
        planner=planner,
        memory=memory,
        rng=np.random.default_rng(config.planner.seed),
        now_s=now_s,
        step_m=float(planner.params.step_m),
        target_guard_m=rho_l_m if config.planner.name.startswith("cr-") else 0.0,
        clearance_m=rho_l_m,
    )


def build_planner(config: ServiceConfig) -> Any:
    """The configured planner: preset, then ``[planner.params]`` overrides, then ``dim``.

    Raises:
        ConfigError: unknown planner parameter or a value the planner refuses.
    """
    pc = config.planner
    if pc.preset == "paper":
        params = PlannerParams.paper()
    elif pc.preset == "reference":
        params = PlannerParams.reference()
    else:
        params = PlannerParams()
    current = {f.name: getattr(params, f.name) for f in dataclasses.fields(params)}
    overrides: dict[str, Any] = {}
    for key, raw in pc.params.items():
        value: Any = raw
        if key not in current or key == "dim":
            allowed = ", ".join(sorted(k for k in current if k != "dim"))
            msg = f"unknown planner parameter planner.params.{key} (allowed: {allowed}; dim is planner.dim)"
            raise ConfigError(msg)
        old = current[key]
        if isinstance(old, enum.Enum):
            try:
                value = type(old)(value)
            except ValueError as err:
                allowed = ", ".join(repr(m.value) for m in type(old))
                msg = f"planner.params.{key} must be one of {allowed}, got {value!r}"
                raise ConfigError(msg) from err
        elif isinstance(old, float) and isinstance(value, int) and not isinstance(value, bool):
            value = float(value)
        overrides[key] = value
    try:
        params = dataclasses.replace(params, **overrides, dim=pc.dim)
    except ConfigError as err:
        msg = f"planner.params: {err}"
        raise ConfigError(msg) from err
    return get_planner(pc.name, params)


def initial_route(config: ServiceConfig) -> Route | None:
    """The goal from the config's ``[goal]`` (a point or a route file), if any."""
    g = config.goal
    if g.route:
        return load_route(config.resolve(g.route), source="config:route")
    if g.north_m is not None and g.east_m is not None:
        return Route.point(g.north_m, g.east_m, g.down_m, source="config")
    return None


class _LatencyWindow:
    def __init__(self) -> None:
        self._buf: collections.deque[float] = collections.deque(maxlen=LATENCY_WINDOW)
        self.all: list[float] = []  # whole run, for the result (bounded by run length * rate)

    def add(self, ms: float) -> None:
        self._buf.append(ms)
        if len(self.all) < 1_000_000:
            self.all.append(ms)

    def summary(self) -> dict[str, float] | None:
        if not self._buf:
            return None
        arr = np.fromiter(self._buf, dtype=np.float64)
        p50, p99 = np.percentile(arr, [50.0, 99.0])
        return {"p50": float(p50), "p99": float(p99), "last": float(arr[-1])}


class CompanionService:
    """The running service. Create with ``await CompanionService.open(config)``, then ``await run()``.

    Args:
        config: Validated configuration.
        route: Goal to fly once the autopilot is heard (overrides ``[goal]``); None = the config's goal.
        clock: Service clock (tests may pass one); default ``ServiceClock(config.cycle.time_scale)``.
        result_path: Where ``run`` writes the ``ServiceResult`` JSON when it ends.
    """

    def __init__(
        self,
        config: ServiceConfig,
        *,
        route: Route | None = None,
        clock: ServiceClock | None = None,
        result_path: Path | None = None,
    ) -> None:
        self.config = config
        self.clock = clock or ServiceClock(config.cycle.time_scale)
        self.planner = build_planner(config)
        self.memory = ObstacleMemory(
            expiry_s=config.sensors.memory_expiry_s,
            merge_radius_m=max(config.sensors.merge_radius_m, 1e-3),
            max_points=config.sensors.max_points,
        )
        self.history = PoseHistory(200)
        self._deferred_scans: collections.deque[RangeScan] = collections.deque()
        self.navigator = build_navigator(config, self.planner, self.memory, now_s=self.clock.now())
        self.counters = ServiceCounters()
        self.latency = _LatencyWindow()
        self.result_path = result_path
        self.link: MavlinkLink | None = None
        self.zenoh: Any = None
        self._route_at_start = route if route is not None else initial_route(config)
        self._stop = asyncio.Event()
        self._new_pose = asyncio.Event()
        self._trigger_rx_wall: float | None = None  # wall time the triggering pose was read
        self._yaw_rad: float | None = None
        self._last_pose_boot_ms: int | None = None
        self._boot_offset_s: float | None = None  # service time - autopilot boot time (latest pose)
        self._global_ref: GlobalReference | None = None
        self._ap_custom_mode: int | None = None
        self._ap_base_mode = 0
        self._ap_heard = False
        self._prestream_since: float | None = None
        self._last_prestream: float | None = None
        self._first_nav_s: float | None = None
        self._end_s: float | None = None
        self._outcome: str | None = None
        self._reason = "starting"
        self._streams_requested = False
        self._start_s = self.clock.now()

    # ---------------------------------------------------------------------------------------------- lifecycle
    @classmethod
    async def open(
        cls,
        config: ServiceConfig,
        *,
        route: Route | None = None,
        clock: ServiceClock | None = None,
        result_path: Path | None = None,
    ) -> CompanionService:
        """Build the service and open its links (MAVLink, and zenoh when enabled).

        Raises:
            ConfigError: planner parameters or the route file are invalid.
            LinkError: a link cannot be opened.
        """
        svc = cls(config, route=route, clock=clock, result_path=result_path)
        tlog = config.resolve(config.link.tlog) if config.link.tlog else None
        svc.link = await MavlinkLink.open(
            config.link.connect,
            source_system=config.link.autopilot_sysid,
            source_component=config.link.component_id,
            tlog_path=tlog,
        )
        if config.zenoh.enabled:
            try:
                svc.zenoh = await _open_zenoh(config)
            except BaseException:
                await svc.link.aclose()
                raise
        return svc

    async def aclose(self) -> None:
        """Close the links (safe to call twice)."""
        if self.link is not None:
            await self.link.aclose()
        if self.zenoh is not None:
            zl, self.zenoh = self.zenoh, None
            await zl.aclose()

    def stop(self) -> None:
        """Ask ``run`` to end (it returns with outcome "stopped" unless the flight already ended)."""
        self._stop.set()

    async def run(self) -> ServiceResult:
        """Run until ``stop()``, or until the flight ends when ``exit_when_done``. Closes the links at the end."""
        error: str | None = None
        try:
            async with asyncio.TaskGroup() as tg:
                tasks = [
                    tg.create_task(self._rx()),
                    tg.create_task(self._cycle_loop()),
                    tg.create_task(self._heartbeat_loop()),
                    tg.create_task(self._takeover_loop()),
                ]
                if self.zenoh is not None:
                    tasks.append(tg.create_task(self._zenoh_loop()))
                await self._stop.wait()
                for task in tasks:
                    task.cancel()
        except* ApfCompanionError as eg:
            error = "; ".join(str(e) for e in eg.exceptions)
            log.error("service.error", extra={"error": error})
            self._outcome = "error"
        finally:
            await self.aclose()
        result = self.result(error=error)
        if self.result_path is not None:
            self.result_path.write_text(result.to_json() + "\n", encoding="utf-8")
        return result

    def result(self, *, error: str | None = None) -> ServiceResult:
        now = self.clock.now()
        end = self._end_s if self._end_s is not None else now
        flight = 0.0 if self._first_nav_s is None else max(0.0, end - self._first_nav_s)
        lat = np.asarray(self.latency.all, dtype=np.float64)
        p50 = float(np.percentile(lat, 50)) if lat.size else None
        p99 = float(np.percentile(lat, 99)) if lat.size else None
        counters = dataclasses.asdict(self.counters) | {f"nav_{k}": v for k, v in self.navigator.counts().items()}
        if self.link is not None:
            counters |= {f"link_{k}": v for k, v in dataclasses.asdict(self.link.stats).items()}
        return ServiceResult(
            outcome=self._outcome or "stopped",
            state=self.navigator.state.value,
            steps=self.navigator.counters.planner_steps,
            flight_time_s=flight,
            latency_ms_p50=p50,
            latency_ms_p99=p99,
            counters=counters,
            error=error,
        )

    # ---------------------------------------------------------------------------------------------- sending
    @property
    def _silent(self) -> bool:
        return self.config.dry_run or self.link is None

    def _send(self, msg: Any) -> None:
        if not self._silent:
            assert self.link is not None
            self.link.send(msg)

    def _boot_ms(self) -> int:
        return int((self.clock.now() - self._start_s) * 1000.0) & 0xFFFFFFFF

    def _command_long(self, command: int, *params: float) -> None:
        assert self.link is not None
        p = [*params, *([0.0] * (7 - len(params)))]
        self._send(
            self.link.mav.command_long_encode(
                self.config.link.autopilot_sysid, self.config.link.autopilot_compid, command, 0, *p
            )
        )

    def _statustext(self, severity: int, text: str) -> None:
        if not self.config.status.statustext or self._silent:
            return
        assert self.link is not None
        self._send(self.link.mav.statustext_encode(severity, text.encode("ascii", "replace")[:50]))
        self.counters.statustexts_sent += 1

    def _ack(self, command: int, result: int, target_system: int, target_component: int) -> None:
        assert self.link is not None
        self._send(self.link.mav.command_ack_encode(command, result, 0, 0, target_system, target_component))

    # ---------------------------------------------------------------------------------------------- receive
    async def _rx(self) -> None:
        assert self.link is not None
        link = self.link
        ap = (self.config.link.autopilot_sysid, self.config.link.autopilot_compid)
        async for msg in link.messages():
            src = (msg.get_srcSystem(), msg.get_srcComponent())
            try:
                if src == ap:
                    self._on_autopilot(msg)
                    if self._new_pose.is_set():
                        await asyncio.sleep(0)  # let the cycle run before more input is processed
                elif msg.get_type() in ("COMMAND_INT", "COMMAND_LONG") and self._for_us(msg):
                    self._on_command(msg)
                else:
                    self.counters.foreign_messages += 1
            except ApfCompanionError as err:
                # Bad input is counted where it is classified; anything else here is logged and survived.
                log.warning("rx.rejected", extra={"type": msg.get_type(), "error": str(err)})

    def _for_us(self, msg: Any) -> bool:
        lc = self.config.link
        return bool(
            msg.get_srcSystem() in lc.gcs_sysids
            and msg.target_system == lc.autopilot_sysid
            and msg.target_component == lc.component_id
        )

    def _on_autopilot(self, msg: Any) -> None:
        kind = msg.get_type()
        now = self.clock.now()
        if kind == "HEARTBEAT":
            self._on_heartbeat(msg, now)
        elif kind == "LOCAL_POSITION_NED":
            self._on_local_position(msg, now)
        elif kind == "ATTITUDE":
            yaw = float(msg.yaw)
            if math.isfinite(yaw):
                self._yaw_rad = yaw
            else:
                self.counters.bad_poses += 1
        elif kind == "GLOBAL_POSITION_INT":
            self._on_global_position(msg)
        elif kind in ("OBSTACLE_DISTANCE", "DISTANCE_SENSOR", "OBSTACLE_DISTANCE_3D") and (self.config.sensors.mavlink):
            self._on_mavlink_ranges(msg, now)

    def _mode_ok(self, custom_mode: int) -> bool:
        if self.config.autopilot.profile is Autopilot.ARDUPILOT:
            return custom_mode == CopterMode.GUIDED
        return Px4Mode.from_custom_mode(custom_mode).main == Px4MainMode.OFFBOARD

    def _on_heartbeat(self, msg: Any, now: float) -> None:
        if msg.type in (MAV_TYPE_ONBOARD_CONTROLLER, 6):  # 6 = MAV_TYPE_GCS: not a vehicle heartbeat
            return
        first = not self._ap_heard or not self.navigator.link_alive(now)
        self._ap_heard = True
        self._ap_custom_mode = int(msg.custom_mode)
        self._ap_base_mode = int(msg.base_mode)
        mode_ok = self.config.dry_run or self._mode_ok(self._ap_custom_mode)
        self.navigator.autopilot_heartbeat(now, mode_ok=mode_ok)
        if first:
            self._request_streams()
            if self._route_at_start is not None:
                route, self._route_at_start = self._route_at_start, None
                self._set_route(route, now)

    def _request_streams(self) -> None:
        assert self.link is not None
        interval_us = 1e6 / self.config.link.telemetry_rate_hz
        for msg_id in (MSG_ID_LOCAL_POSITION_NED, MSG_ID_ATTITUDE):
            self._command_long(MAV_CMD_SET_MESSAGE_INTERVAL, float(msg_id), interval_us)
        self._command_long(MAV_CMD_SET_MESSAGE_INTERVAL, float(MSG_ID_GLOBAL_POSITION_INT), 200_000.0)

    def _on_local_position(self, msg: Any, now: float) -> None:
        self.counters.poses += 1
        boot_ms = int(msg.time_boot_ms)
        if self._last_pose_boot_ms is not None and boot_ms <= self._last_pose_boot_ms:
            # Frozen or reordered: it must not look fresh. (A reboot restarts near 0: accept a large jump back.)
            if self._last_pose_boot_ms - boot_ms < 10_000:
                self.counters.stale_poses += 1
                return
            self.history.clear()
        if self._yaw_rad is None:
            return  # no ATTITUDE yet: body-frame ranges could not be placed
        try:
            pose = Pose(t_s=now, pos_ned_m=np.array((msg.x, msg.y, msg.z), dtype=np.float64), yaw_rad=self._yaw_rad)
        except ConfigError:
            self.counters.bad_poses += 1
            return
        self._last_pose_boot_ms = boot_ms
        self._boot_offset_s = now - boot_ms / 1000.0
        self.history.add(pose)
        if self._deferred_scans:
            self._place_deferred_scans()  # before the cycle this pose triggers
        if self.navigator.update_pose(pose):
            self._trigger_rx_wall = time.perf_counter()
            self._new_pose.set()

    def _on_global_position(self, msg: Any) -> None:
        pose = self.navigator.pose
        if pose is None:
            return
        lat, lon = msg.lat * 1e-7, msg.lon * 1e-7
        alt, rel = msg.alt * 1e-3, msg.relative_alt * 1e-3
        if not all(math.isfinite(v) for v in (lat, lon, alt, rel)) or (msg.lat == 0 and msg.lon == 0):
            return
        p = pose.pos_ned_m
        self._global_ref = GlobalReference(
            lat_deg=lat, lon_deg=lon, alt_amsl_m=alt, alt_rel_m=rel, pos_ned_m=(p[0], p[1], p[2])
        )

    def _scan_time(self, boot_ms: int | None, now: float) -> float:
        """Service time of a measurement stamped with autopilot boot time (receive time if unknown)."""
        if boot_ms is None or self._boot_offset_s is None:
            return now
        t = boot_ms / 1000.0 + self._boot_offset_s
        return t if now - 5.0 < t <= now else now  # implausible stamps (other clock base): receive time

    def _on_mavlink_ranges(self, msg: Any, now: float) -> None:
        kind = msg.get_type()
        try:
            if kind == "OBSTACLE_DISTANCE_3D":
                t = self._scan_time(int(msg.time_boot_ms), now)
                pose = self.history.at(t)
                if pose is None:
                    self.counters.scans_without_pose += 1
                    return
                points = points_from_obstacle_distance_3d(msg, pose)
                self.counters.scans += 1
                self._accept_points(points, t)
                return
            if kind == "OBSTACLE_DISTANCE":
                usec = int(msg.time_usec)
                boot_ms = usec // 1000 if usec < 10**15 else None  # UNIX-epoch stamps: use receive time
                scan = scan_from_obstacle_distance(msg, t_s=self._scan_time(boot_ms, now))
            else:
                scan = scan_from_distance_sensor(msg, t_s=self._scan_time(int(msg.time_boot_ms), now))
        except ProtocolError as err:
            self.counters.bad_scans += 1
            log.debug("ranges.bad", extra={"type": kind, "error": str(err)})
            return
        self._accept_scan(scan)

    def _accept_scan(self, scan: RangeScan) -> None:
        """Place a valid scan with the pose at its measurement time and remember its obstacle points.

        A scan measured after the newest pose waits for the next pose (at most ``SCAN_DEFER_S``), so that it is
        placed with the pose interpolated at its time rather than the previous one: at 20 Hz telemetry and
        1 m/s that is up to 5 cm of obstacle position (measured: the remembered points near the vehicle were
        4-5 cm off (median) with the previous pose, 1.4-2.4 cm interpolated, in the sweep's graze flights).
        """
        self.counters.scans += 1
        self.counters.invalid_sectors += scan.counts.invalid
        self.counters.unknown_sectors += scan.counts.unknown
        self._deferred_scans.append(scan)
        self._place_deferred_scans()

    def _place_deferred_scans(self) -> None:
        """Place the waiting scans, oldest first, up to the first one still newer than the newest pose."""
        latest = self.history.latest()
        while self._deferred_scans:
            scan = self._deferred_scans[0]
            if latest is not None and 0.0 < scan.t_s - latest.t_s <= SCAN_DEFER_S:
                if len(self._deferred_scans) <= SCAN_DEFER_MAX:
                    return
                self.counters.scans_deferred_too_long += 1
            self._deferred_scans.popleft()
            self._place_scan(scan)

    def _place_scan(self, scan: RangeScan) -> None:
        pose = self.history.at(scan.t_s)
        if pose is None:
            self.counters.scans_without_pose += 1
            return
        if scan.counts.valid + scan.counts.free == 0:
            return  # nothing usable: no news about the surroundings, ranges stay as fresh as they were
        points = scan_to_points_ned(scan, pose)
        if points.shape[0]:
            rel = points[:, :2] - pose.pos_ned_m[:2]
            limit = self.config.sensors.max_range_m
            points = points[np.einsum("ij,ij->i", rel, rel) <= limit * limit]
        self.memory.clear_observed(scan, pose)
        self._accept_points(points, scan.t_s)

    def _accept_points(self, points: Any, t_s: float) -> None:
        self.navigator.update_ranges(np.asarray(points, dtype=np.float64).reshape(-1, 3), t_s)

    def _on_command(self, msg: Any) -> None:
        self.counters.commands_for_us += 1
        src_sys, src_comp = msg.get_srcSystem(), msg.get_srcComponent()
        cmd = int(msg.command)
        if cmd != MAV_CMD_DO_REPOSITION:
            self._ack(cmd, MAV_RESULT_UNSUPPORTED, src_sys, src_comp)
            return
        if msg.get_type() == "COMMAND_LONG":
            self._ack(cmd, MAV_RESULT_COMMAND_INT_ONLY, src_sys, src_comp)
            return
        now = self.clock.now()
        try:
            route = local_goal_from_reposition(
                frame=int(msg.frame),
                x=int(msg.x),
                y=int(msg.y),
                z=float(msg.z),
                reference=self._global_ref,
                source=f"mavlink:{src_sys}/{src_comp}",
            )
        except RepositionError as err:
            self.counters.bad_goals += 1
            self._ack(cmd, err.result, src_sys, src_comp)
            log.info("goal.rejected", extra={"source": "mavlink", "error": str(err)})
            return
        accepted = self._set_route(route, now)
        self._ack(cmd, MAV_RESULT_ACCEPTED if accepted else 1, src_sys, src_comp)

    def _set_route(self, route: Route, now: float) -> bool:
        accepted = self.navigator.set_route(route, now)
        if accepted:
            self.counters.goals += 1
            self._outcome = None
            self._end_s = None
            log.info("goal.set", extra={"source": route.source, "waypoints_ned_m": route.to_json_list()})
            self._flush_changes(None, now)
        else:
            self.counters.bad_goals += 1
        return accepted

    # ---------------------------------------------------------------------------------------------- cycle
    async def _cycle_loop(self) -> None:
        """Pose-triggered cycles, at most one per ``min_gap``; a timer cycle when no pose triggered one for
        1.25 periods (a frozen or lost pose is still noticed within one period of its limit)."""
        period = 1.0 / self.config.cycle.rate_hz
        min_gap = 0.8 * period  # jitter margin: a pose stream at the cycle rate triggers every cycle
        last_cycle = self.clock.now()
        last_triggered = -math.inf
        while True:
            deadline = last_cycle + 1.25 * period
            timeout = self.clock.to_wall(deadline - self.clock.now())
            triggered = False
            if timeout > 0:
                with contextlib.suppress(TimeoutError):
                    async with asyncio.timeout(timeout):
                        await self._new_pose.wait()
                        triggered = True
            now = self.clock.now()
            trigger = self._trigger_rx_wall
            self._new_pose.clear()
            self._trigger_rx_wall = None
            if triggered:
                if now - last_triggered < min_gap:
                    continue  # a faster pose stream than the cycle rate: skip this one
                last_triggered = now
            else:
                trigger = None
            last_cycle = now
            self._run_cycle(now, trigger)

    def _run_cycle(self, now: float, trigger_wall: float | None) -> CycleOutput:
        out = self.navigator.cycle(now)
        sp = out.setpoint
        if sp is not None:
            if sp.kind is SetpointKind.PRESTREAM:
                if self._last_prestream is None or now - self._last_prestream > 0.5:
                    self._prestream_since = now
                self._last_prestream = now
            elif sp.kind is SetpointKind.NAVIGATE and self._first_nav_s is None:
                self._first_nav_s = now
            if not self._silent:
                assert self.link is not None
                self.link.send(
                    encode_setpoint(
                        self.link.mav,
                        sp,
                        time_boot_ms=self._boot_ms(),
                        target_system=self.config.link.autopilot_sysid,
                        target_component=self.config.link.autopilot_compid,
                    )
                )
                self.counters.setpoints_sent += 1
            if trigger_wall is not None:
                self.latency.add((time.perf_counter() - trigger_wall) * 1000.0)
            log.debug(
                "cycle.setpoint",
                extra={
                    "state": out.state.value,
                    "kind": sp.kind.value,
                    "pos_ned_m": sp.pos_ned_m,
                    "vel_ned_m_s": sp.vel_ned_m_s,
                    "decision": out.decision,
                    "dry_run": self.config.dry_run,
                },
            )
        self._flush_changes(out, now)
        self._check_done(now)
        return out

    def _flush_changes(self, out: CycleOutput | None, now: float) -> None:
        changes = list(out.changes) if out is not None else []
        changes.extend(self.navigator.drain_changes())  # from set_route / heartbeats, outside a cycle
        for ch in changes:
            self._reason = ch.reason
            log.info(
                "state.change",
                extra={"old": ch.old.value, "new": ch.new.value, "reason": ch.reason, "t_s": ch.t_s},
            )
            if ch.new is not State.LINK_LOST:  # LINK_LOST means silence towards the autopilot
                self._statustext(severity_for(ch.new), statustext_for(ch.new, ch.reason))

    def _check_done(self, now: float) -> None:
        if not self.config.exit_when_done or self._outcome is not None:
            return
        state = self.navigator.state
        outcome = None
        if state is State.ARRIVED:
            outcome = "arrived"
        elif state is State.STUCK:
            outcome = "stuck"
        elif state is State.LINK_LOST:
            outcome = "link_lost"
        elif state is State.IDLE and self.counters.goals > 0 and self.navigator.route is None:
            outcome = "error"  # the goal was dropped: takeover failed or the pilot took over
        elif (
            self.config.max_flight_s > 0
            and self._first_nav_s is not None
            and now - self._first_nav_s > self.config.max_flight_s
        ):
            outcome = "timeout"
        if outcome is not None:
            self._outcome = outcome
            self._end_s = now
            self._stop.set()

    # ---------------------------------------------------------------------------------------------- status
    def _inputs_healthy(self, now: float) -> bool:
        return self.navigator.pose_fresh(now) and self.navigator.ranges_fresh(now)

    async def _heartbeat_loop(self) -> None:
        assert self.link is not None
        cfg = self.config
        nvf_period = 1.0 / cfg.status.named_value_rate_hz if cfg.status.named_value_rate_hz > 0 else math.inf
        z_period = 1.0 / cfg.zenoh.status_rate_hz
        next_hb = next_nvf = next_z = self.clock.now()
        while True:
            now = self.clock.now()
            if now >= next_hb:
                next_hb = now + 1.0
                status = system_status_for(self.navigator.state, healthy_inputs=self._inputs_healthy(now))
                self._send(
                    self.link.mav.heartbeat_encode(MAV_TYPE_ONBOARD_CONTROLLER, MAV_AUTOPILOT_INVALID, 0, 0, status, 3)
                )
            if now >= next_nvf:
                next_nvf = now + nvf_period
                self._send_named_values()
            if self.zenoh is not None and now >= next_z:
                next_z = now + z_period
                self._publish_status(now)
            await self.clock.sleep(min(next_hb, next_nvf, next_z if self.zenoh is not None else math.inf) - now)

    def _send_named_values(self) -> None:
        out = self.navigator.last_output
        if out is None or self.navigator.state is State.LINK_LOST or self._silent:
            return
        assert self.link is not None
        t = self._boot_ms()
        for name, value in (
            (NVF_GOAL_DISTANCE, out.distance_to_goal_m),
            (NVF_NEAREST_OBSTACLE, out.nearest_obstacle_m),
        ):
            if value is not None and math.isfinite(value):
                self._send(self.link.mav.named_value_float_encode(t, name.encode(), float(value)))

    def status_dict(self, now: float) -> dict[str, Any]:
        """The status record (see apf_companion.status for the schema)."""
        nav = self.navigator
        pose = nav.pose
        out = nav.last_output
        target = nav.active_target_ned_m
        route = nav.route
        return {
            "t_s": now,
            "state": nav.state.value,
            "reason": self._reason,
            "pose": None
            if pose is None
            else {
                "north_m": float(pose.pos_ned_m[0]),
                "east_m": float(pose.pos_ned_m[1]),
                "down_m": float(pose.pos_ned_m[2]),
                "yaw_deg": math.degrees(pose.yaw_rad),
                "age_s": now - pose.t_s,
            },
            "goal": None
            if target is None or route is None
            else {
                "north_m": float(target[0]),
                "east_m": float(target[1]),
                "down_m": float(target[2]),
                "leg": nav.leg_index,
                "legs": len(route),
                "source": route.source,
            },
            "distance_to_goal_m": None if out is None else out.distance_to_goal_m,
            "nearest_obstacle_m": None if out is None else out.nearest_obstacle_m,
            "n_obstacles": len(self.memory),
            "loop_latency_ms": self.latency.summary(),
            "decision": None if out is None else out.decision,
            "autopilot": {
                "mode_ok": nav.mode_ok,
                "armed": bool(self._ap_base_mode & MAV_MODE_FLAG_SAFETY_ARMED),
                "link_alive": nav.link_alive(now),
            },
            "counters": dataclasses.asdict(self.counters),
        }

    def _publish_status(self, now: float) -> None:
        if self.zenoh is None or self.config.dry_run:
            return
        try:
            self.zenoh.publish(self.config.zenoh.status_key, encode_status_json(self.status_dict(now)))
        except LinkError:
            log.debug("status.publish_failed", exc_info=True)

    # ---------------------------------------------------------------------------------------------- takeover
    async def _takeover_loop(self) -> None:
        cfg = self.config
        while True:
            await self.clock.sleep(0.05)
            nav = self.navigator
            if cfg.dry_run or not cfg.autopilot.takeover:
                continue
            if nav.state is not State.NAVIGATING or nav.engaged or nav.route is None:
                continue
            route = nav.route
            try:
                await self._take_over(route)
            except _TakeoverFailed as err:
                log.warning("takeover.failed", extra={"error": str(err)})
                if nav.route is route:
                    nav.resume()
                    nav.clear_route(self.clock.now(), f"takeover failed: {err}")
                    self._flush_changes(None, self.clock.now())

    async def _wait_for(self, what: str, cond: Any, resend: Any, timeout_s: float, route: Route) -> None:
        """Wait until ``cond()``; call ``resend()`` every COMMAND_RETRY_S; fail after ``timeout_s`` (vehicle s)."""
        deadline = self.clock.now() + timeout_s
        next_send = self.clock.now()
        while not cond():
            now = self.clock.now()
            if self.navigator.route is not route:
                raise _TakeoverFailed(f"{what}: goal replaced")
            if now > deadline:
                raise _TakeoverFailed(f"{what} not confirmed within {timeout_s:.1f} s")
            if resend is not None and now >= next_send:
                resend()
                next_send = now + COMMAND_RETRY_S
            await self.clock.sleep(0.02)

    def _armed(self) -> bool:
        return bool(self._ap_base_mode & MAV_MODE_FLAG_SAFETY_ARMED)

    def _set_mode_cmd(self) -> None:
        self.counters.mode_requests += 1
        if self.config.autopilot.profile is Autopilot.ARDUPILOT:
            self._command_long(MAV_CMD_DO_SET_MODE, MAV_MODE_FLAG_CUSTOM_MODE_ENABLED, float(CopterMode.GUIDED))
        else:
            self._command_long(
                MAV_CMD_DO_SET_MODE,
                MAV_MODE_FLAG_CUSTOM_MODE_ENABLED,
                float(PX4_OFFBOARD.main),
                float(PX4_OFFBOARD.sub),
            )

    async def _take_over(self, route: Route) -> None:
        cfg = self.config.autopilot
        nav = self.navigator
        ardupilot = cfg.profile is Autopilot.ARDUPILOT
        mode_ok = lambda: self._ap_custom_mode is not None and self._mode_ok(self._ap_custom_mode)  # noqa: E731
        log.info("takeover.start", extra={"profile": cfg.profile.value, "arm": cfg.arm})
        if cfg.arm and not self._armed():
            nav.suspend()  # no setpoints while arming / taking off
            try:
                if ardupilot:
                    # ArduCopter takes off only in GUIDED: switch first, then arm.
                    await self._wait_for("GUIDED", mode_ok, self._set_mode_cmd, cfg.mode_timeout_s, route)
                await self._wait_for(
                    "arming",
                    self._armed,
                    lambda: self._command_long(MAV_CMD_COMPONENT_ARM_DISARM, 1.0),
                    cfg.mode_timeout_s,
                    route,
                )
                if cfg.takeoff_alt_m > 0:
                    home_down = nav.pose.pos_ned_m[2] if nav.pose is not None else 0.0
                    target_down = home_down - cfg.takeoff_alt_m

                    def high_enough() -> bool:
                        p = nav.pose
                        return p is not None and (home_down - p.pos_ned_m[2]) >= (
                            TAKEOFF_REACHED_FRACTION * cfg.takeoff_alt_m
                        )

                    takeoff_alt = cfg.takeoff_alt_m  # ArduCopter: param7 is the height above home
                    if not ardupilot:
                        # PX4: param7 is an AMSL altitude; home AMSL comes from GLOBAL_POSITION_INT.
                        await self._wait_for(
                            "global position", lambda: self._global_ref is not None, None, cfg.mode_timeout_s, route
                        )
                        ref = self._global_ref
                        assert ref is not None
                        takeoff_alt = ref.alt_amsl_m - ref.alt_rel_m + cfg.takeoff_alt_m

                    await self._wait_for(
                        "takeoff",
                        high_enough,
                        lambda: self._command_long(
                            MAV_CMD_NAV_TAKEOFF, 0, 0, 0, math.nan, math.nan, math.nan, takeoff_alt
                        ),
                        cfg.mode_timeout_s + 4.0 * cfg.takeoff_alt_m,
                        route,
                    )
                    log.info("takeover.airborne", extra={"down_m": target_down})
            finally:
                nav.resume()
        if not ardupilot:
            # PX4 accepts OFFBOARD only after setpoints have streamed for a while (> 1 s).
            def prestreamed() -> bool:
                since = self._prestream_since
                last = self._last_prestream
                now = self.clock.now()
                return (
                    since is not None
                    and last is not None
                    and now - last < 0.5
                    and last - since >= cfg.offboard_prestream_s
                )

            await self._wait_for("setpoint pre-stream", prestreamed, None, cfg.mode_timeout_s + 5.0, route)
        await self._wait_for(
            "GUIDED" if ardupilot else "OFFBOARD", mode_ok, self._set_mode_cmd, cfg.mode_timeout_s, route
        )
        log.info("takeover.done", extra={"profile": cfg.profile.value})

    # ---------------------------------------------------------------------------------------------- zenoh
    async def _zenoh_loop(self) -> None:
        zl = self.zenoh
        assert zl is not None
        zc = self.config.zenoh
        async for sample in zl.samples():
            now = self.clock.now()
            if sample.key_expr == zc.goal_key:
                self._on_zenoh_goal(sample.payload, now)
            elif sample.key_expr == zc.sensor_key:
                self._on_zenoh_scan(sample.encoding, sample.payload, now)
            else:
                self.counters.foreign_messages += 1

    def _on_zenoh_goal(self, payload: bytes, now: float) -> None:
        try:
            goal = decode_goal_json(payload)
        except (ProtocolError, ConfigError) as err:
            self.counters.bad_goals += 1
            log.info("goal.rejected", extra={"source": "zenoh", "error": str(err)})
            return
        p = goal.pos_ned_m
        self._set_route(Route.point(float(p[0]), float(p[1]), float(p[2]), source="zenoh"), now)

    def _on_zenoh_scan(self, encoding: str, payload: bytes, now: float) -> None:
        try:
            if "cdr" in encoding:
                scan = decode_laserscan_cdr(payload, t_s=now)
            else:
                scan = decode_scan_json(payload, t_s=now)
                if scan.time_boot_ms is not None:
                    scan = dataclasses.replace(scan, t_s=self._scan_time(scan.time_boot_ms, now))
        except (ProtocolError, ConfigError) as err:
            self.counters.bad_scans += 1
            log.debug("ranges.bad", extra={"source": "zenoh", "error": str(err)})
            return
        self._accept_scan(scan)


class _TakeoverFailed(ApfCompanionError):
    pass


async def _open_zenoh(config: ServiceConfig) -> Any:
    """Open the zenoh session and subscribe: sensor topic latest-wins, goal topic FIFO (bounded)."""
    from apf_companion.links.zenoh import Overflow, ZenohConfig, ZenohLink

    zc = config.zenoh
    config_file = str(config.resolve(zc.config_file)) if zc.config_file else None
    link = await ZenohLink.open(
        ZenohConfig(mode=zc.mode, connect=zc.connect, listen=zc.listen, config_file=config_file)
    )
    try:
        if config.sensors.zenoh:
            await link.subscribe(zc.sensor_key, overflow=Overflow.LATEST_PER_KEY, capacity=4)
        await link.subscribe(zc.goal_key, overflow=Overflow.FIFO, capacity=16)
    except BaseException:
        await link.aclose()
        raise
    return link
