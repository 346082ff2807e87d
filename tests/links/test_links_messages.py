"""The decode table: every consumed MAVLink message becomes a typed record, off the wire, and nothing raises."""

from __future__ import annotations

import dataclasses
import math
from typing import Any

import pytest
from pymavlink.dialects.v20 import ardupilotmega as mavlink

from apf_companion.links.messages import (
    DECODERS,
    Attitude,
    CommandAck,
    CommandInt,
    CommandLong,
    DistanceSensor,
    EkfStatusReport,
    GlobalPositionInt,
    Heartbeat,
    HomePosition,
    LocalPositionNed,
    MissionAck,
    MissionCount,
    MissionCurrent,
    MissionItemInt,
    ObstacleDistance,
    ObstacleDistance3d,
    Odometry,
    ParamRequestList,
    ParamRequestRead,
    ParamSet,
    ParamValue,
    PositionTargetGlobalInt,
    PositionTargetLocalNed,
    Source,
    SysStatus,
    decode,
    source,
)
from sim.vehicle.missionwire import MissionCountWithId, MissionCurrentWithIds

NAN = math.nan


def _wire(build: Any, src: tuple[int, int] = (1, 1)) -> Any:
    """Encode with pymavlink, pack and parse again: exactly what the service gets off the link."""
    tx = mavlink.MAVLink(None, srcSystem=src[0], srcComponent=src[1])
    rx = mavlink.MAVLink(None)
    rx.robust_parsing = True
    parsed = rx.parse_buffer(build(tx).pack(tx))
    assert parsed is not None and len(parsed) == 1
    return parsed[0]


