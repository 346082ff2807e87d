"""ObstacleMemory: expiry, merging, capacity and clearing by observed free space."""

from __future__ import annotations

import math

import numpy as np
import pytest

from apf_companion.errors import ConfigError
from apf_companion.perception import ObstacleMemory, Pose, RangeScan, ScanFrame
from apf_companion.perception.geometry import element_half_width_rad


def test_expiry() -> None:
    mem = ObstacleMemory(expiry_s=2.0, merge_radius_m=0.1, max_points=100)
    mem.add(np.array([[1.0, 0.0, 0.0]]), t_s=0.0)
    mem.add(np.array([[5.0, 0.0, 0.0]]), t_s=1.5)
    assert mem.points(2.0).shape == (2, 3)
    pts = mem.points(2.5)
    np.testing.assert_allclose(pts, [[5.0, 0.0, 0.0]])
    assert mem.points(10.0).shape == (0, 3)


def test_seen_again_is_refreshed_not_duplicated() -> None:
    mem = ObstacleMemory(expiry_s=1.0, merge_radius_m=0.2, max_points=100)
    mem.add(np.array([[1.0, 1.0, 0.0]]), t_s=0.0)
    mem.add(np.array([[1.1, 1.0, 0.0]]), t_s=0.9)
    assert len(mem) == 1
    # Refreshed at 0.9: still there at 1.5, and where it was first seen (a new position would drag a surface's
    # points along with the vehicle's windows; see memory.py).
    np.testing.assert_allclose(mem.points(1.5), [[1.0, 1.0, 0.0]])
    np.testing.assert_allclose(mem.ages_s(1.5), [0.6])


def test_points_along_a_wall_stay_where_they_were_seen() -> None:
    # A chain of points 0.15 m apart seen again 0.1 m further along: each is refreshed in place; none slides.
    mem = ObstacleMemory(expiry_s=10.0, merge_radius_m=0.2, max_points=100)
    chain = np.column_stack([np.full(10, 5.0), 0.3 * np.arange(10), np.zeros(10)])
    mem.add(chain, t_s=0.0)
    mem.add(chain + np.array([0.0, 0.1, 0.0]), t_s=1.0)
    np.testing.assert_allclose(mem.points(1.0), chain)
    np.testing.assert_allclose(mem.ages_s(1.0), np.zeros(10))


def test_a_refresh_keeps_the_largest_spread() -> None:
    mem = ObstacleMemory(expiry_s=10.0, merge_radius_m=0.2, max_points=100)
    mem.add(np.array([[3.0, 0.0, 0.0]]), t_s=0.0, spread_m=np.array([0.0]))  # e.g. a surface-fill point
    mem.add(np.array([[3.05, 0.0, 0.0], [3.1, 0.0, 0.0]]), t_s=1.0, spread_m=np.array([0.2, 0.1]))
    assert len(mem) == 1
    pose = Pose(t_s=1.0, pos_ned_m=np.zeros(3), yaw_rad=0.0)

    # Beams 7.5 degrees apart (windows 3.75 degrees either side). The point, 3 m ahead, lies 2.7 m inside the
    # 0-degree beam's 5 m reading. Its 0.2 m spread is a disc of asin(0.2 / 3) = 3.8 degrees, which meets the
    # -7.5 degree window (3.75 + 3.8 >= 7.5): that beam reads 2.9 m, so the surface may be there, and the point
    # stays. With the fill point's spread 0 (or the smaller 0.1 m: 1.9 degrees) it would be cleared.
    def scan(left_m: float) -> RangeScan:
        return RangeScan(
            t_s=1.0,
            frame=ScanFrame.LOCAL_NED,
            bearings_rad=np.deg2rad([-7.5, 0.0, 7.5]),
            ranges_m=np.array([left_m, 5.0, 5.0]),
            range_min_m=0.1,
            range_max_m=10.0,
        )

    assert mem.clear_observed(scan(2.9), pose) == 0
    assert mem.clear_observed(scan(5.0), pose) == 1  # every window that meets the disc sees past it


def test_merge_within_one_batch_first_per_cell() -> None:
    mem = ObstacleMemory(expiry_s=1.0, merge_radius_m=0.5, max_points=100)
    # Cells have edge 0.5 / sqrt(3) = 0.289 m: 0.01, 0.1 and 0.2 share the first cell, 0.3 is in the next.
    pts = np.array([[0.1, 0.0, 0.0], [0.01, 0.0, 0.0], [0.2, 0.0, 0.0], [0.3, 0.0, 0.0], [5.0, 0.0, 0.0]])
    mem.add(pts, t_s=0.0)
    np.testing.assert_allclose(mem.points(0.0), [[0.1, 0.0, 0.0], [0.3, 0.0, 0.0], [5.0, 0.0, 0.0]])


