"""apf_companion.perception: obstacle ranges and goals in, obstacle points in local NED out.

Adapters turn MAVLink (OBSTACLE_DISTANCE, DISTANCE_SENSOR, OBSTACLE_DISTANCE_3D) and zenoh (JSON, ROS 2
LaserScan CDR) inputs into ``RangeScan`` values, which are placed in local NED with the pose at measurement
time and remembered, with expiry, in an ``ObstacleMemory``. Conventions: docs/parts/perception.md.
"""

from __future__ import annotations

from apf_companion.perception.types import GoalCommand, Pose, RangeScan, ScanFrame, SectorCounts

__all__ = [
    "GoalCommand",
    "Pose",
    "RangeScan",
    "ScanFrame",
    "SectorCounts",
]
