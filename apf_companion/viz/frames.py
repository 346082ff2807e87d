"""Topics and frames of the Foxglove output (shared by the sink, the layout, the MCAP plot and the tests).

Frames (Foxglove frames are plain names; we say what each one is):

- ``ned``: the service's local NED frame, x north, y east, z down [m], origin the autopilot's local origin (the
  EKF origin, as in LOCAL_POSITION_NED). Every pose, point and setpoint is published in it, unchanged.
- ``enu``: a z-up display frame for the 3D panel (its grid and camera assume z up). One ``FrameTransform``
  (parent ``enu``, child ``ned``), published every cycle so a recording can be opened at any time, maps
  p_enu = (p_ned.y, p_ned.x, -p_ned.z): the rotation of pi about the axis (1, 1, 0)/sqrt(2), quaternion
  (x, y, z, w) = (sqrt(1/2), sqrt(1/2), 0, 0), no translation.
- The vehicle's attitude on ``/apf/pose`` is body FRD in ``ned``: yaw psi about the down axis (heading, 0 =
  north, clockwise positive), quaternion (0, 0, sin(psi/2), cos(psi/2)); the service tracks no roll or pitch.
"""

from __future__ import annotations

import enum
import math

__all__ = ["FRAME_ENU", "FRAME_NED", "NED_IN_ENU_XYZW", "Topic", "yaw_quaternion_xyzw"]

FRAME_NED = "ned"
FRAME_ENU = "enu"
#: Rotation of ``ned`` in ``enu`` (x, y, z, w): pi about (1, 1, 0)/sqrt(2) swaps north/east and flips down.
NED_IN_ENU_XYZW = (math.sqrt(0.5), math.sqrt(0.5), 0.0, 0.0)


class Topic(enum.StrEnum):
    """The topics (Foxglove's well-known schemas, protobuf; ``CYCLE`` is JSON)."""

    TF = "/tf"  # foxglove.FrameTransform enu -> ned
    POSE = "/apf/pose"  # foxglove.PoseInFrame, ned
    OBSTACLES = "/apf/obstacles"  # foxglove.PointCloud x, y, z: remembered obstacle points
    SCAN = "/apf/scan"  # foxglove.PointCloud x, y, z: the points the newest scan added
    CANDIDATES = "/apf/candidates"  # foxglove.PointCloud x, y, z, score, cost_m: the bacteria points scored
    SCENE = "/apf/scene"  # foxglove.SceneUpdate: goal and route, chosen point, setpoint, state label
    LOG = "/apf/log"  # foxglove.Log: state changes and decision changes, with their reasons
    CYCLE = "/apf/cycle"  # JSON: state, decision, distances, setpoint, per cycle (plots)


def yaw_quaternion_xyzw(yaw_rad: float) -> tuple[float, float, float, float]:
    """Body FRD in local NED for heading ``yaw_rad`` (rotation about the down axis)."""
    return (0.0, 0.0, math.sin(0.5 * yaw_rad), math.cos(0.5 * yaw_rad))
