"""Real MAVLink frames (pymavlink pack, parse, the link's record decoder) through the perception front end."""

from __future__ import annotations

import logging
import math
from typing import Any

import numpy as np
import pytest
from pymavlink.dialects.v20 import ardupilotmega as mavlink

from apf_companion.builders import perception_params
from apf_companion.config import config_from_mapping
from apf_companion.errors import ConfigError
from apf_companion.links.messages import DistanceSensor, ObstacleDistance, decode
from apf_companion.perception import PerceptionFrontEnd, PerceptionParams, RangeScan, ScanFrame, encode_laserscan_cdr

TX = mavlink.MAVLink(None, srcSystem=1, srcComponent=1)


def _record(msg: Any) -> Any:
    """``msg`` packed as MAVLink 2, parsed back and decoded into the record the service's handlers get."""
    rx = mavlink.MAVLink(None)
    parsed = rx.parse_buffer(msg.pack(TX))
    assert parsed is not None and len(parsed) == 1
    return decode(parsed[0])


def _front(*, yaw_deg: float = 0.0, **kw: Any) -> PerceptionFrontEnd:
    """A front end with one pose: the origin, heading ``yaw_deg`` (time_boot_ms 1000 at service time 10 s)."""
    return _placed(PerceptionFrontEnd(PerceptionParams(**kw)), yaw_deg)


def _configured(yaw_deg: float = 0.0, **sensors: Any) -> PerceptionFrontEnd:
    """A front end built as the service builds it from a ``[sensors]`` table, with the pose of ``_front``."""
    return _placed(PerceptionFrontEnd(perception_params(config_from_mapping({"sensors": sensors}))), yaw_deg)


def _placed(p: PerceptionFrontEnd, yaw_deg: float) -> PerceptionFrontEnd:
    p.on_attitude(math.radians(yaw_deg), time_boot_ms=1000)
    p.on_local_position(1000, (0.0, 0.0, -5.0), 10.0)
    return p


def _ahead(cm: int, frame: int = mavlink.MAV_FRAME_BODY_FRD) -> ObstacleDistance:
    """OBSTACLE_DISTANCE with only element 0 (the sensor's forward direction) measured, ``cm`` away."""
    distances = [cm] + [65535] * 71
    msg = mavlink.MAVLink_obstacle_distance_message(
        1_000_000, mavlink.MAV_DISTANCE_SENSOR_LASER, distances, 5, 20, 1000, 5.0, 0.0, frame
    )
    rec = _record(msg)
    assert isinstance(rec, ObstacleDistance)
    return rec


def _ne(p: PerceptionFrontEnd) -> list[list[float]]:
    """The remembered points' north/east [m], rounded to the centimetre."""
    return np.round(p.points(10.0)[:, :2], 2).tolist()  # type: ignore[no-any-return]


def _proximity_face(face: int, current_cm: int, max_cm: int = 500) -> DistanceSensor:
    """DISTANCE_SENSOR as ArduPilot's send_proximity sends a proximity face (id 10 + face, orientation = face)."""
    msg = mavlink.MAVLink_distance_sensor_message(
        1000, 20, max_cm, current_cm, mavlink.MAV_DISTANCE_SENSOR_LASER, 10 + face, face, 0
    )
    rec = _record(msg)
    assert isinstance(rec, DistanceSensor)
    return rec


def test_an_emptied_proximity_face_is_free_space_not_an_obstacle_at_its_range() -> None:
    p = _front()
    p.on_distance_sensor(_proximity_face(2, 300), 10.0)  # face 2: 90 deg, east of a north-facing vehicle
    assert p.points(10.0)[:, :2] == pytest.approx(np.array([[0.0, 3.0]]))
    # The obstacle has gone: ArduPilot now sends the face at max_distance (id 12, current = max = 500 cm).
    p.on_distance_sensor(_proximity_face(2, 500), 10.0)
    assert p.points(10.0).shape == (0, 3)  # seen through and cleared; no phantom at 5 m
    assert (p.counters.scans, p.counters.bad_scans) == (2, 0)


@pytest.mark.parametrize(
    ("mount_deg", "expected_ne"),
    [(0.0, [[3.0, 0.0]]), (90.0, [[0.0, 3.0]]), (180.0, [[-3.0, 0.0]]), (-90.0, [[0.0, -3.0]])],
)
def test_a_turned_obstacle_distance_sensor_places_its_points_where_it_looks(
    mount_deg: float, expected_ne: list[list[float]]
) -> None:
    """sensors.obstacle_distance_mount_yaw_deg (ArduPilot's PRX1_YAW_CORR): a sensor facing right sees its element 0
    on the right; one facing the tail, behind. Without it, a rear-facing lidar's obstacles are mirrored in front."""
    p = _configured(obstacle_distance_mount_yaw_deg=mount_deg)
    p.on_obstacle_distance(_ahead(300), 10.0)
    assert _ne(p) == expected_ne


