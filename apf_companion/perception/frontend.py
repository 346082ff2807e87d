"""The perception front end: the one owner of pose history, scan timing and the obstacle memory.

Poses (LOCAL_POSITION_NED with the ATTITUDE yaw at its own time, ``HeadingTrack``) go into a ``PoseHistory``;
range scans (MAVLink OBSTACLE_DISTANCE / DISTANCE_SENSOR / OBSTACLE_DISTANCE_3D, zenoh JSON or CDR) are stamped on
the service clock, placed in local NED with the pose at their measurement time and written to the
``ObstacleMemory``. Nothing else writes that memory: the navigator reads it through ``points`` and
``ranges_t_s`` (the ``ObstacleView`` protocol).

``PerceptionFrontEnd`` is the facade the service and the handlers use; its parts each own their state:

- ``PoseIntake`` (poseintake.py): the pose gate, the ATTITUDE samples, the pose history, the boot-time offset and
  the reset / conflict notices.
- ``ScanIntake`` (scanintake.py): decoding, stamping and placing scans, the scans waiting for a pose
  (``SCAN_DEFER_S``, ``SCAN_DEFER_MAX``), the sources' clearing ids, the ``ranges.bad`` log.
- ``ObstacleStore`` (store.py): the obstacle memory (its one writer), the sectors' freshness, the body-frame
  coverage (``LookCoverage``, coverage.py), the newest usable scan's time and points.

Bad input is counted in ``counters`` (``PerceptionCounters``, shared by the parts, each counting its own) and never
raises out of the ``on_*`` methods.
"""

from __future__ import annotations

import collections

from apf_companion.perception.frontparams import BAD_SCAN_LOG_INTERVAL_S, PerceptionCounters, PerceptionParams
from apf_companion.perception.heading import HeadingTrack
from apf_companion.perception.history import PoseHistory
from apf_companion.perception.mavlink_ranges import DistanceSensorLike, ObstacleDistance3dLike, ObstacleDistanceLike
from apf_companion.perception.memory import ObstacleMemory
from apf_companion.perception.plausibility import PoseGate
from apf_companion.perception.poseintake import PoseIntake, Vec3
from apf_companion.perception.ratelog import RateLimitedLog
from apf_companion.perception.scanintake import MAX_SENSOR_IDS, SCAN_DEFER_MAX, SCAN_DEFER_S, ScanIntake
from apf_companion.perception.store import ObstacleStore
from apf_companion.perception.types import FloatArray, Pose, RangeScan

__all__ = [
    "BAD_SCAN_LOG_INTERVAL_S",
    "MAX_SENSOR_IDS",
    "SCAN_DEFER_MAX",
    "SCAN_DEFER_S",
    "PerceptionCounters",
    "PerceptionFrontEnd",
    "PerceptionParams",
]


