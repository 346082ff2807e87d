"""MAVLink obstacle messages to range scans and points.

Reads three messages (field names as in the MAVLink XML):

- OBSTACLE_DISTANCE (330): ``distances[72]`` [cm, uint16], ``increment`` [deg, uint8], ``increment_f``
  [deg, float, wins when non-zero], ``angle_offset`` [deg], ``min_distance``/``max_distance`` [cm],
  ``frame``, ``time_usec``.
- DISTANCE_SENSOR (132): one beam, ``current_distance``/``min_distance``/``max_distance`` [cm],
  ``orientation`` (MAV_SENSOR_ORIENTATION), ``quaternion`` for ROTATION_CUSTOM, ``time_boot_ms``.
- OBSTACLE_DISTANCE_3D (11037, ardupilotmega): one point ``x, y, z`` [m] in ``frame``,
  ``min_distance``/``max_distance`` [m].

Range classification (OBSTACLE_DISTANCE and DISTANCE_SENSOR alike but for the free limit), in this order:

===================================  ==========  =====================================================
reading (cm)                         stored as   counted as
===================================  ==========  =====================================================
UINT16_MAX (65535)                   NaN         unknown (spec: "unknown / not used")
OBSTACLE_DISTANCE: > max_distance    +inf        free (spec: max_distance + 1 = "no obstacle")
DISTANCE_SENSOR: >= max_distance     +inf        free (ArduPilot's "this face is empty", below)
0                                    NaN         invalid, unless ``zero_is_obstacle=True`` (then 0 m)
< min_distance                       NaN         invalid
otherwise                            cm / 100    valid (an obstacle)
===================================  ==========  =====================================================

ArduPilot drops 0 (AP_Proximity_MAV), so 0 is invalid by default although the spec calls it "touching".

A DISTANCE_SENSOR reading of exactly ``max_distance`` is free, not an obstacle at the limit: ArduPilot's proximity
library reports a face that was valid and is now empty that way. ``GCS_Common.cpp`` ``send_proximity`` sends
``dist_array.distance[i]`` with ``max_distance = distance_max_m() * 100`` for every face ever valid, and
``AP_Proximity_Boundary_3D::get_layer_distances`` (called by ``AP_Proximity::get_horizontal_distances``) fills an
invalid face with that same ``distance_max``; so a face emptied in flight (ids 10-17, e.g. id 12 with
``current_distance = max_distance = 500``) would otherwise stay a phantom obstacle at the sensor's full range.
Rangefinders that saturate report their maximum for "nothing seen" too.
Malformed messages raise ``ProtocolError`` (the caller counts them) and never produce a scan.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from typing import Protocol

import numpy as np
import numpy.typing as npt
from pymavlink.dialects.v20 import ardupilotmega as mavlink

from apf_companion.errors import ProtocolError
from apf_companion.perception.types import FloatArray, Pose, RangeScan, ScanFrame, SectorCounts

__all__ = [
    "BODY_FRAMES",
    "MAV_FRAME_GLOBAL",
    "MAX_OBSTACLE_DISTANCE_ELEMENTS",
    "NORTH_ALIGNED_FRAMES",
    "UINT16_MAX",
    "DistanceSensorLike",
    "ObstacleDistance3dLike",
    "ObstacleDistanceLike",
    "obstacle_distance_element_count",
    "points_from_obstacle_distance_3d",
    "scan_from_distance_sensor",
    "scan_from_obstacle_distance",
    "wrap_angle_rad",
]

UINT16_MAX = 65535
MAX_OBSTACLE_DISTANCE_ELEMENTS = 72

# MAV_FRAME values.
MAV_FRAME_GLOBAL: int = mavlink.MAV_FRAME_GLOBAL  # 0: north-aligned per the spec; what ArduPilot scripts send
_MAV_FRAME_LOCAL_NED: int = mavlink.MAV_FRAME_LOCAL_NED
_MAV_FRAME_GLOBAL_RELATIVE_ALT: int = mavlink.MAV_FRAME_GLOBAL_RELATIVE_ALT
_MAV_FRAME_GLOBAL_INT: int = mavlink.MAV_FRAME_GLOBAL_INT
_MAV_FRAME_GLOBAL_RELATIVE_ALT_INT: int = mavlink.MAV_FRAME_GLOBAL_RELATIVE_ALT_INT
_MAV_FRAME_LOCAL_OFFSET_NED: int = mavlink.MAV_FRAME_LOCAL_OFFSET_NED
_MAV_FRAME_GLOBAL_TERRAIN_ALT: int = mavlink.MAV_FRAME_GLOBAL_TERRAIN_ALT
_MAV_FRAME_GLOBAL_TERRAIN_ALT_INT: int = mavlink.MAV_FRAME_GLOBAL_TERRAIN_ALT_INT
_MAV_FRAME_BODY_FRD: int = mavlink.MAV_FRAME_BODY_FRD

NORTH_ALIGNED_FRAMES = frozenset(
    {
        MAV_FRAME_GLOBAL,
        _MAV_FRAME_LOCAL_NED,
        _MAV_FRAME_GLOBAL_RELATIVE_ALT,
        _MAV_FRAME_GLOBAL_INT,
        _MAV_FRAME_GLOBAL_RELATIVE_ALT_INT,
        _MAV_FRAME_GLOBAL_TERRAIN_ALT,
        _MAV_FRAME_GLOBAL_TERRAIN_ALT_INT,
    }
)
"""OBSTACLE_DISTANCE frames whose index 0 is north (+ angle_offset), as PX4 reads them."""

# LOCAL_FRD (20) is not one: it is earth-fixed ("origin fixed relative to earth"), and PX4 reads it as a frame of
# arbitrary heading (mavlink_receiver.cpp handle_message_odometry: LOCAL_FRD -> vehicle_odometry POSE_FRAME_FRD) and
# refuses it in an OBSTACLE_DISTANCE (CollisionPrevention.cpp _addObstacleSensorData: "unsupported frame"). Reading
# it from the nose was a guess; it is refused like any other frame.
BODY_FRAMES = frozenset({_MAV_FRAME_BODY_FRD})
"""OBSTACLE_DISTANCE frames whose index 0 is the vehicle's forward direction (+ angle_offset), as PX4 reads them
(CollisionPrevention.cpp ``_addObstacleSensorData``: BODY_FRD from the nose; GLOBAL and LOCAL_NED from north)."""

# MAV_SENSOR_ORIENTATION: YAW_0 .. YAW_315 are horizontal beams at 45 deg steps; ROTATION_CUSTOM uses the
# quaternion. The other defined orientations (up, down, rolled) are not horizontal beams.
_SENSOR_ROTATION_YAW_315: int = mavlink.MAV_SENSOR_ROTATION_YAW_315
_SENSOR_ROTATION_CUSTOM: int = mavlink.MAV_SENSOR_ROTATION_CUSTOM
_SENSOR_ROTATION_LAST_DEFINED: int = mavlink.MAV_SENSOR_ROTATION_ROLL_90_PITCH_315  # 40, the last before CUSTOM
_CUSTOM_MAX_ELEVATION_RAD = math.radians(30.0)

# uint32 time_boot_ms spans 49.7 days; a time_usec beyond that is UNIX time, not time since boot.
_MAX_BOOT_MS = 0xFFFFFFFF


class ObstacleDistanceLike(Protocol):
    """The OBSTACLE_DISTANCE fields read here (a pymavlink message satisfies it)."""

    @property
    def time_usec(self) -> int: ...
    @property
    def distances(self) -> Sequence[int]: ...
    @property
    def increment(self) -> int: ...
    @property
    def min_distance(self) -> int: ...
    @property
    def max_distance(self) -> int: ...
    @property
    def increment_f(self) -> float: ...
    @property
    def angle_offset(self) -> float: ...
    @property
    def frame(self) -> int: ...


class DistanceSensorLike(Protocol):
    """The DISTANCE_SENSOR fields read here (a pymavlink message satisfies it)."""

    @property
    def time_boot_ms(self) -> int: ...
    @property
    def min_distance(self) -> int: ...
    @property
    def max_distance(self) -> int: ...
    @property
    def current_distance(self) -> int: ...
    @property
    def orientation(self) -> int: ...
    @property
    def quaternion(self) -> Sequence[float]: ...


class ObstacleDistance3dLike(Protocol):
    """The OBSTACLE_DISTANCE_3D fields read here (a pymavlink message satisfies it)."""

    @property
    def time_boot_ms(self) -> int: ...
    @property
    def frame(self) -> int: ...
    @property
    def x(self) -> float: ...
    @property
    def y(self) -> float: ...
    @property
    def z(self) -> float: ...
    @property
    def min_distance(self) -> float: ...
    @property
    def max_distance(self) -> float: ...


def wrap_angle_rad(angle_rad: FloatArray) -> FloatArray:
    """Wrap angles to [-pi, pi)."""
    return np.asarray((angle_rad + np.pi) % (2.0 * np.pi) - np.pi, dtype=np.float64)


def _classify_cm(
    distances_cm: npt.NDArray[np.int64], min_cm: int, free_from_cm: int, *, zero_is_obstacle: bool
) -> tuple[FloatArray, SectorCounts]:
    """Ranges [m] and counts for uint16 centimetre readings (table in the module docstring); readings of
    ``free_from_cm`` or more are free (OBSTACLE_DISTANCE: max_distance + 1; DISTANCE_SENSOR: max_distance)."""
    d = distances_cm
    unknown = d == UINT16_MAX
    free = ~unknown & (d >= free_from_cm)
    # 0 is below any min_distance except 0, so it is tested on its own.
    zero_bad = (d == 0) & (not zero_is_obstacle)
    zero_ok = (d == 0) & zero_is_obstacle
    invalid = ~unknown & ~free & ~zero_ok & (zero_bad | (d < min_cm))
    valid = ~(unknown | free | invalid)
    ranges_m = np.where(valid, d.astype(np.float64) / 100.0, np.nan)
    ranges_m[free] = np.inf
    counts = SectorCounts(
        valid=int(np.count_nonzero(valid)),
        free=int(np.count_nonzero(free)),
        unknown=int(np.count_nonzero(unknown)),
        invalid=int(np.count_nonzero(invalid)),
    )
    return ranges_m, counts


def _check_limits_cm(min_cm: int, max_cm: int, message: str) -> None:
    if not (0 < max_cm <= UINT16_MAX) or min_cm > max_cm or min_cm < 0:
        msg = (
            f"{message}: min_distance={min_cm} cm and max_distance={max_cm} cm must satisfy "
            "0 <= min_distance <= max_distance and 0 < max_distance"
        )
        raise ProtocolError(msg)


def _obstacle_distance_angles(msg: ObstacleDistanceLike) -> tuple[float, float]:
    """(increment, angle_offset) [deg] of an OBSTACLE_DISTANCE; ProtocolError when unusable."""
    increment_f = float(msg.increment_f)
    angle_offset_deg = float(msg.angle_offset)
    if not math.isfinite(increment_f):
        msg_text = f"OBSTACLE_DISTANCE: increment_f={increment_f} is not finite"
        raise ProtocolError(msg_text)
    if not math.isfinite(angle_offset_deg):
        msg_text = f"OBSTACLE_DISTANCE: angle_offset={angle_offset_deg} is not finite"
        raise ProtocolError(msg_text)
    increment_deg = increment_f if increment_f != 0.0 else float(msg.increment)
    if increment_deg == 0.0:
        msg_text = "OBSTACLE_DISTANCE: increment and increment_f are both 0"
        raise ProtocolError(msg_text)
    if abs(increment_deg) > 360.0:
        msg_text = f"OBSTACLE_DISTANCE: increment {increment_deg} deg is wider than a full turn"
        raise ProtocolError(msg_text)
    return increment_deg, angle_offset_deg


def _obstacle_distance_frame(frame: int, frame_override: ScanFrame | None) -> ScanFrame:
    if frame_override is not None:
        scan_frame = frame_override
    elif frame in BODY_FRAMES:
        scan_frame = ScanFrame.BODY_FRD
    elif frame in NORTH_ALIGNED_FRAMES:
        scan_frame = ScanFrame.LOCAL_NED
    else:
        msg_text = f"OBSTACLE_DISTANCE: frame={frame} is not supported (use BODY_FRD=12 or LOCAL_NED=1)"
        raise ProtocolError(msg_text)
    return scan_frame


def obstacle_distance_element_count(increment_deg: float) -> int:
    """How many OBSTACLE_DISTANCE elements ArduPilot reads for this increment: ``360 / |increment|`` rounded to
    the nearest integer (halves up), at most 72.

    ArduPilot ``libraries/AP_Proximity/AP_Proximity_MAV.cpp`` ``handle_obstacle_distance_msg``:
    ``total_distances = MIN(((360.0f / fabsf(increment)) + 0.5f), 72)``, a float stored into a uint8_t
    (truncated). Computed in float32 as there, so a ratio on a half rounds the same way.
    """
    with np.errstate(divide="ignore", over="ignore"):  # a subnormal increment is 0 in float32: inf, then 72
        ratio = np.float32(360.0) / np.abs(np.float32(increment_deg)) + np.float32(0.5)
    return int(min(ratio, np.float32(MAX_OBSTACLE_DISTANCE_ELEMENTS)))


def _obstacle_distance_elements(distances: Sequence[int], increment_deg: float) -> npt.NDArray[np.int64]:
    """The elements that are read (``obstacle_distance_element_count``) [cm]."""
    n = obstacle_distance_element_count(increment_deg)
    distances_cm = np.asarray(distances, dtype=np.int64)[:n]
    if distances_cm.size < n:
        msg_text = f"OBSTACLE_DISTANCE: {distances_cm.size} distances, expected at least {n}"
        raise ProtocolError(msg_text)
    return distances_cm


def scan_from_obstacle_distance(
    msg: ObstacleDistanceLike,
    *,
    t_s: float,
    zero_is_obstacle: bool = False,
    frame_override: ScanFrame | None = None,
    mount_yaw_rad: float = 0.0,
) -> RangeScan:
    """Read an OBSTACLE_DISTANCE message into a ``RangeScan``.

    Element ``i`` lies at bearing ``angle_offset + i * increment`` degrees, clockwise, from the frame's zero: the
    vehicle's forward axis for BODY_FRD (12), north for GLOBAL* and LOCAL_NED (1); any other frame (LOCAL_FRD 20 too:
    earth-fixed, of no stated heading) is refused. ``increment_f`` is used when non-zero, else ``increment``; a negative
    ``increment_f`` runs counter-clockwise, as the spec allows. The number of elements read is ``360 / |increment|``
    rounded (halves up), at most 72, as ArduPilot reads them (``obstacle_distance_element_count``); later elements are
    not used and not counted.
    The scan's ``time_boot_ms`` is ``time_usec // 1000`` when that fits a uint32 (time since boot), else None.

    Parameters
    ----------
    msg:
        The message (pymavlink ``MAVLink_obstacle_distance_message`` or anything with those fields).
    t_s:
        Measurement time on the service's monotonic clock [s].
    zero_is_obstacle:
        Treat a 0 cm reading as an obstacle touching the sensor (the spec's meaning) instead of invalid.
    frame_override:
        Use this frame whatever ``frame`` says. ``ScanFrame.BODY_FRD`` reproduces ArduPilot, which ignores
        ``frame``, for senders known to fill it wrongly (e.g. sensor scripts written for ArduPilot, or older
        mavros, sending 0 for a body-mounted sensor). The service sets it from ``sensors.obstacle_distance_frame``.
    mount_yaw_rad:
        Added to every bearing when the scan is read from the nose (BODY_FRD): the sensor's forward axis,
        clockwise from the vehicle's nose, as ArduPilot's PRX1_YAW_CORR (``AP_Proximity_MAV.cpp``:
        ``yaw_correction = wrap_360(param_yaw_offset + angle_offset)``). Not applied to north-aligned frames.
        The service sets it from ``sensors.obstacle_distance_mount_yaw_deg``.

    Raises
    ------
    ProtocolError
        ``increment`` and ``increment_f`` both 0; ``|increment|`` > 360; ``increment_f`` or ``angle_offset`` not finite;
        ``min_distance > max_distance``; ``max_distance`` 0; an unsupported ``frame`` (unless
        ``frame_override`` is given).
    """
    increment_deg, angle_offset_deg = _obstacle_distance_angles(msg)
    scan_frame = _obstacle_distance_frame(int(msg.frame), frame_override)
    min_cm, max_cm = int(msg.min_distance), int(msg.max_distance)
    _check_limits_cm(min_cm, max_cm, "OBSTACLE_DISTANCE")

    distances_cm = _obstacle_distance_elements(msg.distances, increment_deg)
    n = distances_cm.size
    ranges_m, counts = _classify_cm(distances_cm, min_cm, max_cm + 1, zero_is_obstacle=zero_is_obstacle)
    yaw_rad = mount_yaw_rad if scan_frame is ScanFrame.BODY_FRD else 0.0  # a north-aligned scan has no mount
    degrees = angle_offset_deg + increment_deg * np.arange(n, dtype=np.float64)
    bearings_rad = wrap_angle_rad(np.deg2rad(degrees) + yaw_rad)
    time_ms = int(msg.time_usec) // 1000
    return RangeScan(
        t_s=t_s,
        frame=scan_frame,
        bearings_rad=bearings_rad,
        ranges_m=ranges_m,
        range_min_m=min_cm / 100.0,
        range_max_m=max_cm / 100.0,
        time_boot_ms=time_ms if 0 <= time_ms <= _MAX_BOOT_MS else None,
        counts=counts,
        source="mavlink:obstacle_distance",
    )


def _custom_bearing_rad(quaternion: Sequence[float]) -> float | None:
    """Bearing (FRD, clockwise from forward) of a sensor's x axis rotated by ``quaternion`` (w, x, y, z).

    Returns None when the beam points more than 30 deg above or below the horizontal plane.
    """
    q = np.asarray(quaternion, dtype=np.float64)
    norm = float(np.linalg.norm(q)) if q.shape == (4,) else 0.0
    if not math.isfinite(norm) or norm < 1e-6:
        msg = f"DISTANCE_SENSOR: ROTATION_CUSTOM needs a valid quaternion, got {list(q)}"
        raise ProtocolError(msg)
    w, x, y, z = q / norm
    # First column of the rotation matrix: where the sensor's x axis points in body FRD.
    fx = 1.0 - 2.0 * (y * y + z * z)
    fy = 2.0 * (x * y + w * z)
    fz = 2.0 * (x * z - w * y)
    if abs(math.atan2(fz, math.hypot(fx, fy))) > _CUSTOM_MAX_ELEVATION_RAD:
        return None
    # FRD: y is right, so atan2(y, x) is clockwise from forward.
    return math.atan2(fy, fx)


def scan_from_distance_sensor(msg: DistanceSensorLike, *, t_s: float, zero_is_obstacle: bool = False) -> RangeScan:
    """Read a DISTANCE_SENSOR message into a one-beam BODY_FRD ``RangeScan``.

    ``orientation`` YAW_0 .. YAW_315 (0..7) gives bearing ``orientation * 45`` deg clockwise from forward.
    ROTATION_CUSTOM (100) takes the bearing of the sensor's x axis rotated by ``quaternion`` when that beam is
    within 30 deg of horizontal. Every other defined orientation (PITCH_90 up, PITCH_270 down, rolled
    mounts) is not a horizontal beam: the result is an EMPTY scan (length 0, all counts 0), not an error,
    because a downward rangefinder on the link is normal. Readings are classified as in the module table: a
    ``current_distance`` of ``max_distance`` or more is free out to ``max_distance`` (ArduPilot reports an emptied
    proximity face so), not an obstacle.

    Raises
    ------
    ProtocolError
        ``orientation`` not a defined MAV_SENSOR_ORIENTATION; ROTATION_CUSTOM with a zero or non-finite
        quaternion; bad ``min_distance``/``max_distance``.
    """
    orientation = int(msg.orientation)
    min_cm, max_cm = int(msg.min_distance), int(msg.max_distance)
    if orientation <= _SENSOR_ROTATION_YAW_315:
        bearing_rad: float | None = math.radians(45.0 * orientation)
    elif orientation == _SENSOR_ROTATION_CUSTOM:
        bearing_rad = _custom_bearing_rad(msg.quaternion)
    elif orientation <= _SENSOR_ROTATION_LAST_DEFINED:
        bearing_rad = None
    else:
        text = f"DISTANCE_SENSOR: orientation={orientation} is not a MAV_SENSOR_ORIENTATION"
        raise ProtocolError(text)
    _check_limits_cm(min_cm, max_cm, "DISTANCE_SENSOR")
    time_boot_ms = int(msg.time_boot_ms)
    if bearing_rad is None:
        return RangeScan(
            t_s=t_s,
            frame=ScanFrame.BODY_FRD,
            bearings_rad=np.empty(0),
            ranges_m=np.empty(0),
            range_min_m=min_cm / 100.0,
            range_max_m=max_cm / 100.0,
            time_boot_ms=time_boot_ms,
            source="mavlink:distance_sensor",
        )
    ranges_m, counts = _classify_cm(
        np.array([int(msg.current_distance)], dtype=np.int64), min_cm, max_cm, zero_is_obstacle=zero_is_obstacle
    )  # free from max_distance itself: ArduPilot's emptied proximity face (module docstring)
    return RangeScan(
        t_s=t_s,
        frame=ScanFrame.BODY_FRD,
        bearings_rad=wrap_angle_rad(np.array([bearing_rad])),
        ranges_m=ranges_m,
        range_min_m=min_cm / 100.0,
        range_max_m=max_cm / 100.0,
        time_boot_ms=time_boot_ms,
        counts=counts,
        source="mavlink:distance_sensor",
    )


def points_from_obstacle_distance_3d(msg: ObstacleDistance3dLike, pose: Pose) -> FloatArray:
    """Place an OBSTACLE_DISTANCE_3D point in local NED.

    Frames: BODY_FRD (12): ``(x, y, z)`` is forward/right/down from the vehicle; it is rotated by the yaw of
    ``pose`` (roll and pitch are ignored: the companion only tracks yaw) and added to its position.
    LOCAL_NED (1): ``(x, y, z)`` is the obstacle's position in local NED, used as is. LOCAL_OFFSET_NED (7):
    a north-aligned offset from the vehicle. ``pose`` should be the pose at ``time_boot_ms``.

    A point whose distance from the vehicle (the norm of the offset; for LOCAL_NED, from ``pose``) lies
    outside ``[min_distance, max_distance]`` is dropped, as ArduPilot does.

    Returns
    -------
    (K, 3) float64, K in {0, 1}.

    Raises
    ------
    ProtocolError
        Non-finite coordinates or limits, ``min_distance > max_distance``, an unsupported ``frame``.
    """
    xyz = np.array([msg.x, msg.y, msg.z], dtype=np.float64)
    min_m, max_m = float(msg.min_distance), float(msg.max_distance)
    if not np.all(np.isfinite(xyz)):
        text = f"OBSTACLE_DISTANCE_3D: x, y, z must be finite, got {list(xyz)}"
        raise ProtocolError(text)
    if not (math.isfinite(min_m) and math.isfinite(max_m) and 0.0 <= min_m <= max_m):
        text = f"OBSTACLE_DISTANCE_3D: need 0 <= min_distance <= max_distance, got {min_m} and {max_m}"
        raise ProtocolError(text)
    frame = int(msg.frame)
    if frame == _MAV_FRAME_BODY_FRD:
        c, s = math.cos(pose.yaw_rad), math.sin(pose.yaw_rad)
        offset = np.array([c * xyz[0] - s * xyz[1], s * xyz[0] + c * xyz[1], xyz[2]])
    elif frame == _MAV_FRAME_LOCAL_OFFSET_NED:
        offset = xyz
    elif frame == _MAV_FRAME_LOCAL_NED:
        offset = xyz - pose.pos_ned_m
    else:
        text = f"OBSTACLE_DISTANCE_3D: frame={frame} is not supported (BODY_FRD=12, LOCAL_NED=1, 7)"
        raise ProtocolError(text)
    dist_m = float(np.linalg.norm(offset))
    if not min_m <= dist_m <= max_m:
        return np.empty((0, 3), dtype=np.float64)
    return np.asarray((pose.pos_ned_m + offset)[None, :], dtype=np.float64)
