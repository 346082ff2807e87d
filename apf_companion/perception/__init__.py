"""apf_companion.perception: obstacle ranges and goals in, obstacle points in local NED out.

Adapters turn MAVLink (OBSTACLE_DISTANCE, DISTANCE_SENSOR, OBSTACLE_DISTANCE_3D) and zenoh (``apf.range_scan/1``
JSON, ROS 2 LaserScan CDR) inputs into ``RangeScan`` values. ``scan_to_points_ned`` places them in local
NED with the pose at measurement time (from a ``PoseHistory``), and an ``ObstacleMemory`` remembers the
points with expiry. Conventions and schemas: docs/perception.md.
"""

from __future__ import annotations

from apf_companion.perception.cdr import (
    LaserScanMsg,
    decode_laserscan_cdr,
    encode_laserscan_cdr,
    laserscan_to_scan,
    parse_laserscan_cdr,
)
from apf_companion.perception.forward import FORWARD_SECTORS, ForwardSectors, obstacle_sectors_cm
from apf_companion.perception.frontend import PerceptionCounters, PerceptionFrontEnd, PerceptionParams
from apf_companion.perception.geometry import scan_bearings_ned_rad, scan_to_points_ned, surface_fill_points
from apf_companion.perception.heading import HeadingTrack, euler_yaw_rate_rad_s
from apf_companion.perception.history import PoseHistory
from apf_companion.perception.mavlink_ranges import (
    obstacle_distance_element_count,
    points_from_obstacle_distance_3d,
    scan_from_distance_sensor,
    scan_from_obstacle_distance,
)
from apf_companion.perception.memory import ObstacleMemory
from apf_companion.perception.payload import ENCODING_CDR, ENCODING_JSON, decode_scan_payload
from apf_companion.perception.plausibility import PoseGate, PoseLimits, Verdict
from apf_companion.perception.schema import (
    GOAL_SCHEMA,
    SCAN_SCHEMA,
    decode_goal_json,
    decode_scan_json,
    encode_goal_json,
    encode_scan_json,
)
from apf_companion.perception.types import GoalCommand, Pose, RangeScan, ScanFrame, SectorCounts

__all__ = [
    "ENCODING_CDR",
    "ENCODING_JSON",
    "FORWARD_SECTORS",
    "GOAL_SCHEMA",
    "SCAN_SCHEMA",
    "ForwardSectors",
    "GoalCommand",
    "HeadingTrack",
    "LaserScanMsg",
    "ObstacleMemory",
    "PerceptionCounters",
    "PerceptionFrontEnd",
    "PerceptionParams",
    "Pose",
    "PoseGate",
    "PoseHistory",
    "PoseLimits",
    "RangeScan",
    "ScanFrame",
    "SectorCounts",
    "Verdict",
    "decode_goal_json",
    "decode_laserscan_cdr",
    "decode_scan_json",
    "decode_scan_payload",
    "encode_goal_json",
    "encode_laserscan_cdr",
    "encode_scan_json",
    "euler_yaw_rate_rad_s",
    "laserscan_to_scan",
    "obstacle_distance_element_count",
    "obstacle_sectors_cm",
    "parse_laserscan_cdr",
    "points_from_obstacle_distance_3d",
    "scan_bearings_ned_rad",
    "scan_from_distance_sensor",
    "scan_from_obstacle_distance",
    "scan_to_points_ned",
    "surface_fill_points",
]