CASES: list[tuple[str, Any, type[Any], dict[str, Any]]] = [
    (
        "HEARTBEAT",
        lambda m: m.heartbeat_encode(mavlink.MAV_TYPE_QUADROTOR, mavlink.MAV_AUTOPILOT_ARDUPILOTMEGA, 129, 4, 4),
        Heartbeat,
        {"type": mavlink.MAV_TYPE_QUADROTOR, "base_mode": 129, "custom_mode": 4, "system_status": 4},
    ),
    (
        "LOCAL_POSITION_NED",
        lambda m: m.local_position_ned_encode(1234, 1.5, -2.0, -5.0, 0.5, 0.0, 0.1),
        LocalPositionNed,
        {"time_boot_ms": 1234, "x": 1.5, "y": -2.0, "z": -5.0, "vx": 0.5},
    ),
    ("ATTITUDE", lambda m: m.attitude_encode(77, 0.1, 0.2, 1.5, 0, 0, 0), Attitude, {"time_boot_ms": 77}),
    (
        "GLOBAL_POSITION_INT",
        lambda m: m.global_position_int_encode(5, -353632621, 1491652374, 584000, 5000, 0, 0, 0, 0),
        GlobalPositionInt,
        {"lat": -353632621, "lon": 1491652374, "alt": 584000, "relative_alt": 5000},
    ),
    (
        "OBSTACLE_DISTANCE",
        lambda m: m.obstacle_distance_encode(
            9_000_000, 0, [100] * 72, 5, 20, 800, increment_f=5.0, angle_offset=-2.5, frame=12
        ),
        ObstacleDistance,
        {"time_usec": 9_000_000, "increment": 5, "min_distance": 20, "max_distance": 800, "frame": 12},
    ),
    (
        "DISTANCE_SENSOR",
        lambda m: m.distance_sensor_encode(42, 20, 700, 250, 0, 0, 0, 0, quaternion=[1.0, 0.0, 0.0, 0.0]),
        DistanceSensor,
        {"time_boot_ms": 42, "current_distance": 250, "orientation": 0, "quaternion": (1.0, 0.0, 0.0, 0.0)},
    ),
    (
        "OBSTACLE_DISTANCE_3D",
        lambda m: m.obstacle_distance_3d_encode(8, 0, 12, 0, 1.0, 2.0, 0.5, 0.1, 20.0),
        ObstacleDistance3d,
        {"time_boot_ms": 8, "frame": 12, "x": 1.0, "y": 2.0, "z": 0.5, "max_distance": 20.0},
    ),
    (
        "ODOMETRY",
        lambda m: m.odometry_encode(
            7_000, 1, 12, 1.0, 2.0, -5.0, [1, 0, 0, 0], 0, 0, 0, 0, 0, 0, [NAN] * 21, [NAN] * 21, reset_counter=3
        ),
        Odometry,
        {"time_usec": 7_000, "reset_counter": 3},
    ),
    (
        "COMMAND_LONG",
        lambda m: m.command_long_encode(1, 191, mavlink.MAV_CMD_DO_REPOSITION, 0, -1, 1, 0, NAN, 0, 0, -5.0),
        CommandLong,
        {"target_system": 1, "target_component": 191, "command": mavlink.MAV_CMD_DO_REPOSITION},
    ),
    (
        "COMMAND_INT",
        lambda m: m.command_int_encode(
            1, 191, mavlink.MAV_FRAME_LOCAL_NED, mavlink.MAV_CMD_DO_REPOSITION, 0, 0, -1, 1, 0, NAN, 0, 50000, -5.0
        ),
        CommandInt,
        {"frame": mavlink.MAV_FRAME_LOCAL_NED, "x": 0, "y": 50000, "z": -5.0},
    ),
    (
        "COMMAND_ACK",
        lambda m: m.command_ack_encode(mavlink.MAV_CMD_NAV_TAKEOFF, mavlink.MAV_RESULT_FAILED, 0, 0, 1, 191),
        CommandAck,
        {"command": mavlink.MAV_CMD_NAV_TAKEOFF, "result": mavlink.MAV_RESULT_FAILED, "target_component": 191},
    ),
    (
        "EKF_STATUS_REPORT",
        lambda m: m.ekf_status_report_encode(mavlink.EKF_ATTITUDE | mavlink.EKF_CONST_POS_MODE, 0, 0, 0, 0, 0),
        EkfStatusReport,
        {"flags": mavlink.EKF_ATTITUDE | mavlink.EKF_CONST_POS_MODE},
    ),
    (
        "PARAM_REQUEST_LIST",
        lambda m: m.param_request_list_encode(1, 0),
        ParamRequestList,
        {"target_system": 1, "target_component": 0},
    ),
    (
        "PARAM_REQUEST_READ",
        lambda m: m.param_request_read_encode(1, 191, b"APF_RHO_L", -1),
        ParamRequestRead,
        {"param_id": "APF_RHO_L", "param_index": -1},
    ),
    (
        "PARAM_SET",
        lambda m: m.param_set_encode(1, 191, b"APF_SILENT_DRIFT", 0.5, mavlink.MAV_PARAM_TYPE_REAL32),
        ParamSet,
        {"param_id": "APF_SILENT_DRIFT", "param_value": 0.5, "param_type": mavlink.MAV_PARAM_TYPE_REAL32},
    ),
    (
        "POSITION_TARGET_LOCAL_NED",
        lambda m: m.position_target_local_ned_encode(
            9, mavlink.MAV_FRAME_LOCAL_NED, 0x0DC0, 1, 2, -5, 0, 0, 0, 0, 0, 0, 0, 0
        ),
        PositionTargetLocalNed,
        {"coordinate_frame": mavlink.MAV_FRAME_LOCAL_NED, "type_mask": 0x0DC0, "x": 1.0, "z": -5.0},
    ),
    (
        "POSITION_TARGET_GLOBAL_INT",
        lambda m: m.position_target_global_int_encode(
            9, mavlink.MAV_FRAME_GLOBAL_RELATIVE_ALT_INT, 0x0DF8, -353632621, 1491652374, 5.0, 0, 0, 0, 0, 0, 0, 0, 0
        ),
        PositionTargetGlobalInt,
        {"lat_int": -353632621, "lon_int": 1491652374, "alt": 5.0, "type_mask": 0x0DF8},
    ),
    (
        "MISSION_COUNT",
        lambda m: m.mission_count_encode(1, 191, 6, mavlink.MAV_MISSION_TYPE_FENCE),
        MissionCount,
        {"count": 6, "mission_type": mavlink.MAV_MISSION_TYPE_FENCE, "target_component": 191},
    ),
    (
        "MISSION_CURRENT",
        lambda m: m.mission_current_encode(3, 7, mavlink.MISSION_STATE_ACTIVE, 1),
        MissionCurrent,
        {"fence_id": 0},  # pymavlink 2.4.50 sends no ids
    ),
    (
        "MISSION_ITEM_INT",
        lambda m: m.mission_item_int_encode(
            1,
            191,
            2,
            mavlink.MAV_FRAME_GLOBAL,
            mavlink.MAV_CMD_NAV_FENCE_POLYGON_VERTEX_INCLUSION,
            0,
            0,
            6.0,
            0,
            0,
            0,
            -353632621,
            1491652374,
            0.0,
            mavlink.MAV_MISSION_TYPE_FENCE,
        ),
        MissionItemInt,
        {"seq": 2, "command": mavlink.MAV_CMD_NAV_FENCE_POLYGON_VERTEX_INCLUSION, "param1": 6.0, "x": -353632621},
    ),
    (
        "MISSION_ACK",
        lambda m: m.mission_ack_encode(1, 191, mavlink.MAV_MISSION_DENIED, mavlink.MAV_MISSION_TYPE_FENCE),
        MissionAck,
        {"type": mavlink.MAV_MISSION_DENIED, "mission_type": mavlink.MAV_MISSION_TYPE_FENCE},
    ),
    (
        "PARAM_VALUE",
        lambda m: m.param_value_encode(b"FENCE_MARGIN", 2.5, mavlink.MAV_PARAM_TYPE_REAL32, 900, 12),
        ParamValue,
        {"param_id": "FENCE_MARGIN", "param_value": 2.5, "param_type": mavlink.MAV_PARAM_TYPE_REAL32},
    ),
    (
        "HOME_POSITION",
        lambda m: m.home_position_encode(-353632621, 1491652374, 584000, 0, 0, 0, [1, 0, 0, 0], 0, 0, 0),
        HomePosition,
        {"latitude": -353632621, "longitude": 1491652374, "altitude": 584000},
    ),
    (
        "SYS_STATUS",
        lambda m: m.sys_status_encode(0x100000, 0x100000, 0x300000, 0, 12000, 0, 80, 0, 0, 0, 0, 0, 0),
        SysStatus,
        {"present": 0x100000, "enabled": 0x100000, "health": 0x300000},
    ),
]


