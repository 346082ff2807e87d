"""The perception front end: the one owner of pose history, scan timing and the obstacle memory.

Poses (LOCAL_POSITION_NED with the ATTITUDE yaw at its own time, ``HeadingTrack``) go into a ``PoseHistory``;
range scans (MAVLink OBSTACLE_DISTANCE / DISTANCE_SENSOR / OBSTACLE_DISTANCE_3D, zenoh JSON or CDR) are stamped on
the service clock, placed in local NED with the pose at their measurement time and written to the
``ObstacleMemory``. Nothing else writes that memory: the navigator reads it through ``points`` and
``ranges_t_s`` (the ``ObstacleView`` protocol).

A scan measured after the newest pose waits for the next pose (at most ``SCAN_DEFER_S``, at most
``SCAN_DEFER_MAX`` scans), so that it is placed with the pose interpolated at its time rather than the previous
one: at 20 Hz telemetry and 1 m/s that is up to 5 cm of obstacle position (measured: the remembered points near
the vehicle were 4-5 cm off (median) with the previous pose, 1.4-2.4 cm interpolated, in the sweep's graze
flights).

Bad input is counted in ``counters`` and never raises out of the ``on_*`` methods. A rejected scan is also logged
(``ranges.bad`` at WARNING, naming the source and the decoder's error): the first one at once, then at most one line
per ``BAD_SCAN_LOG_INTERVAL_S`` of the service clock, carrying how many were not logged since the previous line.
"""

from __future__ import annotations

import collections
import dataclasses
import logging
import math
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from apf_companion.errors import ConfigError, ProtocolError
from apf_companion.perception.geometry import (
    return_spread_m,
    scan_bearings_ned_rad,
    scan_to_points_ned,
    surface_fill_points,
)
from apf_companion.perception.heading import HeadingTrack
from apf_companion.perception.history import PoseHistory
from apf_companion.perception.mavlink_ranges import (
    MAV_FRAME_GLOBAL,
    DistanceSensorLike,
    ObstacleDistance3dLike,
    ObstacleDistanceLike,
    points_from_obstacle_distance_3d,
    scan_from_distance_sensor,
    scan_from_obstacle_distance,
)
from apf_companion.perception.memory import ObstacleMemory
from apf_companion.perception.payload import decode_scan_payload
from apf_companion.perception.plausibility import PoseGate, PoseLimits, Verdict
from apf_companion.perception.ratelog import RateLimitedLog
from apf_companion.perception.sectors import SectorFreshness
from apf_companion.perception.types import FloatArray, Pose, RangeScan, ScanFrame

__all__ = [
    "BAD_SCAN_LOG_INTERVAL_S",
    "MAX_SENSOR_IDS",
    "SCAN_DEFER_MAX",
    "SCAN_DEFER_S",
    "PerceptionCounters",
    "PerceptionFrontEnd",
    "PerceptionParams",
]

log = logging.getLogger(__name__)

# Sensor ids are named by the scan's source, and a zenoh LaserScan's source carries its frame_id: a publisher that
# changes frame_id on every scan would grow the table for ever. Sources beyond this many share one id.
MAX_SENSOR_IDS = 64
SCAN_DEFER_S = 0.25  # a scan newer than the newest pose waits this long at most for the next pose [s]
SCAN_DEFER_MAX = 8  # and at most this many scans wait
MAX_HEADING_AGE_S = 1.0  # a pose this far from every ATTITUDE (the stream stopped) places no ranges [s]
POSE_HISTORY_LEN = 200  # poses kept to place scans (10 s at 20 Hz)
STAMP_PLAUSIBLE_S = 5.0  # a stamp older than this (or in the future) is on another clock: use receive time
UNIX_USEC = 10**15  # OBSTACLE_DISTANCE.time_usec at or above this is UNIX time, not time since boot
# A sensor sending only bad scans (10-50 Hz) must not fill the journal, but the user must see why bad_scans counts.
BAD_SCAN_LOG_INTERVAL_S = 10.0  # at most one ranges.bad (or pose.conflict) WARNING per this long (service clock) [s]
CONFLICT_HINT = (
    "two LOCAL_POSITION_NED streams with the autopilot's ids claim different positions for the same time (a spoofed "
    "stream, or a second source with the same sysid/compid): braking while they disagree; "
    "link.require_signed_telemetry drops unsigned poses"
)


