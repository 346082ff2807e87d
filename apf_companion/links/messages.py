"""Typed records of the MAVLink messages the service consumes, decoded once where messages enter the service.

``decode(msg)`` turns a pymavlink message into one of the frozen records below (looked up by message type in
``DECODERS``), so no pymavlink ``Any`` travels further. It never raises: a message type the service does not
consume gives None, and so does a consumed message whose fields cannot be read (the caller tells the two apart
with ``DECODERS``: a consumed type that decodes to None is malformed, and counted). Float fields are passed on
as they are, NaN and inf included: deciding what a non-finite value means (a bad pose, a malformed scan) is the
consumer's job, where it is counted.

Field names and units follow the MAVLink XML (common.xml, ardupilotmega.xml for OBSTACLE_DISTANCE_3D).
"""

from __future__ import annotations

import struct
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

from pymavlink.dialects.v20 import ardupilotmega as mavlink

__all__ = [
    "DECODERS",
    "Attitude",
    "CommandAck",
    "CommandInt",
    "CommandLong",
    "DistanceSensor",
    "EkfStatusReport",
    "FenceRecord",
    "GlobalPositionInt",
    "Heartbeat",
    "HomePosition",
    "LocalPositionNed",
    "MissionAck",
    "MissionCount",
    "MissionCurrent",
    "MissionItemInt",
    "MissionRecord",
    "ObstacleDistance",
    "ObstacleDistance3d",
    "Odometry",
    "ParamRequestList",
    "ParamRequestRead",
    "ParamSet",
    "ParamValue",
    "PositionTargetGlobalInt",
    "PositionTargetLocalNed",
    "Record",
    "Source",
    "SysStatus",
    "decode",
    "source",
]


@dataclass(frozen=True, slots=True)
class Source:
    """Who sent a message: MAVLink system and component id."""

    system: int
    component: int


@dataclass(frozen=True, slots=True, kw_only=True)
class Heartbeat:
    src: Source
    type: int  # MAV_TYPE
    autopilot: int  # MAV_AUTOPILOT
    base_mode: int  # MAV_MODE_FLAG bits
    custom_mode: int
    system_status: int  # MAV_STATE


@dataclass(frozen=True, slots=True, kw_only=True)
class LocalPositionNed:
    src: Source
    time_boot_ms: int
    x: float  # north [m], local NED
    y: float  # east [m]
    z: float  # down [m]
    vx: float  # [m/s]
    vy: float
    vz: float


@dataclass(frozen=True, slots=True, kw_only=True)
class Attitude:
    src: Source
    time_boot_ms: int
    roll: float  # [rad]
    pitch: float
    yaw: float  # [rad], 0 = north, clockwise positive
    pitchspeed: float = 0.0  # body rates [rad/s], FRD (the autopilots send gyro rates, not Euler rates)
    yawspeed: float = 0.0


@dataclass(frozen=True, slots=True, kw_only=True)
class Odometry:
    """Only what the pose gate uses: the estimator's reset counter (uint8, wraps)."""

    src: Source
    time_usec: int
    reset_counter: int


@dataclass(frozen=True, slots=True, kw_only=True)
class GlobalPositionInt:
    src: Source
    time_boot_ms: int
    lat: int  # [degE7]
    lon: int  # [degE7]
    alt: int  # AMSL [mm]
    relative_alt: int  # above home [mm]


@dataclass(frozen=True, slots=True, kw_only=True)
class HomePosition:
    """The autopilot's home (the fence's circle is centred on it)."""

    src: Source
    latitude: int  # [degE7]
    longitude: int  # [degE7]
    altitude: int  # AMSL [mm]


@dataclass(frozen=True, slots=True, kw_only=True)
class ObstacleDistance:
    src: Source
    time_usec: int
    distances: tuple[int, ...]  # [cm]
    increment: int  # [deg]
    min_distance: int  # [cm]
    max_distance: int  # [cm]
    increment_f: float  # [deg], wins when non-zero
    angle_offset: float  # [deg]
    frame: int  # MAV_FRAME


@dataclass(frozen=True, slots=True, kw_only=True)
class DistanceSensor:
    src: Source
    time_boot_ms: int
    min_distance: int  # [cm]
    max_distance: int  # [cm]
    current_distance: int  # [cm]
    orientation: int  # MAV_SENSOR_ORIENTATION
    quaternion: tuple[float, ...]  # (w, x, y, z) for MAV_SENSOR_ROTATION_CUSTOM
    sensor_id: int = 0  # DISTANCE_SENSOR.id (ArduPilot's proximity sectors: 10-17)


