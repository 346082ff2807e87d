"""A scan measured between two poses is placed with the pose interpolated at its time, not the previous one."""

from __future__ import annotations

import math

import numpy as np
from pymavlink.dialects.v20 import ardupilotmega as mavlink2

from apf_companion.config import ServiceConfig
from apf_companion.links.messages import decode
from apf_companion.service import CompanionService
from tests.conftest import ManualClock

UINT16_MAX = 65535


def _msgs() -> mavlink2.MAVLink:
    mav = mavlink2.MAVLink(None, srcSystem=1, srcComponent=1)
    mav.robust_parsing = True
    return mav


def _roundtrip(mav: mavlink2.MAVLink, msg: mavlink2.MAVLink_message) -> mavlink2.MAVLink_message:
    """Pack and parse, so the service gets exactly what it gets off the wire."""
    buf = msg.pack(mav)
    parsed = _msgs().parse_buffer(buf)
    assert parsed is not None and len(parsed) == 1
    return parsed[0]


def _feed(svc: CompanionService, msg: mavlink2.MAVLink_message) -> None:
    """As the service's receive task does: decode once, hand the record to the autopilot handlers."""
    rec = decode(msg)
    assert rec is not None
    svc.handlers.handle(rec, svc.clock.now())


def _pose(svc: CompanionService, clock: ManualClock, mav: mavlink2.MAVLink, boot_ms: int, north_m: float) -> None:
    clock.t = 100.0 + boot_ms / 1000.0
    _feed(svc, _roundtrip(mav, mav.local_position_ned_encode(boot_ms, north_m, 0.0, -5.0, 1.0, 0.0, 0.0)))


def _scan_ahead(mav: mavlink2.MAVLink, boot_ms: int, range_cm: int) -> mavlink2.MAVLink_message:
    """One obstacle straight ahead (sector 0, body FRD), everything else unknown."""
    distances = [range_cm] + [UINT16_MAX] * 71
    msg = mav.obstacle_distance_encode(
        boot_ms * 1000, 0, distances, 5, 20, 800, increment_f=5.0, angle_offset=0.0, frame=12
    )
    return _roundtrip(mav, msg)


def test_scan_between_poses_is_placed_with_the_interpolated_pose() -> None:
    clock = ManualClock()
    svc = CompanionService(ServiceConfig(), clock=clock)
    mav = _msgs()
    clock.t = 100.0
    _feed(svc, _roundtrip(mav, mav.attitude_encode(0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0)))  # facing north
    # Flying north at 1 m/s, poses every 50 ms; the scan is measured at 90 ms, 1.00 m from an obstacle.
    _pose(svc, clock, mav, 0, 0.0)
    _pose(svc, clock, mav, 50, 0.05)
    clock.t = 100.095
    _feed(svc, _scan_ahead(mav, 90, 100))
    assert len(svc.perception.memory) == 0  # waits for the pose after its time
    _pose(svc, clock, mav, 100, 0.10)
    pts = svc.perception.memory.points(clock.t)
    assert pts.shape == (1, 3)
    # The obstacle is at 0.09 + 1.00 north; the pose at 50 ms would have put it at 1.05.
    assert math.isclose(pts[0, 0], 1.09, abs_tol=1e-6), pts
    assert abs(pts[0, 1]) < 1e-9
    assert svc.perception.counters.scans == 1 and svc.perception.counters.scans_without_pose == 0


def test_scan_not_newer_than_the_pose_is_placed_at_once_and_a_lost_pose_stream_does_not_hold_scans() -> None:
    clock = ManualClock()
    svc = CompanionService(ServiceConfig(), clock=clock)
    mav = _msgs()
    _feed(svc, _roundtrip(mav, mav.attitude_encode(0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0)))
    _pose(svc, clock, mav, 0, 0.0)
    _pose(svc, clock, mav, 50, 0.05)
    _feed(svc, _scan_ahead(mav, 40, 200))  # measured before the newest pose
    pts = svc.perception.memory.points(clock.t)
    assert pts.shape == (1, 3) and math.isclose(pts[0, 0], 0.04 + 2.0, abs_tol=1e-6)
    # No pose after the scans: once more than SCAN_DEFER_MAX wait, the oldest are placed with the newest pose
    # (within its hold time) or counted as without a pose; the queue stays bounded.
    for k in range(12):
        clock.t = 100.06 + 0.01 * k
        _feed(svc, _scan_ahead(mav, 60 + 10 * k, 300))
    assert len(svc.perception.deferred) <= 8
    assert svc.perception.counters.scans_deferred_too_long >= 4
    assert np.all(np.isfinite(svc.perception.memory.points(clock.t)))