@dataclass(frozen=True, slots=True, kw_only=True)
class PerceptionParams:
    """What the front end needs of the configuration (``[sensors]``)."""

    max_range_m: float = 10.0  # obstacle points farther than this from the vehicle are not remembered [m]
    memory_expiry_s: float = 5.0
    merge_radius_m: float = 0.2
    max_points: int = 2000
    pose_limits: PoseLimits = dataclasses.field(default_factory=PoseLimits)
    clear_scans: int = 1  # scans of the sensor that saw a point that must see through it before it is forgotten
    clear_span_s: float = 0.0  # ... spread over at least this long [s]
    sectors: int = 0  # azimuth sectors whose freshness is tracked (0 = off)
    sector_max_age_s: float = 1.0
    surface_fill: bool = True  # points along chords between adjacent returns on one surface (geometry.py)
    surface_fill_spacing_m: float = 0.2
    surface_fill_max_gap_m: float = 1.5
    surface_fill_line_tol_m: float = 0.05
    # How OBSTACLE_DISTANCE.frame is read: None = as sent; ScanFrame.BODY_FRD = every frame from the nose (ArduPilot)
    obstacle_distance_frame: ScanFrame | None = None
    obstacle_distance_mount_yaw_rad: float = 0.0  # added to OBSTACLE_DISTANCE bearings read from the nose [rad]
    laserscan_mount_yaw_rad: float = 0.0  # a zenoh LaserScan sensor's forward axis in body FRD [rad]

    def __post_init__(self) -> None:
        # Checked here, not at the first scan: the on_* methods must not raise.
        for name in ("obstacle_distance_mount_yaw_rad", "laserscan_mount_yaw_rad"):
            if not math.isfinite(getattr(self, name)):
                msg = f"{name} must be finite, got {getattr(self, name)}"
                raise ConfigError(msg)
        fill = (self.surface_fill_spacing_m, self.surface_fill_max_gap_m, self.surface_fill_line_tol_m)
        if not all(math.isfinite(v) for v in fill) or min(fill[:2]) <= 0.0 or fill[2] < 0.0:
            msg = f"surface fill spacing/max gap must be finite and > 0, line tolerance >= 0, got {fill}"
            raise ConfigError(msg)


@dataclass(slots=True)
class PerceptionCounters:
    """Bad and good input at the perception edge."""

    poses: int = 0
    bad_poses: int = 0  # NaN / non-finite LOCAL_POSITION_NED or ATTITUDE
    stale_poses: int = 0  # time_boot_ms not newer than the last accepted one (frozen or reordered)
    out_of_bounds_poses: int = 0  # a coordinate beyond [safety] max_abs_position_m
    implausible_poses: int = 0  # further than the vehicle can move since the last pose
    pose_time_leads: int = 0  # time_boot_ms ahead of the receive clock (its tracked relation) beyond the tolerance
    pose_time_jumps: int = 0  # time_boot_ms far back without reboot evidence
    pose_conflicts: int = 0  # stale, and contradicts the accepted poses of its time: a second stream (brakes)
    pose_resets: int = 0  # re-anchored on a sustained new position / time base (EKF reset, reboot)
    bad_velocities: int = 0  # a reported velocity non-finite or beyond [safety] max_speed_m_s: pose kept, no velocity
    stale_attitudes: int = 0  # an ATTITUDE not newer than the newest (reordered, duplicate): ignored
    poses_without_heading: int = 0  # no ATTITUDE within MAX_HEADING_AGE_S of the pose: no range placed with it
    bad_attitude_rates: int = 0  # ATTITUDE body rates non-finite or beyond 720 deg/s: the heading rate taken as 0
    scans: int = 0
    bad_scans: int = 0  # ProtocolError from a decoder (malformed message / payload)
    invalid_sectors: int = 0  # readings classified invalid (below min, zero, out of range)
    unknown_sectors: int = 0
    scans_without_pose: int = 0
    scans_deferred_too_long: int = 0  # placed with the newest pose: more than SCAN_DEFER_MAX scans waited
    clears_refused: int = 0  # a scan saw through a point another sensor saw: not cleared
    obstacle_distance_frame_global: int = 0  # OBSTACLE_DISTANCE with frame 0 read north-aligned (as sent)