def test_every_consumed_message_has_a_case() -> None:
    assert {c[0] for c in CASES} == set(DECODERS)


@pytest.mark.parametrize(("name", "build", "kind", "fields"), CASES, ids=[c[0] for c in CASES])
def test_decode_gives_the_typed_record(name: str, build: Any, kind: type[Any], fields: dict[str, Any]) -> None:
    rec = decode(_wire(build, src=(1, 1)))
    assert type(rec) is kind
    assert rec is not None and rec.src == Source(1, 1)
    for key, want in fields.items():
        assert getattr(rec, key) == pytest.approx(want), key
    assert dataclasses.is_dataclass(rec)
    with pytest.raises(dataclasses.FrozenInstanceError):
        rec.src = Source(2, 2)  # type: ignore[misc]


@pytest.mark.parametrize("fence_id", [0xDEADBEEF, 0x100, 1, 0xFFFFFFFF])
def test_the_plan_ids_that_pymavlinks_dialect_lacks_are_read_from_the_frame(fence_id: int) -> None:
    # 0x100 and 1: MAVLink 2 trims the payload's trailing zero bytes, mid-field
    rec = decode(_wire(lambda m: MissionCurrentWithIds(3, 7, mavlink.MISSION_STATE_ACTIVE, 1, fence_id)))
    assert isinstance(rec, MissionCurrent) and rec.fence_id == fence_id
    count = decode(_wire(lambda m: MissionCountWithId((1, 191), 6, mavlink.MAV_MISSION_TYPE_FENCE, fence_id)))
    assert isinstance(count, MissionCount) and (count.count, count.opaque_id) == (6, fence_id)
    assert count.mission_type == mavlink.MAV_MISSION_TYPE_FENCE and count.target_component == 191


