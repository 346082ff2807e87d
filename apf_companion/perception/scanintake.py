"""The scan intake: range messages in, decoded, stamped, placed with the pose at their time, into the obstacle store.

Range scans (MAVLink OBSTACLE_DISTANCE / DISTANCE_SENSOR / OBSTACLE_DISTANCE_3D, zenoh JSON or CDR) are stamped on
the service clock (the pose intake's boot-time offset), placed in local NED with the pose at their measurement time
(its ``PoseHistory``) and written to the ``ObstacleStore``.

A scan measured after the newest pose waits for the next pose (at most ``SCAN_DEFER_S``, at most
``SCAN_DEFER_MAX`` scans), so that it is placed with the pose interpolated at its time rather than the previous
one: at 20 Hz telemetry and 1 m/s that is up to 5 cm of obstacle position (measured: the remembered points near
the vehicle were 4-5 cm off (median) with the previous pose, 1.4-2.4 cm interpolated, in the sweep's graze
flights).

Bad input is counted and never raises out of the ``on_*`` methods. A rejected scan is also logged (``ranges.bad``
at WARNING, naming the source and the decoder's error): the first one at once, then at most one line per
``BAD_SCAN_LOG_INTERVAL_S`` of the service clock, carrying how many were not logged since the previous line.
"""

from __future__ import annotations

import collections
import dataclasses
import logging
from collections.abc import Callable

import numpy as np

from apf_companion.errors import ConfigError, ProtocolError
from apf_companion.perception.frontparams import BAD_SCAN_LOG_INTERVAL_S, PerceptionCounters, PerceptionParams
from apf_companion.perception.geometry import return_spread_m, scan_to_points_ned, surface_fill_points
from apf_companion.perception.mavlink_ranges import (
    MAV_FRAME_GLOBAL,
    DistanceSensorLike,
    ObstacleDistance3dLike,
    ObstacleDistanceLike,
    points_from_obstacle_distance_3d,
    scan_from_distance_sensor,
    scan_from_obstacle_distance,
)
from apf_companion.perception.payload import decode_scan_payload
from apf_companion.perception.poseintake import PoseIntake
from apf_companion.perception.ratelog import RateLimitedLog
from apf_companion.perception.store import ObstacleStore
from apf_companion.perception.types import FloatArray, Pose, RangeScan

__all__ = ["MAX_SENSOR_IDS", "SCAN_DEFER_MAX", "SCAN_DEFER_S", "ScanIntake"]

log = logging.getLogger("apf_companion.perception.frontend")  # the logger its lines had before the front end's split
# Sensor ids are named by the scan's source, and a zenoh LaserScan's source carries its frame_id: a publisher that
# changes frame_id on every scan would grow the table for ever. Sources beyond this many share one id.
MAX_SENSOR_IDS = 64
SCAN_DEFER_S = 0.25  # a scan newer than the newest pose waits this long at most for the next pose [s]
SCAN_DEFER_MAX = 8  # and at most this many scans wait
UNIX_USEC = 10**15  # OBSTACLE_DISTANCE.time_usec at or above this is UNIX time, not time since boot