class PerceptionFrontEnd:
    """Poses and scans in; placed obstacle points in the one ``ObstacleMemory`` out."""

    def __init__(self, params: PerceptionParams) -> None:
        self.params = params
        self.memory = ObstacleMemory(
            expiry_s=params.memory_expiry_s,
            merge_radius_m=max(params.merge_radius_m, 1e-3),
            max_points=params.max_points,
        )
        self.history = PoseHistory(POSE_HISTORY_LEN)
        self.counters = PerceptionCounters()
        self.deferred: collections.deque[RangeScan] = collections.deque()
        self.heading = HeadingTrack()
        self.gate = PoseGate(params.pose_limits)
        self.sectors = SectorFreshness(params.sectors, params.sector_max_age_s)
        self._sensor_ids: dict[str, int] = {}
        self.bad_scan_log = RateLimitedLog(log, "ranges.bad", BAD_SCAN_LOG_INTERVAL_S)
        self.conflict_log = RateLimitedLog(log, "pose.conflict", BAD_SCAN_LOG_INTERVAL_S)
        self.reset_reason: str | None = None  # set on a re-anchor; the handler takes it (hold + STATUSTEXT)
        self.conflict_said = False  # a pose.conflict WARNING was logged; the handler takes it (STATUSTEXT)
        self._boot_offset_s: float | None = None  # service time - autopilot boot time (latest pose)
        self._ranges_t_s: float | None = None
        #: The obstacle points the newest usable scan added, (M, 3) local NED [m] (read by the visualisation).
        self.latest_scan_ned_m: FloatArray = np.empty((0, 3))

    # ---- what the navigator reads (ObstacleView) -----------------------------------------------------------
    def points(self, now_s: float) -> FloatArray:
        """The remembered obstacle points still valid at ``now_s``, (N, 3) local NED [m]."""
        return self.memory.points(now_s)

    @property
    def ranges_t_s(self) -> float | None:
        """Measurement time of the newest usable scan (service clock), None before the first."""
        return self._ranges_t_s

    def __len__(self) -> int:
        return len(self.memory)

    def direction_fresh(self, bearing_ned_rad: float, now_s: float) -> bool:
        """The azimuth sector of ``bearing_ned_rad`` (local NED) has a recent reading (``[safety] sectors``)."""
        return self.sectors.fresh(bearing_ned_rad, now_s)

    def yaw_now(self, now_s: float) -> float | None:
        """The heading [rad] at service time ``now_s``: the ATTITUDE samples carried to the autopilot's present (by
        the rate, at most 0.25 s). None before the first pose or ATTITUDE, or with no ATTITUDE for
        ``MAX_HEADING_AGE_S`` (the stream stopped)."""
        boot_s = self.autopilot_boot_s(now_s)
        if boot_s is None:
            return None
        boot_ms = round(boot_s * 1000.0)
        return None if self.heading.age_s(boot_ms) > MAX_HEADING_AGE_S else self.heading.at(boot_ms)

    def autopilot_boot_s(self, now_s: float) -> float | None:
        """The autopilot's time since boot at service time ``now_s`` (offset of the latest pose), None before."""
        return None if self._boot_offset_s is None else now_s - self._boot_offset_s

    # ---- poses ---------------------------------------------------------------------------------------------
    def on_attitude(self, yaw_rad: float, *, time_boot_ms: int | None = None, yaw_rate_rad_s: float = 0.0) -> None:
        """ATTITUDE.yaw [rad] measured at ``time_boot_ms``, with the heading rate [rad/s]: poses take the yaw at
        their own time from these samples (perception/heading.py). Without a time, the next poses carry it as is."""
        if np.isfinite(yaw_rad):
            h = self.heading
            h.update(float(yaw_rad), time_boot_ms, yaw_rate_rad_s)
            self.counters.stale_attitudes, self.counters.bad_attitude_rates = h.stale, h.bad_rates
        else:
            self.counters.bad_poses += 1

    def on_local_position(
        self,
        time_boot_ms: int,
        pos_ned_m: tuple[float, float, float],
        now_s: float,
        vel_ned_m_s: tuple[float, float, float] | None = None,
    ) -> Pose | None:
        """A LOCAL_POSITION_NED received at ``now_s``: the new pose (history updated, waiting scans placed), or
        None when it is stale, non-finite or no heading is known yet. An implausible reported velocity does not
        reject the pose: the pose carries no velocity (the navigator's braking envelope is then off)."""
        self.counters.poses += 1
        yaw_rad = self.heading.at(time_boot_ms)
        if yaw_rad is None:
            return None  # no ATTITUDE yet: body-frame ranges could not be placed
        verdict = self.gate.check(time_boot_ms, pos_ned_m, now_s)
        if verdict is Verdict.CONFLICT and self.conflict_log.note(now_s, hint=CONFLICT_HINT):
            self.conflict_said = True  # the handler takes it (``take_conflict``): a STATUSTEXT as often as the log
        if verdict is Verdict.RESET:
            self._reset(f"position reset to {pos_ned_m[0]:.1f} {pos_ned_m[1]:.1f} {pos_ned_m[2]:.1f}")
        elif verdict is not Verdict.ACCEPT:
            counter = _REJECTED[verdict]
            setattr(self.counters, counter, getattr(self.counters, counter) + 1)
            return None
        vel = self._plausible_velocity(vel_ned_m_s)
        try:
            pose = Pose(t_s=now_s, pos_ned_m=np.array(pos_ned_m, dtype=np.float64), yaw_rad=yaw_rad, vel_ned_m_s=vel)
        except ConfigError:
            self.counters.bad_poses += 1
            return None
        last = self.gate.last
        # The pose's effective time (its stamp, no later than the receive clock allows): a pose stamped ahead does
        # not move where scans and headings are placed in time.
        self._boot_offset_s = now_s - (time_boot_ms / 1000.0 if last is None else last.eff_s)
        if self.heading.age_s(time_boot_ms) > MAX_HEADING_AGE_S:
            # The ATTITUDE stream stopped: the navigator still gets the position, but no range is placed with
            # a guessed heading (scans then find no pose, the memory ages, and "ranges stale" holds).
            self.counters.poses_without_heading += 1
            return pose
        self.history.add(pose)
        if self.deferred:
            self._place_deferred()  # before the cycle this pose triggers
        return pose

    def _plausible_velocity(self, vel: tuple[float, float, float] | None) -> FloatArray | None:
        if vel is None:
            return None
        v = np.array(vel, dtype=np.float64)
        if not np.all(np.isfinite(v)) or float(np.sqrt(v @ v)) > self.gate.limits.max_speed_m_s:
            self.counters.bad_velocities += 1
            return None
        return v

    def _reset(self, reason: str) -> None:
        """The gate re-anchored: poses and remembered points are in the old frame; forget them."""
        self.counters.pose_resets += 1
        self.history.clear()
        self.memory.clear()
        self.sectors.clear()
        self.reset_reason = reason
        log.warning("pose.reset", extra={"reason": reason})

    def take_reset(self) -> str | None:
        """The reason of a re-anchor since the last call, or None."""
        reason, self.reset_reason = self.reset_reason, None
        return reason

    def take_conflict(self) -> bool:
        """Whether a ``pose.conflict`` WARNING was logged since the last call (at most one per
        ``BAD_SCAN_LOG_INTERVAL_S``): the pilot is told why the vehicle brakes as often as the log is."""
        said, self.conflict_said = self.conflict_said, False
        return said

    def scan_time(self, boot_ms: int | None, now_s: float) -> float:
        """Service time of a measurement stamped with autopilot boot time (receive time if unknown)."""
        if boot_ms is None or self._boot_offset_s is None:
            return now_s
        t = boot_ms / 1000.0 + self._boot_offset_s
        return t if now_s - STAMP_PLAUSIBLE_S < t <= now_s else now_s  # implausible stamps: receive time

    # ---- scans ---------------------------------------------------------------------------------------------
    def on_obstacle_distance(self, msg: ObstacleDistanceLike, now_s: float) -> None:
        """An OBSTACLE_DISTANCE, its frame read as ``params.obstacle_distance_frame`` says, turned by the mount."""
        usec = msg.time_usec
        boot_ms = usec // 1000 if usec < UNIX_USEC else None  # UNIX-epoch stamps: use receive time
        p = self.params
        if p.obstacle_distance_frame is None and msg.frame == MAV_FRAME_GLOBAL:
            self._frame_global()

        def decode() -> RangeScan:
            return scan_from_obstacle_distance(
                msg,
                t_s=self.scan_time(boot_ms, now_s),
                frame_override=p.obstacle_distance_frame,
                mount_yaw_rad=p.obstacle_distance_mount_yaw_rad,
            )

        self._decoded("OBSTACLE_DISTANCE", now_s, decode)

    def _frame_global(self) -> None:
        """OBSTACLE_DISTANCE frame 0 read as sent: correct per the spec (MAV_FRAME_GLOBAL is north-aligned), but
        what a sensor script written for ArduPilot sends for a body-mounted sensor (ArduPilot ignores the frame,
        AP_Proximity_MAV.cpp), whose obstacles would then turn with the vehicle's heading. Counted; said once."""
        self.counters.obstacle_distance_frame_global += 1
        if self.counters.obstacle_distance_frame_global == 1:
            log.warning(
                "ranges.frame_global",
                extra={
                    "hint": "OBSTACLE_DISTANCE with frame 0 (MAV_FRAME_GLOBAL) is read north-aligned, as the spec "
                    "says; ArduPilot ignores the frame and reads it from the nose. If the sensor is body-mounted "
                    'set sensors.obstacle_distance_frame = "body_frd"; to keep reading it north-aligned and '
                    "silence this, have the sender use frame 1 (LOCAL_NED)",
                    "key": "sensors.obstacle_distance_frame",
                },
            )

    def on_distance_sensor(self, msg: DistanceSensorLike, now_s: float) -> None:
        t_s = self.scan_time(msg.time_boot_ms, now_s)
        self._decoded("DISTANCE_SENSOR", now_s, lambda: scan_from_distance_sensor(msg, t_s=t_s))

    def on_obstacle_distance_3d(self, msg: ObstacleDistance3dLike, now_s: float) -> None:
        """One obstacle point, placed with the pose at its time (no deferral: it is a point, not a scan)."""
        t = self.scan_time(msg.time_boot_ms, now_s)
        pose = self.history.at(t)
        if pose is None:
            self.counters.scans_without_pose += 1
            return
        try:
            points = points_from_obstacle_distance_3d(msg, pose)
        except ProtocolError as err:
            self._bad("OBSTACLE_DISTANCE_3D", err, now_s)
            return
        self.counters.scans += 1
        rel = np.asarray(points, dtype=np.float64).reshape(-1, 3) - pose.pos_ned_m
        self.sectors.note(np.arctan2(rel[:, 1], rel[:, 0]), t)
        self._remember(points, t, self._sensor_id("mavlink:obstacle_distance_3d"))

    def on_scan_payload(self, encoding: str | None, payload: bytes, now_s: float) -> None:
        """A zenoh scan: ROS 2 LaserScan CDR, or ``apf.range_scan/1`` JSON (stamped with boot time, if given).

        ``decode_scan_payload`` picks the decoder: from the encoding when it names JSON or CDR, else from the
        payload's first bytes (zenoh-bridge-ros2dds and rmw_zenoh publish with the default ``zenoh/bytes``)."""

        def decode() -> RangeScan:
            scan = decode_scan_payload(payload, encoding, t_s=now_s, mount_yaw_rad=self.params.laserscan_mount_yaw_rad)
            if scan.time_boot_ms is not None:
                scan = dataclasses.replace(scan, t_s=self.scan_time(scan.time_boot_ms, now_s))
            return scan

        self._decoded("zenoh", now_s, decode, errors=(ProtocolError, ConfigError))

    def on_scan(self, scan: RangeScan) -> None:
        """Place a decoded scan with the pose at its measurement time (or let it wait for the next pose)."""
        self.counters.scans += 1
        self.counters.invalid_sectors += scan.counts.invalid
        self.counters.unknown_sectors += scan.counts.unknown
        self.deferred.append(scan)
        self._place_deferred()

    def _decoded(
        self,
        source: str,
        now_s: float,
        decode: Callable[[], RangeScan],
        errors: tuple[type[Exception], ...] = (ProtocolError,),
    ) -> None:
        try:
            scan = decode()
        except errors as err:
            self._bad(source, err, now_s)
            return
        self.on_scan(scan)

    def _bad(self, source: str, err: Exception, now_s: float) -> None:
        """A scan the decoder refused at ``now_s``: counted, and logged (rate-limited) with why."""
        self.counters.bad_scans += 1
        self.bad_scan_log.note(now_s, source=source, error=str(err))

    def _place_deferred(self) -> None:
        """Place the waiting scans, oldest first, up to the first one still newer than the newest pose."""
        latest = self.history.latest()
        while self.deferred:
            scan = self.deferred[0]
            if latest is not None and 0.0 < scan.t_s - latest.t_s <= SCAN_DEFER_S:
                if len(self.deferred) <= SCAN_DEFER_MAX:
                    return
                self.counters.scans_deferred_too_long += 1
            self.deferred.popleft()
            self._place(scan)

    def _place(self, scan: RangeScan) -> None:
        pose = self.history.at(scan.t_s)
        if pose is None:
            self.counters.scans_without_pose += 1
            return
        if scan.counts.valid + scan.counts.free == 0:
            return  # nothing usable: no news about the surroundings, ranges stay as fresh as they were
        points = scan_to_points_ned(scan, pose)
        spread = return_spread_m(scan)  # how far beside its point each return's surface may lie (memory.py)
        if self.params.surface_fill:
            fill = surface_fill_points(
                scan,
                pose,
                spacing_m=self.params.surface_fill_spacing_m,
                max_gap_m=self.params.surface_fill_max_gap_m,
                line_tol_m=self.params.surface_fill_line_tol_m,
            )
            points = np.concatenate([points, fill])  # measured returns first: the memory's merge keeps them
            spread = np.concatenate([spread, np.zeros(fill.shape[0])])  # a chord's points lie on its line
        if points.shape[0]:
            rel = points[:, :2] - pose.pos_ned_m[:2]
            limit = self.params.max_range_m
            within = np.einsum("ij,ij->i", rel, rel) <= limit * limit
            points, spread = points[within], spread[within]
        p = self.params
        sensor = self._sensor_id(scan.source)
        refused = self.memory.clears_refused
        self.memory.clear_observed(scan, pose, sensor=sensor, clear_scans=p.clear_scans, clear_span_s=p.clear_span_s)
        self.counters.clears_refused += self.memory.clears_refused - refused
        bearings = scan_bearings_ned_rad(scan, pose)
        self.sectors.note(bearings[~np.isnan(scan.ranges_m)], scan.t_s)
        self._remember(points, scan.t_s, sensor, spread)

    def _sensor_id(self, source: str) -> int:
        """The clearing id of a scan source; sources after the first ``MAX_SENSOR_IDS`` share the id
        ``MAX_SENSOR_IDS`` (they can clear each other's points, never those of the first ones)."""
        sensor = self._sensor_ids.get(source)
        if sensor is None:
            sensor = len(self._sensor_ids)
            if sensor >= MAX_SENSOR_IDS:
                return MAX_SENSOR_IDS
            self._sensor_ids[source] = sensor
        return sensor

    def _remember(self, points: FloatArray, t_s: float, sensor: int = -1, spread_m: FloatArray | None = None) -> None:
        """The one write to the obstacle memory: a usable scan measured at ``t_s`` (possibly no points: all free
        is news too, it keeps the ranges fresh)."""
        pts = np.asarray(points, dtype=np.float64).reshape(-1, 3)
        self.latest_scan_ned_m = pts
        if pts.shape[0]:
            self.memory.add(pts, t_s, sensor, spread_m)
        if self._ranges_t_s is None or t_s > self._ranges_t_s:
            self._ranges_t_s = t_s

    def remember(self, points_ned_m: FloatArray, t_s: float) -> None:
        """Obstacle points already placed in local NED, measured at ``t_s`` (a perfect sensor in tests and
        closed-loop simulations; the service itself feeds scans): every direction counts as measured."""
        self.sectors.note_all(t_s)
        self._remember(points_ned_m, t_s)


_REJECTED = {
    Verdict.NON_FINITE: "bad_poses",
    Verdict.OUT_OF_BOUNDS: "out_of_bounds_poses",
    Verdict.STALE: "stale_poses",
    Verdict.TIME_LEAD: "pose_time_leads",
    Verdict.TIME_JUMP: "pose_time_jumps",
    Verdict.CONFLICT: "pose_conflicts",
    Verdict.JUMP: "implausible_poses",
}
"""The counter of each rejecting verdict."""