def test_a_mavlink1_frame_has_no_plan_ids() -> None:
    tx = mavlink.MAVLink(None, srcSystem=1, srcComponent=1)
    frame = MissionCurrentWithIds(3, 7, 0, 0, 0xDEADBEEF).pack(tx, force_mavlink1=True)
    rx = mavlink.MAVLink(None)
    rec = decode(rx.parse_buffer(frame)[0])
    assert isinstance(rec, MissionCurrent) and rec.fence_id == 0


def test_the_sender_is_kept() -> None:
    msg = _wire(lambda m: m.heartbeat_encode(mavlink.MAV_TYPE_GCS, mavlink.MAV_AUTOPILOT_INVALID, 0, 0, 0), (255, 190))
    rec = decode(msg)
    assert isinstance(rec, Heartbeat) and rec.src == Source(255, 190) == source(msg)


def test_messages_the_service_does_not_consume_decode_to_none() -> None:
    assert decode(_wire(lambda m: m.system_time_encode(0, 0))) is None
    assert decode(_wire(lambda m: m.statustext_encode(mavlink.MAV_SEVERITY_INFO, b"hello"))) is None


@pytest.mark.parametrize("bad", [NAN, math.inf, -math.inf])
def test_non_finite_fields_decode_and_are_left_to_the_consumer(bad: float) -> None:
    pose = decode(_wire(lambda m: m.local_position_ned_encode(10, bad, 0.0, bad, bad, 0.0, 0.0)))
    assert isinstance(pose, LocalPositionNed) and not math.isfinite(pose.x) and not math.isfinite(pose.z)
    att = decode(_wire(lambda m: m.attitude_encode(10, 0.0, 0.0, bad, 0, 0, 0)))
    assert isinstance(att, Attitude) and not math.isfinite(att.yaw)
    od = decode(
        _wire(lambda m: m.obstacle_distance_encode(1, 0, [100] * 72, 0, 20, 800, increment_f=bad, angle_offset=bad))
    )
    assert isinstance(od, ObstacleDistance) and not math.isfinite(od.increment_f)
    p3 = decode(_wire(lambda m: m.obstacle_distance_3d_encode(8, 0, 12, 0, bad, 2.0, 0.5, bad, 20.0)))
    assert isinstance(p3, ObstacleDistance3d) and not math.isfinite(p3.x)
    ds = decode(_wire(lambda m: m.distance_sensor_encode(1, 20, 700, 250, 0, 0, 100, 0, quaternion=[bad] * 4)))
    assert isinstance(ds, DistanceSensor) and not math.isfinite(ds.quaternion[0])


class _Broken:
    """A message whose fields cannot be read (what a buggy dialect or a hand-made object could hand over)."""

    def __init__(self, kind: str, **fields: Any) -> None:
        self._kind = kind
        self.__dict__.update(fields)

    def get_type(self) -> str:
        return self._kind

    def get_srcSystem(self) -> int:
        return 1

    def get_srcComponent(self) -> int:
        return 1


@pytest.mark.parametrize("name", sorted(DECODERS))
def test_unreadable_fields_are_rejected_never_raised(name: str) -> None:
    assert decode(_Broken(name)) is None  # every field missing
    assert decode(_Broken(name, time_boot_ms=NAN, time_usec=math.inf, type=None, command="x")) is None


def test_an_object_that_is_no_message_is_rejected() -> None:
    assert decode(object()) is None
    assert source(object()) is None