@dataclass(frozen=True, slots=True, kw_only=True)
class ObstacleDistance3d:
    src: Source
    time_boot_ms: int
    frame: int  # MAV_FRAME
    x: float  # [m]
    y: float
    z: float
    min_distance: float  # [m]
    max_distance: float  # [m]


@dataclass(frozen=True, slots=True, kw_only=True)
class CommandLong:
    src: Source
    target_system: int
    target_component: int
    command: int  # MAV_CMD
    params: tuple[float, float, float, float, float, float, float]


@dataclass(frozen=True, slots=True, kw_only=True)
class CommandInt:
    src: Source
    target_system: int
    target_component: int
    frame: int  # MAV_FRAME
    command: int  # MAV_CMD
    params: tuple[float, float, float, float]  # param1..param4
    x: int  # latitude [degE7] or local x
    y: int
    z: float


@dataclass(frozen=True, slots=True, kw_only=True)
class CommandAck:
    src: Source
    command: int  # MAV_CMD
    result: int  # MAV_RESULT
    target_system: int  # 0 when the sender did not fill it (MAVLink 1 extension field)
    target_component: int


@dataclass(frozen=True, slots=True, kw_only=True)
class EkfStatusReport:
    src: Source
    flags: int  # EKF_STATUS_FLAGS bits (ardupilotmega.xml)


@dataclass(frozen=True, slots=True, kw_only=True)
class ParamRequestList:
    src: Source
    target_system: int
    target_component: int


@dataclass(frozen=True, slots=True, kw_only=True)
class ParamRequestRead:
    src: Source
    target_system: int
    target_component: int
    param_id: str  # NUL padding stripped
    param_index: int  # -1: look up by param_id


@dataclass(frozen=True, slots=True, kw_only=True)
class ParamSet:
    src: Source
    target_system: int
    target_component: int
    param_id: str
    param_value: float  # float32 on the wire; integers are cast (ArduPilot's encoding, not byte-wise)
    param_type: int  # MAV_PARAM_TYPE


@dataclass(frozen=True, slots=True, kw_only=True)
class SysStatus:
    """Only the onboard sensors' bitmasks (MAV_SYS_STATUS_SENSOR): the fence reader reads GEOFENCE's."""

    src: Source
    present: int  # onboard_control_sensors_present
    enabled: int  # onboard_control_sensors_enabled
    health: int  # onboard_control_sensors_health


@dataclass(frozen=True, slots=True, kw_only=True)
class ParamValue:
    """One of the autopilot's parameters (the service reads its fence parameters: apf_companion.fencelimits)."""

    src: Source
    param_id: str
    param_value: float  # float32 on the wire: ArduPilot casts integers, PX4 sends their bytes (param_type says)
    param_type: int  # MAV_PARAM_TYPE


@dataclass(frozen=True, slots=True, kw_only=True)
class MissionCount:
    """The mission protocol's item count (the service reads the fence: mission_type MAV_MISSION_TYPE_FENCE)."""

    src: Source
    target_system: int
    target_component: int
    count: int
    mission_type: int  # MAV_MISSION_TYPE
    opaque_id: int = 0  # the plan's id (MAVLink 2 extension; 0: not sent, or no plan): as MISSION_CURRENT's


@dataclass(frozen=True, slots=True, kw_only=True)
class MissionCurrent:
    """Only the fence plan's id: 0 when there is no fence or the autopilot sends no ids (ArduPilot 4.6), else a
    value that changes whenever the fence does (PX4: the CRC32 of its items, ``mavlink_mission.cpp``, 1 Hz on
    every link)."""

    src: Source
    fence_id: int


@dataclass(frozen=True, slots=True, kw_only=True)
class MissionItemInt:
    """One mission item; for a fence item x/y are latitude/longitude [1e-7 deg] and param1 a vertex count or a
    radius [m] (MAV_CMD_NAV_FENCE_*)."""

    src: Source
    target_system: int
    target_component: int
    seq: int
    frame: int  # MAV_FRAME
    command: int  # MAV_CMD
    param1: float
    x: int
    y: int
    mission_type: int  # MAV_MISSION_TYPE


@dataclass(frozen=True, slots=True, kw_only=True)
class MissionAck:
    src: Source
    target_system: int
    target_component: int
    type: int  # MAV_MISSION_RESULT
    mission_type: int  # MAV_MISSION_TYPE