class ScanIntake:
    """Owns the scans waiting for a pose, the scan sources' clearing ids and the ``ranges.bad`` log."""

    def __init__(
        self, params: PerceptionParams, counters: PerceptionCounters, *, poses: PoseIntake, store: ObstacleStore
    ) -> None:
        self.params = params
        self.counters = counters
        self._poses = poses
        self._store = store
        self.deferred: collections.deque[RangeScan] = collections.deque()
        self._sensor_ids: dict[str, int] = {}
        self.bad_scan_log = RateLimitedLog(log, "ranges.bad", BAD_SCAN_LOG_INTERVAL_S)

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
                t_s=self._poses.scan_time(boot_ms, now_s),
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
        t_s = self._poses.scan_time(msg.time_boot_ms, now_s)
        self._decoded("DISTANCE_SENSOR", now_s, lambda: scan_from_distance_sensor(msg, t_s=t_s))

    def on_obstacle_distance_3d(self, msg: ObstacleDistance3dLike, now_s: float) -> None:
        """One obstacle point, placed with the pose at its time (no deferral: it is a point, not a scan)."""
        t = self._poses.scan_time(msg.time_boot_ms, now_s)
        pose = self._poses.history.at(t)
        if pose is None:
            self.counters.scans_without_pose += 1
            return
        try:
            points = points_from_obstacle_distance_3d(msg, pose)
        except ProtocolError as err:
            self._bad("OBSTACLE_DISTANCE_3D", err, now_s)
            return
        self.counters.scans += 1
        self._store.add_points(points, pose, t, self._sensor_id("mavlink:obstacle_distance_3d"))

    def on_scan_payload(self, encoding: str | None, payload: bytes, now_s: float) -> None:
        """A zenoh scan: ROS 2 LaserScan CDR, or ``apf.range_scan/1`` JSON (stamped with boot time, if given).

        ``decode_scan_payload`` picks the decoder: from the encoding when it names JSON or CDR, else from the
        payload's first bytes (zenoh-bridge-ros2dds and rmw_zenoh publish with the default ``zenoh/bytes``)."""

        def decode() -> RangeScan:
            scan = decode_scan_payload(payload, encoding, t_s=now_s, mount_yaw_rad=self.params.laserscan_mount_yaw_rad)
            if scan.time_boot_ms is not None:
                scan = dataclasses.replace(scan, t_s=self._poses.scan_time(scan.time_boot_ms, now_s))
            return scan

        self._decoded("zenoh", now_s, decode, errors=(ProtocolError, ConfigError))

    def on_scan(self, scan: RangeScan) -> None:
        """Place a decoded scan with the pose at its measurement time (or let it wait for the next pose)."""
        self.counters.scans += 1
        self.counters.invalid_sectors += scan.counts.invalid
        self.counters.unknown_sectors += scan.counts.unknown
        self.deferred.append(scan)
        self.place_deferred()

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

    def place_deferred(self) -> None:
        """Place the waiting scans, oldest first, up to the first one still newer than the newest pose."""
        latest = self._poses.history.latest()
        while self.deferred:
            scan = self.deferred[0]
            if latest is not None and 0.0 < scan.t_s - latest.t_s <= SCAN_DEFER_S:
                if len(self.deferred) <= SCAN_DEFER_MAX:
                    return
                self.counters.scans_deferred_too_long += 1
            self.deferred.popleft()
            self._place(scan)

    def _place(self, scan: RangeScan) -> None:
        pose = self._poses.history.at(scan.t_s)
        if pose is None:
            self.counters.scans_without_pose += 1
            return
        if scan.counts.valid + scan.counts.free == 0:
            return  # nothing usable: no news about the surroundings, ranges stay as fresh as they were
        points, spread = self._points(scan, pose)
        self._store.observe(scan, pose, points, spread, self._sensor_id(scan.source))

    def _points(self, scan: RangeScan, pose: Pose) -> tuple[FloatArray, FloatArray]:
        """The scan's obstacle points within ``max_range_m`` of the vehicle, local NED, and how far beside each
        its surface may lie (memory.py): the returns first, then the surface fill (when on)."""
        points = scan_to_points_ned(scan, pose)
        spread = return_spread_m(scan)  # how far beside its point each return's surface may lie (memory.py)
        p = self.params
        if p.surface_fill:
            fill = surface_fill_points(
                scan,
                pose,
                spacing_m=p.surface_fill_spacing_m,
                max_gap_m=p.surface_fill_max_gap_m,
                line_tol_m=p.surface_fill_line_tol_m,
            )
            points = np.concatenate([points, fill])  # measured returns first: the memory's merge keeps them
            spread = np.concatenate([spread, np.zeros(fill.shape[0])])  # a chord's points lie on its line
        if points.shape[0]:
            rel = points[:, :2] - pose.pos_ned_m[:2]
            within = np.einsum("ij,ij->i", rel, rel) <= p.max_range_m * p.max_range_m
            points, spread = points[within], spread[within]
        return points, spread

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