def test_the_mount_yaw_turns_with_the_vehicle_and_not_a_north_aligned_scan() -> None:
    p = _configured(yaw_deg=90.0, obstacle_distance_mount_yaw_deg=90.0)  # facing east, sensor to the right: south
    p.on_obstacle_distance(_ahead(300), 10.0)
    assert _ne(p) == [[-3.0, 0.0]]
    q = _configured(yaw_deg=90.0, obstacle_distance_mount_yaw_deg=90.0)
    q.on_obstacle_distance(_ahead(300, frame=mavlink.MAV_FRAME_LOCAL_NED), 10.0)  # element 0 is north
    assert _ne(q) == [[3.0, 0.0]]


@pytest.mark.parametrize(("mount_deg", "expected_ne"), [(0.0, [[3.0, 0.0]]), (180.0, [[-3.0, 0.0]])])
def test_a_turned_laserscan_places_its_points_where_it_looks(mount_deg: float, expected_ne: list[list[float]]) -> None:
    """sensors.laserscan_mount_yaw_deg: a lidar mounted facing the tail sees its 0-angle beam behind the vehicle."""
    beam = RangeScan(
        t_s=0.0,
        frame=ScanFrame.BODY_FRD,
        bearings_rad=np.array([0.0]),
        ranges_m=np.array([3.0]),
        range_min_m=0.1,
        range_max_m=12.0,
    )
    p = _configured(laserscan_mount_yaw_deg=mount_deg)
    p.on_scan_payload("zenoh/bytes", encode_laserscan_cdr(beam, frame_id="laser"), 10.0)
    assert _ne(p) == expected_ne


def test_frame_0_is_north_aligned_as_sent_and_from_the_nose_with_the_override() -> None:
    """MAV_FRAME_GLOBAL (0) is north-aligned per common.xml; ArduPilot ignores the frame (AP_Proximity_MAV.cpp),
    so scripts written for it send 0 for a body-mounted sensor. Vehicle facing east, element 0 at 3 m."""
    as_sent = _configured(yaw_deg=90.0)
    as_sent.on_obstacle_distance(_ahead(300, frame=mavlink.MAV_FRAME_GLOBAL), 10.0)
    assert _ne(as_sent) == [[3.0, 0.0]]  # north, whatever the heading
    body = _configured(yaw_deg=90.0, obstacle_distance_frame="body_frd", obstacle_distance_mount_yaw_deg=180.0)
    body.on_obstacle_distance(_ahead(300, frame=mavlink.MAV_FRAME_GLOBAL), 10.0)
    assert _ne(body) == [[0.0, -3.0]]  # from the nose (east), turned by the mount (west)
    # The override reads any frame from the nose, as ArduPilot does; an unknown one too.
    body.on_obstacle_distance(_ahead(400, frame=mavlink.MAV_FRAME_GLOBAL_INT + 100), 10.0)
    assert body.counters.bad_scans == 0


def _frame_warnings(caplog: pytest.LogCaptureFixture) -> list[logging.LogRecord]:
    return [r for r in caplog.records if r.getMessage() == "ranges.frame_global" and r.levelno == logging.WARNING]


def test_frame_0_read_as_sent_is_counted_and_said_once_naming_the_key(caplog: pytest.LogCaptureFixture) -> None:
    caplog.set_level(logging.INFO, logger="apf_companion.perception.frontend")
    p = _configured()
    p.on_obstacle_distance(_ahead(300, frame=mavlink.MAV_FRAME_BODY_FRD), 10.0)
    assert _frame_warnings(caplog) == [] and p.counters.obstacle_distance_frame_global == 0
    for _ in range(3):
        p.on_obstacle_distance(_ahead(300, frame=mavlink.MAV_FRAME_GLOBAL), 10.0)
    [warning] = _frame_warnings(caplog)
    assert warning.key == "sensors.obstacle_distance_frame"  # type: ignore[attr-defined]
    assert 'obstacle_distance_frame = "body_frd"' in warning.hint  # type: ignore[attr-defined]
    assert p.counters.obstacle_distance_frame_global == 3
    # With the override set, frame 0 is what the user asked for: not counted, not said.
    caplog.clear()
    q = _configured(obstacle_distance_frame="body_frd")
    q.on_obstacle_distance(_ahead(300, frame=mavlink.MAV_FRAME_GLOBAL), 10.0)
    assert _frame_warnings(caplog) == [] and q.counters.obstacle_distance_frame_global == 0


