"""What the perception front end and its parts read of the configuration (``[sensors]``), and what they count."""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass

from apf_companion.errors import ConfigError
from apf_companion.perception.plausibility import PoseLimits
from apf_companion.perception.types import ScanFrame

__all__ = ["BAD_SCAN_LOG_INTERVAL_S", "PerceptionCounters", "PerceptionParams"]

# A sensor sending only bad scans (10-50 Hz) must not fill the journal, but the user must see why bad_scans counts.
BAD_SCAN_LOG_INTERVAL_S = 10.0  # at most one ranges.bad (or pose.conflict) WARNING per this long (service clock) [s]


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
    estimator_resets: int = 0  # ODOMETRY reset_counter changes from the autopilot (PX4 EKF2: position, velocity, yaw)
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
