"""Real MAVLink frames (pymavlink pack, parse, the link's record decoder) through the perception front end."""

from __future__ import annotations

from typing import Any

import numpy as np
import pytest
from pymavlink.dialects.v20 import ardupilotmega as mavlink

from apf_companion.links.messages import DistanceSensor, decode
from apf_companion.perception import PerceptionFrontEnd, PerceptionParams

TX = mavlink.MAVLink(None, srcSystem=1, srcComponent=1)


def _record(msg: Any) -> Any:
    """``msg`` packed as MAVLink 2, parsed back and decoded into the record the service's handlers get."""
    rx = mavlink.MAVLink(None)
    parsed = rx.parse_buffer(msg.pack(TX))
    assert parsed is not None and len(parsed) == 1
    return decode(parsed[0])


def _front(**kw: Any) -> PerceptionFrontEnd:
    """A front end with one pose: the origin, facing north (time_boot_ms 1000 at service time 10 s)."""
    p = PerceptionFrontEnd(PerceptionParams(**kw))
    p.on_attitude(0.0, time_boot_ms=1000)
    p.on_local_position(1000, (0.0, 0.0, -5.0), 10.0)
    return p


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
