"""The perception front end: the one owner of pose history, scan timing and the obstacle memory."""

from __future__ import annotations

import ast
import logging
import math
from pathlib import Path

import numpy as np
import pytest
from pymavlink.dialects.v20 import ardupilotmega as mavlink

from apf_companion.links.messages import ObstacleDistance, ObstacleDistance3d, Source
from apf_companion.perception import PerceptionFrontEnd, PerceptionParams, RangeScan, ScanFrame, encode_laserscan_cdr
from apf_companion.perception.frontend import BAD_SCAN_LOG_INTERVAL_S, MAX_SENSOR_IDS

ROOT = Path(__file__).resolve().parents[2]
SRC = Source(1, 1)


def front(**kw: float) -> PerceptionFrontEnd:
    return PerceptionFrontEnd(PerceptionParams(**kw))  # type: ignore[arg-type]


def test_no_pose_before_a_heading_and_a_non_finite_heading_is_counted() -> None:
    p = front()
    assert p.on_local_position(100, (0.0, 0.0, -5.0), 1.0) is None  # no ATTITUDE yet
    p.on_attitude(math.nan)
    assert p.counters.bad_poses == 1
    p.on_attitude(0.5)
    pose = p.on_local_position(200, (1.0, 2.0, -5.0), 1.1)
    assert pose is not None and pose.yaw_rad == 0.5 and pose.pos_ned_m.tolist() == [1.0, 2.0, -5.0]
    assert p.counters.poses == 2 and len(p.history) == 1


def test_frozen_reordered_and_non_finite_poses_are_refused_and_a_reboot_is_accepted() -> None:
    p = front()
    p.on_attitude(0.0)
    assert p.on_local_position(50_000, (0.0, 0.0, -5.0), 1.0) is not None
    assert p.on_local_position(50_000, (0.1, 0.0, -5.0), 1.1) is None  # frozen
    assert p.on_local_position(49_000, (0.1, 0.0, -5.0), 1.2) is None  # reordered
    assert p.counters.stale_poses == 2
    assert p.on_local_position(50_100, (math.nan, 0.0, -5.0), 1.3) is None
    assert p.counters.bad_poses == 1
    # A large jump back is a reboot only with boot evidence (HEARTBEAT after a silence, MAV_STATE_BOOT).
    assert p.on_local_position(300, (0.0, 0.0, -5.0), 1.4) is None
    assert p.counters.pose_time_jumps == 1
    p.gate.note_reboot()
    assert p.on_local_position(350, (0.0, 0.0, -5.0), 1.45) is not None
    assert len(p.history) == 1 and p.counters.pose_resets == 1
    assert p.take_reset() is not None and p.take_reset() is None


def test_scan_stamps_map_boot_time_to_the_service_clock_and_implausible_ones_to_receipt() -> None:
    p = front()
    assert p.scan_time(1000, 7.0) == 7.0  # no pose yet: receive time
    p.on_attitude(0.0)
    p.on_local_position(2000, (0.0, 0.0, -5.0), 10.0)  # offset 8 s
    assert p.scan_time(1500, 10.2) == pytest.approx(9.5)
    assert p.scan_time(3000, 10.2) == 10.2  # in the future
    assert p.scan_time(None, 10.2) == 10.2


def _scan(time_usec: int, ahead_cm: int, frame: int = mavlink.MAV_FRAME_BODY_FRD) -> ObstacleDistance:
    return ObstacleDistance(
        src=SRC,
        time_usec=time_usec,
        distances=(ahead_cm,) + (65535,) * 71,
        increment=5,
        min_distance=20,
        max_distance=800,
        increment_f=5.0,
        angle_offset=0.0,
        frame=frame,
    )


def test_a_scan_is_remembered_and_keeps_the_ranges_fresh() -> None:
    p = front()
    p.on_attitude(0.0)
    p.on_local_position(1000, (0.0, 0.0, -5.0), 10.0)
    assert p.ranges_t_s is None
    p.on_obstacle_distance(_scan(1_000_000, 300), 10.0)
    pts = p.points(10.0)
    assert pts.shape == (1, 3) and pts[0, 0] == pytest.approx(3.0)
    assert p.ranges_t_s == pytest.approx(10.0) and len(p) == 1
    assert p.counters.scans == 1 and p.counters.unknown_sectors == 71


def test_a_malformed_scan_is_counted_and_changes_nothing() -> None:
    p = front()
    p.on_attitude(0.0)
    p.on_local_position(1000, (0.0, 0.0, -5.0), 10.0)
    p.on_obstacle_distance(_scan(1_000_000, 300, frame=mavlink.MAV_FRAME_GLOBAL_INT + 100), 10.0)
    p.on_scan_payload("application/json", b"{not json", 10.0)
    assert p.counters.bad_scans == 2 and len(p) == 0 and p.ranges_t_s is None


def _bad_scan_lines(caplog: pytest.LogCaptureFixture) -> list[tuple[str, str, int]]:
    return [
        (r.source, r.error, r.unlogged)  # type: ignore[attr-defined]
        for r in caplog.records
        if r.getMessage() == "ranges.bad" and r.levelno == logging.WARNING
    ]