class PerceptionFrontEnd:
    """Poses and scans in; placed obstacle points in the one ``ObstacleMemory`` out (see the module docstring)."""

    def __init__(self, params: PerceptionParams) -> None:
        self.params = params
        self.counters = PerceptionCounters()
        self.store = ObstacleStore(params, self.counters)
        self.poses = PoseIntake(params.pose_limits, self.counters, store=self.store, pose_added=self._pose_added)
        self.scans = ScanIntake(params, self.counters, poses=self.poses, store=self.store)

    def _pose_added(self) -> None:
        self.scans.place_deferred()  # before the cycle this pose triggers

    def points(self, now_s: float) -> FloatArray:
        """The remembered obstacle points still valid at ``now_s``, (N, 3) local NED [m]."""
        return self.store.memory.points(now_s)

    @property
    def ranges_t_s(self) -> float | None:
        """Measurement time of the newest usable scan (service clock), None before the first."""
        return self.store.ranges_t_s

    def __len__(self) -> int:
        return len(self.store.memory)

    def direction_fresh(self, bearing_ned_rad: float, now_s: float) -> bool:
        """The azimuth sector of ``bearing_ned_rad`` (local NED) has a recent reading (``[safety] sectors``)."""
        return self.store.sectors.fresh(bearing_ned_rad, now_s)

    def look_offset_rad(self, now_s: float) -> float:
        """Body bearing (FRD, (-pi, pi] [rad]) of the centre of the arc the range sensors cover at ``now_s``; 0 with
        no recent reading or all-round coverage (``LookCoverage``, coverage.py)."""
        return self.store.coverage.offset_rad(now_s)

    @property
    def latest_scan_ned_m(self) -> FloatArray:
        """The obstacle points the newest usable scan added, (M, 3) local NED [m] (read by the visualisation)."""
        return self.store.latest_scan_ned_m

    def yaw_now(self, now_s: float) -> float | None:
        """The heading [rad] at service time ``now_s``; None before the first pose or with ATTITUDE stopped."""
        return self.poses.yaw_now(now_s)

    def autopilot_boot_s(self, now_s: float) -> float | None:
        """The autopilot's time since boot at service time ``now_s`` (offset of the latest pose), None before."""
        return self.poses.autopilot_boot_s(now_s)

    def scan_time(self, boot_ms: int | None, now_s: float) -> float:
        """Service time of a measurement stamped with autopilot boot time (receive time if unknown)."""
        return self.poses.scan_time(boot_ms, now_s)

    def on_attitude(self, yaw_rad: float, *, time_boot_ms: int | None = None, yaw_rate_rad_s: float = 0.0) -> None:
        """ATTITUDE.yaw [rad] measured at ``time_boot_ms``, with the heading rate [rad/s] (``PoseIntake``)."""
        self.poses.on_attitude(yaw_rad, time_boot_ms=time_boot_ms, yaw_rate_rad_s=yaw_rate_rad_s)

    def on_local_position(
        self, time_boot_ms: int, pos_ned_m: Vec3, now_s: float, vel_ned_m_s: Vec3 | None = None
    ) -> Pose | None:
        """A LOCAL_POSITION_NED received at ``now_s``: the new pose (history updated, waiting scans placed), or
        None when it is rejected or no heading is known yet (``PoseIntake.on_local_position``)."""
        return self.poses.on_local_position(time_boot_ms, pos_ned_m, now_s, vel_ned_m_s)

    def take_reset(self) -> str | None:
        """The reason of a re-anchor since the last call, or None."""
        return self.poses.take_reset()

    def take_conflict(self) -> bool:
        """Whether a ``pose.conflict`` WARNING was logged since the last call."""
        return self.poses.take_conflict()

    @property
    def history(self) -> PoseHistory:
        return self.poses.history

    @property
    def heading(self) -> HeadingTrack:
        return self.poses.heading

    @property
    def gate(self) -> PoseGate:
        return self.poses.gate

    def on_obstacle_distance(self, msg: ObstacleDistanceLike, now_s: float) -> None:
        """An OBSTACLE_DISTANCE, its frame read as ``params.obstacle_distance_frame`` says, turned by the mount."""
        self.scans.on_obstacle_distance(msg, now_s)

    def on_distance_sensor(self, msg: DistanceSensorLike, now_s: float) -> None:
        """A DISTANCE_SENSOR: a one-beam scan (none from a beam that is not horizontal)."""
        self.scans.on_distance_sensor(msg, now_s)

    def on_obstacle_distance_3d(self, msg: ObstacleDistance3dLike, now_s: float) -> None:
        """One obstacle point, placed with the pose at its time (no deferral)."""
        self.scans.on_obstacle_distance_3d(msg, now_s)

    def on_scan_payload(self, encoding: str | None, payload: bytes, now_s: float) -> None:
        """A zenoh scan: ROS 2 LaserScan CDR, or ``apf.range_scan/1`` JSON (``ScanIntake.on_scan_payload``)."""
        self.scans.on_scan_payload(encoding, payload, now_s)

    def on_scan(self, scan: RangeScan) -> None:
        """Place a decoded scan with the pose at its measurement time (or let it wait for the next pose)."""
        self.scans.on_scan(scan)

    @property
    def deferred(self) -> collections.deque[RangeScan]:
        return self.scans.deferred

    @property
    def bad_scan_log(self) -> RateLimitedLog:
        return self.scans.bad_scan_log

    @property
    def memory(self) -> ObstacleMemory:
        return self.store.memory

    def remember(self, points_ned_m: FloatArray, t_s: float) -> None:
        """Obstacle points already placed in local NED, measured at ``t_s`` (a perfect sensor in tests and
        closed-loop simulations; the service itself feeds scans): every direction counts as measured."""
        self.store.remember(points_ned_m, t_s)