@dataclass(frozen=True, slots=True, kw_only=True)
class PositionTargetLocalNed:
    """The autopilot's current guided target (its echo of SET_POSITION_TARGET_*, or a GCS's "fly here")."""

    src: Source
    time_boot_ms: int
    coordinate_frame: int  # MAV_FRAME
    type_mask: int  # POSITION_TARGET_TYPEMASK ignore bits
    x: float  # north [m], local NED
    y: float  # east [m]
    z: float  # down [m]


@dataclass(frozen=True, slots=True, kw_only=True)
class PositionTargetGlobalInt:
    src: Source
    time_boot_ms: int
    coordinate_frame: int  # MAV_FRAME (GLOBAL_INT, GLOBAL_RELATIVE_ALT_INT, GLOBAL_TERRAIN_ALT_INT)
    type_mask: int
    lat_int: int  # [degE7]
    lon_int: int  # [degE7]
    alt: float  # [m], meaning set by the frame


Record = (
    Heartbeat
    | LocalPositionNed
    | Attitude
    | GlobalPositionInt
    | HomePosition
    | ObstacleDistance
    | DistanceSensor
    | ObstacleDistance3d
    | Odometry
    | CommandLong
    | CommandInt
    | CommandAck
    | EkfStatusReport
    | ParamRequestList
    | ParamRequestRead
    | ParamSet
    | ParamValue
    | SysStatus
    | PositionTargetLocalNed
    | PositionTargetGlobalInt
    | MissionCount
    | MissionCurrent
    | MissionItemInt
    | MissionAck
)


#: The mission protocol's answers the service reads (the fence download).
MissionRecord = MissionCount | MissionItemInt | MissionAck
#: What the fence reader takes from the autopilot: the download's answers, its parameters, its home.
FenceRecord = MissionCount | MissionCurrent | MissionItemInt | MissionAck | ParamValue | HomePosition | SysStatus


_V2_HEADER_LEN = 10  # MAVLink 2: magic, len, incompat, compat, seq, sysid, compid, msgid (3 bytes)
# Payload offsets of extension fields (common.xml: extensions follow the size-sorted base fields in declared order).
# MISSION_COUNT: count u16, target_system u8, target_component u8, mission_type u8, opaque_id u32.
_COUNT_OPAQUE_ID = 5
# MISSION_CURRENT: seq u16, total u16, mission_state u8, mission_mode u8, mission_id u32, fence_id u32, rally u32.
_CURRENT_FENCE_ID = 10


def _src(msg: Any) -> Source:
    return Source(int(msg.get_srcSystem()), int(msg.get_srcComponent()))


def _heartbeat(msg: Any) -> Heartbeat:
    return Heartbeat(
        src=_src(msg),
        type=int(msg.type),
        autopilot=int(msg.autopilot),
        base_mode=int(msg.base_mode),
        custom_mode=int(msg.custom_mode),
        system_status=int(msg.system_status),
    )


def _local_position_ned(msg: Any) -> LocalPositionNed:
    return LocalPositionNed(
        src=_src(msg),
        time_boot_ms=int(msg.time_boot_ms),
        x=float(msg.x),
        y=float(msg.y),
        z=float(msg.z),
        vx=float(msg.vx),
        vy=float(msg.vy),
        vz=float(msg.vz),
    )


def _attitude(msg: Any) -> Attitude:
    return Attitude(
        src=_src(msg),
        time_boot_ms=int(msg.time_boot_ms),
        roll=float(msg.roll),
        pitch=float(msg.pitch),
        yaw=float(msg.yaw),
        pitchspeed=float(msg.pitchspeed),
        yawspeed=float(msg.yawspeed),
    )


def _odometry(msg: Any) -> Odometry:
    return Odometry(src=_src(msg), time_usec=int(msg.time_usec), reset_counter=int(msg.reset_counter))


def _global_position_int(msg: Any) -> GlobalPositionInt:
    return GlobalPositionInt(
        src=_src(msg),
        time_boot_ms=int(msg.time_boot_ms),
        lat=int(msg.lat),
        lon=int(msg.lon),
        alt=int(msg.alt),
        relative_alt=int(msg.relative_alt),
    )


def _obstacle_distance(msg: Any) -> ObstacleDistance:
    return ObstacleDistance(
        src=_src(msg),
        time_usec=int(msg.time_usec),
        distances=tuple(int(d) for d in msg.distances),
        increment=int(msg.increment),
        min_distance=int(msg.min_distance),
        max_distance=int(msg.max_distance),
        increment_f=float(msg.increment_f),
        angle_offset=float(msg.angle_offset),
        frame=int(msg.frame),
    )