def test_rejected_scans_are_logged_at_warning_rate_limited_on_the_service_clock(
    caplog: pytest.LogCaptureFixture,
) -> None:
    """The service runs at INFO: a bad scan must say why at WARNING, the first at once, then at most one line per
    BAD_SCAN_LOG_INTERVAL_S (of the clock the caller passes) with the count not logged meanwhile."""
    caplog.set_level(logging.INFO, logger="apf_companion.perception.frontend")
    p = front()
    bad_frame = _scan(1_000_000, 300, frame=mavlink.MAV_FRAME_GLOBAL_INT + 100)
    p.on_scan_payload("application/json", b"{not json", 10.0)
    [(source, error, unlogged)] = _bad_scan_lines(caplog)
    assert (source, unlogged) == ("zenoh", 0) and "not valid UTF-8 JSON" in error
    for i in range(5):  # a flood within the interval: counted, not logged
        p.on_obstacle_distance(bad_frame, 10.0 + i)
    p.on_scan_payload("application/json", b"{not json", 10.0 + BAD_SCAN_LOG_INTERVAL_S - 1e-3)
    assert len(_bad_scan_lines(caplog)) == 1 and p.counters.bad_scans == 7
    p.on_obstacle_distance(bad_frame, 10.0 + BAD_SCAN_LOG_INTERVAL_S)  # the interval is over: the next is logged
    lines = _bad_scan_lines(caplog)
    assert len(lines) == 2
    assert lines[1][0] == "OBSTACLE_DISTANCE" and "frame=105 is not supported" in lines[1][1]
    assert lines[1][2] == 6  # the six since the first line
    p.on_obstacle_distance(bad_frame, 10.0 + 1.5 * BAD_SCAN_LOG_INTERVAL_S)
    assert len(_bad_scan_lines(caplog)) == 2 and p.bad_scan_log.unlogged == 1


def test_an_obstacle_point_3d_is_placed_with_the_pose_at_its_time() -> None:
    p = front()
    p.on_attitude(math.pi / 2)  # facing east
    p.on_local_position(1000, (0.0, 0.0, -5.0), 10.0)
    ahead = ObstacleDistance3d(
        src=SRC,
        time_boot_ms=1000,
        frame=mavlink.MAV_FRAME_BODY_FRD,
        x=2.0,
        y=0.0,
        z=0.0,
        min_distance=0.1,
        max_distance=20.0,
    )
    p.on_obstacle_distance_3d(ahead, 10.0)
    pts = p.points(10.0)
    assert pts.shape == (1, 3) and pts[0, :2] == pytest.approx([0.0, 2.0])
    bad = ObstacleDistance3d(
        src=SRC,
        time_boot_ms=1000,
        frame=mavlink.MAV_FRAME_BODY_FRD,
        x=math.inf,
        y=0.0,
        z=0.0,
        min_distance=0.1,
        max_distance=20.0,
    )
    p.on_obstacle_distance_3d(bad, 10.0)
    assert p.counters.bad_scans == 1 and len(p) == 1


def test_points_beyond_max_range_are_not_remembered() -> None:
    p = front(max_range_m=2.0)
    p.on_attitude(0.0)
    p.on_local_position(1000, (0.0, 0.0, -5.0), 10.0)
    p.on_obstacle_distance(_scan(1_000_000, 300), 10.0)
    assert len(p) == 0 and p.ranges_t_s == pytest.approx(10.0)  # still news: nothing within 2 m ahead


def test_remember_moves_the_ranges_time_only_forwards() -> None:
    p = front()
    p.remember(np.array([[1.0, 0.0, -5.0]]), 5.0)
    p.remember(np.zeros((0, 3)), 4.0)
    assert p.ranges_t_s == 5.0 and len(p) == 1


WRITES = {"add", "clear_observed", "clear", "expire"}


def test_only_the_front_end_writes_the_obstacle_memory() -> None:
    """One writer: no module in apf_companion but the front end's obstacle store (perception/store.py) calls the
    memory's writing methods."""
    offenders = []
    for path in sorted((ROOT / "apf_companion").rglob("*.py")):
        if path.name in ("store.py", "memory.py"):
            continue
        for node in ast.walk(ast.parse(path.read_text())):
            if (
                isinstance(node, ast.Call)
                and isinstance(node.func, ast.Attribute)
                and node.func.attr in WRITES
                and "memory" in ast.unparse(node.func.value)
            ):
                offenders.append(f"{path.relative_to(ROOT)}:{node.lineno} {ast.unparse(node)}")
    assert not offenders, offenders


def test_a_new_frame_id_on_every_scan_does_not_grow_the_sensor_table() -> None:
    """A zenoh publisher changing its LaserScan frame_id on every scan: sources beyond MAX_SENSOR_IDS share one id."""
    p = front()
    p.on_attitude(0.0)
    scan = RangeScan(
        t_s=0.0,
        frame=ScanFrame.BODY_FRD,
        bearings_rad=np.deg2rad([-5.0, 0.0, 5.0]),
        ranges_m=np.array([4.0, 4.0, 4.0]),
        range_min_m=0.2,
        range_max_m=12.0,
    )
    n = 3 * MAX_SENSOR_IDS
    for i in range(n):
        t = 10.0 + 0.1 * i
        p.on_local_position(1000 + 100 * i, (0.0, 0.0, -5.0), t)
        p.on_scan_payload("application/cdr", encode_laserscan_cdr(scan, frame_id=f"laser{i}"), t)
    p.on_local_position(1000 + 100 * n, (0.0, 0.0, -5.0), 10.0 + 0.1 * n)  # places the last one
    assert p.counters.scans == n and p.counters.bad_scans == 0 and p.counters.scans_without_pose == 0
    assert len(p.scans._sensor_ids) == MAX_SENSOR_IDS
    assert len(p) > 0  # the extra sources' obstacles are remembered all the same