@pytest.mark.parametrize(
    ("sensors", "match"),
    [
        ({"obstacle_distance_frame": "north"}, r"sensors\.obstacle_distance_frame must be 'as_sent' or 'body_frd'"),
        ({"obstacle_distance_mount_yaw_deg": 270.0}, r"sensors\.obstacle_distance_mount_yaw_deg must be in"),
        ({"laserscan_mount_yaw_deg": math.nan}, r"sensors\.laserscan_mount_yaw_deg must be in"),
        ({"laserscan_mount_yaw_deg": "rear"}, r"sensors\.laserscan_mount_yaw_deg must be a number"),
    ],
)
def test_bad_mount_settings_name_the_key(sensors: dict[str, Any], match: str) -> None:
    with pytest.raises(ConfigError, match=match):
        config_from_mapping({"sensors": sensors})


def test_the_front_end_refuses_a_non_finite_mount() -> None:
    with pytest.raises(ConfigError, match="laserscan_mount_yaw_rad"):
        PerceptionParams(laserscan_mount_yaw_rad=math.inf)


def _px4(distances: list[int], frame: int, *, increment_f: float = 10.0, angle_offset: float = 0.0) -> ObstacleDistance:
    """OBSTACLE_DISTANCE as PX4 streams its collision-prevention map (streams/OBSTACLE_DISTANCE.hpp: ``increment``
    0, ``increment_f`` the map's 10 deg, ``frame`` as the map's, ``time_usec`` its boot-time stamp)."""
    msg = mavlink.MAVLink_obstacle_distance_message(
        1_000_000, mavlink.MAV_DISTANCE_SENSOR_LASER, distances, 0, 20, 1000, increment_f, angle_offset, frame
    )
    rec = _record(msg)
    assert isinstance(rec, ObstacleDistance)
    return rec


def test_px4s_body_frd_map_is_read_from_the_nose_with_increment_f_and_its_no_data_value() -> None:
    """PX4's map: 36 bins of 10 deg (``increment`` 0, so ``increment_f``), UINT16_MAX = no data, > max = free.
    Vehicle facing east: bin 9 (90 deg right of the nose) is south."""
    d = [65535] * 72
    d[9], d[0] = 300, 1001  # an obstacle at 3 m to the right; ahead free
    p = _configured(yaw_deg=90.0)
    p.on_obstacle_distance(_px4(d, mavlink.MAV_FRAME_BODY_FRD), 10.0)
    assert _ne(p) == [[-3.0, 0.0]]
    assert p.counters.bad_scans == 0


@pytest.mark.parametrize("frame", [mavlink.MAV_FRAME_LOCAL_NED, mavlink.MAV_FRAME_GLOBAL])
def test_an_earth_fixed_scan_is_not_turned_by_the_heading_again(frame: int) -> None:
    """GLOBAL (0) and LOCAL_NED (1): element 0 is north + angle_offset (CollisionPrevention.cpp subtracts the
    vehicle's yaw to put them in its body map); for any heading the point is where the sender said."""
    d = [65535] * 72
    d[0] = 300  # angle_offset 90: element 0 is east
    for yaw_deg in (0.0, 90.0, -135.0):
        p = _configured(yaw_deg=yaw_deg)
        p.on_obstacle_distance(_px4(d, frame, angle_offset=90.0), 10.0)
        assert _ne(p) == [[0.0, 3.0]]


@pytest.mark.parametrize("frame", [mavlink.MAV_FRAME_LOCAL_FRD, mavlink.MAV_FRAME_BODY_NED, 105])
def test_a_frame_px4_does_not_read_is_refused_and_counted_not_guessed(frame: int) -> None:
    """LOCAL_FRD (20) is earth-fixed with no stated heading (PX4 reads it so in ODOMETRY); PX4's collision
    prevention refuses it, BODY_NED and any unknown value ("unsupported frame"): refused, counted, no point."""
    p = _configured(yaw_deg=30.0)
    p.on_obstacle_distance(_px4([300] * 72, frame), 10.0)
    assert p.counters.bad_scans == 1 and p.points(10.0).shape == (0, 3)