def test_dense_arc_is_thinned_but_covered() -> None:
    # 360 beams on an arc at 10 m (8.7 cm apart): fewer points, one per grid cell, none of the arc uncovered.
    b = np.linspace(-np.pi / 2, np.pi / 2, 360)
    arc = np.column_stack([10.0 * np.cos(b), 10.0 * np.sin(b), np.zeros(360)])
    mem = ObstacleMemory(expiry_s=1.0, merge_radius_m=0.2, max_points=1000)
    mem.add(arc, t_s=0.0)
    kept = mem.points(0.0)
    assert len(kept) < 300
    cells = np.floor(kept / (0.2 / np.sqrt(3.0))).astype(np.int64)
    assert len(np.unique(cells, axis=0)) == len(kept)
    d = np.linalg.norm(arc[:, None, :] - kept[None, :, :], axis=-1)
    assert np.all(d.min(axis=1) <= 0.2)
    # Seen again next cycle, slightly moved: fresh points cover the new arc and the memory does not grow much
    # (an old point stays, with its old time, only where no kept new point came within the radius).
    moved = arc + 0.01
    mem.add(moved, t_s=0.5)
    assert len(mem) <= 1.1 * len(kept)
    fresh = mem.points(0.5)[mem.ages_s(0.5) == 0.0]
    d = np.linalg.norm(moved[:, None, :] - fresh[None, :, :], axis=-1)
    assert np.all(d.min(axis=1) <= 0.2)


def test_non_finite_rows_ignored_and_shape_checked() -> None:
    mem = ObstacleMemory()
    mem.add(np.array([[math.nan, 0.0, 0.0], [1.0, 2.0, 3.0], [1e300, 0.0, 0.0], [-math.inf, 0, 0]]), t_s=0.0)
    assert len(mem) == 1
    with pytest.raises(ConfigError, match="shape"):
        mem.add(np.zeros((2, 2)), t_s=0.0)


def test_capacity_drops_oldest() -> None:
    mem = ObstacleMemory(expiry_s=100.0, merge_radius_m=0.1, max_points=3)
    for i in range(5):
        mem.add(np.array([[float(i), 0.0, 0.0]]), t_s=float(i))
    np.testing.assert_allclose(mem.points(5.0)[:, 0], [2.0, 3.0, 4.0])
    assert mem.dropped_full == 2


def test_bad_config() -> None:
    with pytest.raises(ConfigError, match="expiry_s"):
        ObstacleMemory(expiry_s=0.0)
    with pytest.raises(ConfigError, match="merge_radius_m"):
        ObstacleMemory(merge_radius_m=math.nan)
    with pytest.raises(ConfigError, match="max_points"):
        ObstacleMemory(max_points=0)


def _ring_scan(ranges_m: list[float], *, range_max_m: float = 10.0) -> RangeScan:
    n = len(ranges_m)
    return RangeScan(
        t_s=0.0,
        frame=ScanFrame.BODY_FRD,
        bearings_rad=np.deg2rad(np.arange(n) * 360.0 / n),
        ranges_m=np.array(ranges_m),
        range_min_m=0.1,
        range_max_m=range_max_m,
    )


def test_clear_observed_free_and_obstacle_beams() -> None:
    mem = ObstacleMemory(expiry_s=100.0, merge_radius_m=0.1, max_points=100)
    remembered = np.array(
        [
            [3.0, 0.0, 0.0],  # north: beam 0 (forward) is free -> cleared
            [0.0, 3.0, 0.0],  # east: beam 1 sees an obstacle at 5 m -> 3 m is nearer -> cleared
            [0.0, 4.9, 0.0],  # east, within the 0.3 m margin of the reading -> kept
            [-3.0, 0.0, 0.0],  # south: beam 2 is unknown -> kept
            [0.0, -12.0, 0.0],  # west: free beam but beyond range_max -> kept
            [3.0, 0.0, -5.0],  # north but 5 m above the scan plane -> kept
        ]
    )
    mem.add(remembered, t_s=0.0)
    pose = Pose(t_s=0.0, pos_ned_m=np.zeros(3), yaw_rad=0.0)
    removed = mem.clear_observed(_ring_scan([math.inf, 5.0, math.nan, math.inf]), pose)
    assert removed == 2
    np.testing.assert_allclose(mem.points(0.0), remembered[2:])


def test_clear_observed_uses_yaw() -> None:
    mem = ObstacleMemory(expiry_s=100.0, merge_radius_m=0.1, max_points=100)
    mem.add(np.array([[0.0, 3.0, 0.0]]), t_s=0.0)  # east
    facing_east = Pose(t_s=0.0, pos_ned_m=np.zeros(3), yaw_rad=math.pi / 2)
    # Only the forward beam is free; facing east, forward is east.
    assert mem.clear_observed(_ring_scan([math.inf, math.nan, math.nan, math.nan]), facing_east) == 1
    assert len(mem) == 0