def _distance_sensor(msg: Any) -> DistanceSensor:
    return DistanceSensor(
        src=_src(msg),
        time_boot_ms=int(msg.time_boot_ms),
        min_distance=int(msg.min_distance),
        max_distance=int(msg.max_distance),
        current_distance=int(msg.current_distance),
        orientation=int(msg.orientation),
        quaternion=tuple(float(q) for q in msg.quaternion),
        sensor_id=int(msg.id),
    )


def _obstacle_distance_3d(msg: Any) -> ObstacleDistance3d:
    return ObstacleDistance3d(
        src=_src(msg),
        time_boot_ms=int(msg.time_boot_ms),
        frame=int(msg.frame),
        x=float(msg.x),
        y=float(msg.y),
        z=float(msg.z),
        min_distance=float(msg.min_distance),
        max_distance=float(msg.max_distance),
    )


def _command_long(msg: Any) -> CommandLong:
    p = (msg.param1, msg.param2, msg.param3, msg.param4, msg.param5, msg.param6, msg.param7)
    return CommandLong(
        src=_src(msg),
        target_system=int(msg.target_system),
        target_component=int(msg.target_component),
        command=int(msg.command),
        params=(float(p[0]), float(p[1]), float(p[2]), float(p[3]), float(p[4]), float(p[5]), float(p[6])),
    )


def _command_int(msg: Any) -> CommandInt:
    return CommandInt(
        src=_src(msg),
        target_system=int(msg.target_system),
        target_component=int(msg.target_component),
        frame=int(msg.frame),
        command=int(msg.command),
        params=(float(msg.param1), float(msg.param2), float(msg.param3), float(msg.param4)),
        x=int(msg.x),
        y=int(msg.y),
        z=float(msg.z),
    )


def _command_ack(msg: Any) -> CommandAck:
    return CommandAck(
        src=_src(msg),
        command=int(msg.command),
        result=int(msg.result),
        target_system=int(getattr(msg, "target_system", 0) or 0),
        target_component=int(getattr(msg, "target_component", 0) or 0),
    )


def _ekf_status_report(msg: Any) -> EkfStatusReport:
    return EkfStatusReport(src=_src(msg), flags=int(msg.flags))


def _param_id(raw: Any) -> str:
    if isinstance(raw, bytes):
        raw = raw.decode("ascii", "replace")
    return str(raw).split("\x00", 1)[0]


def _param_request_list(msg: Any) -> ParamRequestList:
    return ParamRequestList(
        src=_src(msg), target_system=int(msg.target_system), target_component=int(msg.target_component)
    )


def _param_request_read(msg: Any) -> ParamRequestRead:
    return ParamRequestRead(
        src=_src(msg),
        target_system=int(msg.target_system),
        target_component=int(msg.target_component),
        param_id=_param_id(msg.param_id),
        param_index=int(msg.param_index),
    )


def _param_set(msg: Any) -> ParamSet:
    return ParamSet(
        src=_src(msg),
        target_system=int(msg.target_system),
        target_component=int(msg.target_component),
        param_id=_param_id(msg.param_id),
        param_value=float(msg.param_value),
        param_type=int(msg.param_type),
    )


def _param_value(msg: Any) -> ParamValue:
    return ParamValue(
        src=_src(msg),
        param_id=_param_id(msg.param_id),
        param_value=float(msg.param_value),
        param_type=int(msg.param_type),
    )


def _sys_status(msg: Any) -> SysStatus:
    return SysStatus(
        src=_src(msg),
        present=int(msg.onboard_control_sensors_present),
        enabled=int(msg.onboard_control_sensors_enabled),
        health=int(msg.onboard_control_sensors_health),
    )


def _home_position(msg: Any) -> HomePosition:
    return HomePosition(
        src=_src(msg), latitude=int(msg.latitude), longitude=int(msg.longitude), altitude=int(msg.altitude)
    )


def _position_target_local_ned(msg: Any) -> PositionTargetLocalNed:
    return PositionTargetLocalNed(
        src=_src(msg),
        time_boot_ms=int(msg.time_boot_ms),
        coordinate_frame=int(msg.coordinate_frame),
        type_mask=int(msg.type_mask),
        x=float(msg.x),
        y=float(msg.y),
        z=float(msg.z),
    )