def test_spread_input_is_checked() -> None:
    mem = ObstacleMemory(expiry_s=10.0, merge_radius_m=0.2, max_points=100)
    with pytest.raises(ConfigError, match="spread_m"):
        mem.add(np.zeros((2, 3)), t_s=0.0, spread_m=np.zeros(3))
    # A non-finite or negative spread counts as none: the point is cleared by its own beam alone.
    mem.add(np.array([[3.0, 0.0, 0.0], [0.0, 3.0, 0.0]]), t_s=0.0, spread_m=np.array([math.nan, -1.0]))
    pose = Pose(t_s=0.0, pos_ned_m=np.zeros(3), yaw_rad=0.0)
    scan = RangeScan(
        t_s=0.0,
        frame=ScanFrame.LOCAL_NED,
        bearings_rad=np.deg2rad(np.arange(0.0, 360.0, 5.0)),
        ranges_m=np.where(np.arange(72) % 18 == 1, 1.0, 9.0),  # 5 and 95 degrees read 1 m, beside the points
        range_min_m=0.1,
        range_max_m=10.0,
    )
    assert mem.clear_observed(scan, pose) == 2


def test_element_half_width() -> None:
    assert element_half_width_rad(np.deg2rad(np.arange(0.0, 360.0, 5.0))) == pytest.approx(math.radians(2.5))
    assert element_half_width_rad(np.array([1.0])) == 0.0
    assert element_half_width_rad(np.deg2rad([350.0, 0.0, 10.0])) == pytest.approx(math.radians(5.0))


def test_a_closer_look_supersedes_a_far_one() -> None:
    # A return placed from 8 m (spread 0.35 m) and the same jamb seen from 2 m (spread 0.09 m), 0.3 m away: outside
    # the merge radius, inside the old point's spread, and four times as precise: the old point goes.
    mem = ObstacleMemory(expiry_s=10.0, merge_radius_m=0.2, max_points=100)
    mem.add(np.array([[8.0, 11.0, -5.0], [8.0, 5.0, -5.0]]), t_s=0.0, spread_m=np.array([0.35, 0.35]))
    mem.add(np.array([[8.0, 10.7, -5.0]]), t_s=1.0, spread_m=np.array([0.09]))
    np.testing.assert_allclose(mem.points(1.0), [[8.0, 5.0, -5.0], [8.0, 10.7, -5.0]])
    # Not twice as precise: refreshed in place (0.1 m away), nothing superseded.
    mem.add(np.array([[8.0, 5.1, -5.0]]), t_s=2.0, spread_m=np.array([0.2]))
    np.testing.assert_allclose(mem.points(2.0), [[8.0, 5.0, -5.0], [8.0, 10.7, -5.0]])
    np.testing.assert_allclose(mem.ages_s(2.0), [0.0, 1.0])
    # A fill point (spread 0) supersedes nothing (it refreshes the point 0.15 m away), and nothing supersedes it.
    mem.add(np.array([[8.0, 5.15, -5.0]]), t_s=3.0, spread_m=np.array([0.0]))
    assert len(mem) == 2
    mem.add(np.array([[0.0, 0.0, -5.0]]), t_s=3.0, spread_m=np.array([0.0]))
    mem.add(np.array([[0.0, 0.1, -5.0]]), t_s=3.0, spread_m=np.array([0.01]))
    np.testing.assert_allclose(mem.points(3.0)[-1], [0.0, 0.0, -5.0])


def test_a_climb_does_not_stack_points_in_layers() -> None:
    # A horizontal scan's points are at the vehicle's height: climbing 0.1 m per scan past a wall, the refreshed
    # points follow the newest height instead of leaving a layer every 0.2 m.
    mem = ObstacleMemory(expiry_s=100.0, merge_radius_m=0.2, max_points=10_000)
    wall = np.column_stack([np.full(20, 5.0), 0.2 * np.arange(20), np.zeros(20)])
    for k in range(50):
        mem.add(wall + np.array([0.0, 0.0, -0.1 * k]), t_s=0.1 * k, spread_m=np.full(20, 0.1))
    pts = mem.points(5.0)
    assert len(pts) == 20
    np.testing.assert_allclose(pts[:, 2], -4.9)


def test_a_return_within_the_spread_stands_for_the_kept_point() -> None:
    # P, 5 m out at 5 degrees, lies in a free window; the 0-degree window reads 5.0 m, a return 0.44 m from P. With
    # a spread of 0.4 m, P's disc meets that window and the return is farther than the spread: P may be a surface
    # that scan cannot see, and stays. With 0.5 m the return lies within the spread and stands for it: P goes.
    pose = Pose(t_s=1.0, pos_ned_m=np.zeros(3), yaw_rad=0.0)
    ranges = np.full(72, math.inf)
    ranges[0] = 5.0
    scan = RangeScan(
        t_s=1.0,
        frame=ScanFrame.LOCAL_NED,
        bearings_rad=np.deg2rad(5.0 * np.arange(72)),
        ranges_m=ranges,
        range_min_m=0.1,
        range_max_m=9.0,
    )
    p = np.array([[5.0 * math.cos(math.radians(5.0)), 5.0 * math.sin(math.radians(5.0)), 0.0]])
    for spread, removed in ((0.4, 0), (0.5, 1)):
        mem = ObstacleMemory(expiry_s=10.0, merge_radius_m=0.2, max_points=100)
        mem.add(p, t_s=0.0, spread_m=np.array([spread]))
        assert mem.clear_observed(scan, pose) == removed