def _position_target_global_int(msg: Any) -> PositionTargetGlobalInt:
    return PositionTargetGlobalInt(
        src=_src(msg),
        time_boot_ms=int(msg.time_boot_ms),
        coordinate_frame=int(msg.coordinate_frame),
        type_mask=int(msg.type_mask),
        lat_int=int(msg.lat_int),
        lon_int=int(msg.lon_int),
        alt=float(msg.alt),
    )


def _extension_u32(msg: Any, name: str, offset: int) -> int:
    """The uint32 MAVLink 2 extension field ``name`` at payload ``offset``: from the frame where pymavlink's dialect
    (2.4.50) predates the field (mavlink/mavlink#2012's plan ids). MAVLink 2 trims a payload's trailing zero bytes,
    so bytes beyond its end are 0; a MAVLink 1 frame has no extensions (0)."""
    value = getattr(msg, name, None)
    if value is not None:  # a newer dialect has decoded it
        return int(value)
    frame = bytes(msg.get_msgbuf())
    if len(frame) < _V2_HEADER_LEN or frame[0] != mavlink.PROTOCOL_MARKER_V2:
        return 0
    payload = frame[_V2_HEADER_LEN : _V2_HEADER_LEN + frame[1]]
    return int(struct.unpack_from("<I", payload[offset : offset + 4].ljust(4, b"\0"))[0])


def _mission_count(msg: Any) -> MissionCount:
    return MissionCount(
        src=_src(msg),
        target_system=int(msg.target_system),
        target_component=int(msg.target_component),
        count=int(msg.count),
        mission_type=int(getattr(msg, "mission_type", 0)),  # a MAVLink 2 extension: 0 (MISSION) when absent
        opaque_id=_extension_u32(msg, "opaque_id", _COUNT_OPAQUE_ID),
    )


def _mission_current(msg: Any) -> MissionCurrent:
    return MissionCurrent(src=_src(msg), fence_id=_extension_u32(msg, "fence_id", _CURRENT_FENCE_ID))


def _mission_item_int(msg: Any) -> MissionItemInt:
    return MissionItemInt(
        src=_src(msg),
        target_system=int(msg.target_system),
        target_component=int(msg.target_component),
        seq=int(msg.seq),
        frame=int(msg.frame),
        command=int(msg.command),
        param1=float(msg.param1),
        x=int(msg.x),
        y=int(msg.y),
        mission_type=int(getattr(msg, "mission_type", 0)),
    )


def _mission_ack(msg: Any) -> MissionAck:
    return MissionAck(
        src=_src(msg),
        target_system=int(msg.target_system),
        target_component=int(msg.target_component),
        type=int(msg.type),
        mission_type=int(getattr(msg, "mission_type", 0)),
    )


DECODERS: dict[str, Callable[[Any], Record]] = {
    "HEARTBEAT": _heartbeat,
    "LOCAL_POSITION_NED": _local_position_ned,
    "ATTITUDE": _attitude,
    "GLOBAL_POSITION_INT": _global_position_int,
    "OBSTACLE_DISTANCE": _obstacle_distance,
    "DISTANCE_SENSOR": _distance_sensor,
    "OBSTACLE_DISTANCE_3D": _obstacle_distance_3d,
    "ODOMETRY": _odometry,
    "COMMAND_LONG": _command_long,
    "COMMAND_INT": _command_int,
    "COMMAND_ACK": _command_ack,
    "EKF_STATUS_REPORT": _ekf_status_report,
    "PARAM_REQUEST_LIST": _param_request_list,
    "PARAM_REQUEST_READ": _param_request_read,
    "PARAM_SET": _param_set,
    "PARAM_VALUE": _param_value,
    "HOME_POSITION": _home_position,
    "SYS_STATUS": _sys_status,
    "POSITION_TARGET_LOCAL_NED": _position_target_local_ned,
    "POSITION_TARGET_GLOBAL_INT": _position_target_global_int,
    "MISSION_COUNT": _mission_count,
    "MISSION_CURRENT": _mission_current,
    "MISSION_ITEM_INT": _mission_item_int,
    "MISSION_ACK": _mission_ack,
}
"""Message type name -> decoder, for every message the service consumes."""


def decode(msg: Any) -> Record | None:
    """The typed record of ``msg``; None for a type the service does not consume or unreadable fields."""
    try:
        decoder = DECODERS.get(msg.get_type())
        return None if decoder is None else decoder(msg)
    except (AttributeError, TypeError, ValueError, OverflowError):
        return None


def source(msg: Any) -> Source | None:
    """The sender of any pymavlink message (consumed or not); None if it cannot be read."""
    try:
        return _src(msg)
    except (AttributeError, TypeError, ValueError):
        return None
