"""Surface fill: points along the chord between adjacent sector returns that lie on one straight surface.

Walls get closed, separate trunks keep their gaps, wrong fills are cleared by later scans that see through them.
The scans come from the simulator's sensor geometry (``World.window_ranges_m``: the nearest surface in each
5-degree window, as the service's sim sensor and ArduPilot's proximity sectors report).
"""

from __future__ import annotations

import ast
import inspect
import math
import textwrap
from typing import Any

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from apf_companion.builders import perception_params
from apf_companion.config import config_from_mapping
from apf_companion.errors import ConfigError
from apf_companion.perception import PerceptionFrontEnd, PerceptionParams
from apf_companion.perception import geometry as geometry_module
from apf_companion.perception.geometry import scan_bearings_ned_rad, scan_to_points_ned, surface_fill_points
from apf_companion.perception.types import FloatArray, Pose, RangeScan, ScanFrame
from sim.world import World, load_world
from sim.world.files import example_world_path
from sim.world.geometry import clearance_many_m

SECTORS_RAD = np.deg2rad(5.0 * np.arange(72))
HALF_RAD = math.radians(2.5)
PASSABLE_M = 2.0 * (0.25 + 0.1)  # collision radius + a 0.1 m margin, both sides


def _scan(
    world: World, pos_ne: tuple[float, float], bearings_rad: FloatArray = SECTORS_RAD, t_s: float = 0.0
) -> RangeScan:
    ranges = world.window_ranges_m(pos_ne, bearings_rad, HALF_RAD)
    return RangeScan(
        t_s=t_s,
        frame=ScanFrame.LOCAL_NED,
        bearings_rad=bearings_rad,
        ranges_m=np.where(ranges > 8.0, np.inf, ranges),
        range_min_m=0.2,
        range_max_m=8.0,
    )


def _pose(pos_ne: tuple[float, float], t_s: float = 0.0, yaw_rad: float = 0.0) -> Pose:
    return Pose(t_s=t_s, pos_ned_m=np.array([pos_ne[0], pos_ne[1], -5.0]), yaw_rad=yaw_rad)


def _on_chord_of_adjacent_returns(scan: RangeScan, pose: Pose, fill: FloatArray, max_gap_m: float) -> bool:
    """Every filled point lies on the segment between the returns of two adjacent sectors (a reference check
    with a per-pair loop, independent of the implementation's rolled arrays)."""
    b = scan_bearings_ned_rad(scan, pose)
    n = b.size
    inc = float(np.median(np.remainder(np.diff(b) + math.pi, 2 * math.pi) - math.pi)) if n > 1 else 0.0
    segments = []
    for i in range(n):
        j = (i + 1) % n
        step = math.remainder(b[j] - b[i], 2 * math.pi)
        if n < 2 or not 0 < abs(inc) < math.pi / 2 or abs(step - inc) > 1e-3 * abs(inc):
            continue
        if not (math.isfinite(scan.ranges_m[i]) and math.isfinite(scan.ranges_m[j])):
            continue
        pi = pose.pos_ned_m[:2] + scan.ranges_m[i] * np.array([math.cos(b[i]), math.sin(b[i])])
        pj = pose.pos_ned_m[:2] + scan.ranges_m[j] * np.array([math.cos(b[j]), math.sin(b[j])])
        if np.hypot(*(pj - pi)) <= max_gap_m + 1e-9:
            segments.append((pi, pj))
    for pt in fill:
        if pt[2] != pose.pos_ned_m[2]:
            return False
        ok = False
        for pi, pj in segments:
            d = pj - pi
            t = float(np.clip(np.dot(pt[:2] - pi, d) / max(np.dot(d, d), 1e-300), 0.0, 1.0))
            if np.hypot(*(pi + t * d - pt[:2])) <= 1e-9 * (1.0 + np.abs(pt[:2]).max()):
                ok = True
                break
        if not ok:
            return False
    return True


# ---- walls --------------------------------------------------------------------------------------------------
WALL = World.from_obstacles(walls_ne_m=[[[10.0, -20.0], [10.0, 20.0]]], wall_thickness_m=0.2)


def test_oblique_wall_chords_are_filled_at_the_spacing() -> None:
    pos = (9.4, 0.0)  # 0.5 m from the wall face
    scan, pose = _scan(WALL, pos), _pose(pos)
    fill = surface_fill_points(scan, pose)
    assert fill.shape[0] > 0 and fill.dtype == np.float64
    assert _on_chord_of_adjacent_returns(scan, pose, fill, 1.5)
    # Returns + fill along the wall within 3 m of abeam: no gap wider than the spacing.
    pts = np.concatenate([scan_to_points_ned(scan, pose), fill])
    along = np.sort(pts[(np.abs(pts[:, 0] - 10.0) < 0.5) & (np.abs(pts[:, 1]) <= 3.0), 1])
    assert np.diff(along).max() <= 0.2 + 1e-9
    # Without fill the sector returns alone leave passable gaps there (the porosity the fill closes).
    raw = scan_to_points_ned(scan, pose)
    raw_along = np.sort(raw[(np.abs(raw[:, 0] - 10.0) < 0.5) & (np.abs(raw[:, 1]) <= 3.0), 1])
    assert np.diff(raw_along).max() > PASSABLE_M
    # All filled points are near the wall: in front of its centre line, within the sensor's window error of the
    # face (the sim's wall range is the distance to the centre line less half the thickness: up to 1 cm beyond
    # the face at these angles).
    assert np.all(fill[:, 0] < 10.0) and np.all(fill[:, 0] > 9.6)


def test_spacing_and_max_gap_parameters() -> None:
    pos = (9.4, 0.0)
    scan, pose = _scan(WALL, pos), _pose(pos)
    coarse = surface_fill_points(scan, pose, spacing_m=0.5)
    fine = surface_fill_points(scan, pose, spacing_m=0.05)
    assert 0 < coarse.shape[0] < fine.shape[0]
    short = surface_fill_points(scan, pose, max_gap_m=0.5)
    assert _on_chord_of_adjacent_returns(scan, pose, short, 0.5)
    assert surface_fill_points(scan, pose, max_gap_m=0.1).shape == (0, 3)
    assert surface_fill_points(scan, pose, line_tol_m=0.0).shape == (0, 3)  # returns are never exactly collinear
    bad: tuple[dict[str, Any], ...] = (
        {"spacing_m": 0.0},
        {"spacing_m": math.nan},
        {"max_gap_m": -1.0},
        {"line_tol_m": -0.1},
    )
    for kwargs in bad:
        with pytest.raises(ConfigError):
            surface_fill_points(scan, pose, **kwargs)


def test_full_circle_wraps_from_last_to_first_sector() -> None:
    pos = (9.4, 0.0)
    pose = _pose(pos)
    # Element 0 at 75 degrees, element 71 at 70 degrees: the 70-75 degree chord is the wrap pair.
    rolled = np.deg2rad(75.0 + 5.0 * np.arange(72))
    a = surface_fill_points(_scan(WALL, pos), pose)
    b = surface_fill_points(_scan(WALL, pos, rolled), pose)
    key = np.lexsort(a.T)
    assert a.shape == b.shape
    np.testing.assert_allclose(a[key], b[np.lexsort(b.T)], atol=1e-9)
    # A partial scan (not closing the circle) has no wrap pair: the 70-75 chord is gone.
    partial = np.deg2rad(75.0 + 5.0 * np.arange(71))
    c = surface_fill_points(_scan(WALL, pos, partial), pose)
    bearing = np.degrees(np.arctan2(c[:, 1] - pos[1], c[:, 0] - pos[0]))
    assert c.shape[0] > 0 and not np.any((bearing > 70.0) & (bearing < 75.0))
    assert np.any((bearing > -75.0) & (bearing < -70.0))


def test_body_frame_scan_is_turned_by_yaw() -> None:
    pos, yaw = (9.4, 0.0), 0.7
    ned = _scan(WALL, pos)
    body = RangeScan(
        t_s=0.0,
        frame=ScanFrame.BODY_FRD,
        bearings_rad=SECTORS_RAD - yaw,
        ranges_m=ned.ranges_m,
        range_min_m=0.2,
        range_max_m=8.0,
    )
    np.testing.assert_allclose(
        surface_fill_points(body, _pose(pos, yaw_rad=yaw)), surface_fill_points(ned, _pose(pos)), atol=1e-9
    )


def test_corner_and_free_neighbours_are_not_filled() -> None:
    # Two returns alone, or with free / unknown neighbours, never make a line.
    ranges = np.full(72, np.inf)
    ranges[10:12] = [2.0, 2.5]
    ranges[30:33] = [2.0, np.nan, 2.5]
    scan = RangeScan(
        t_s=0.0, frame=ScanFrame.LOCAL_NED, bearings_rad=SECTORS_RAD, ranges_m=ranges, range_min_m=0.2, range_max_m=8.0
    )
    assert surface_fill_points(scan, _pose((0.0, 0.0))).shape == (0, 3)
    # A corner: two walls meeting at right angles, seen from inside; the chord across the corner stays open.
    corner = World.from_obstacles(walls_ne_m=[[[5.0, -5.0], [5.0, 5.0]], [[-5.0, 5.0], [5.0, 5.0]]])
    pos = (3.0, 0.0)
    scan = _scan(corner, pos)
    fill = surface_fill_points(scan, _pose(pos))
    assert fill.shape[0] > 0
    # Every filled point is on one wall or the other, no farther off than the sector returns themselves (the
    # window error: a return sits at its window's nearest range, on the window's centre bearing); a chord across
    # the corner would leave both walls by up to half its length.
    raw_off = clearance_many_m(corner, scan_to_points_ned(scan, _pose(pos))[:, :2]).max()
    assert 0.1 < raw_off < 0.25
    assert np.all(clearance_many_m(corner, fill[:, :2]) <= raw_off)
    assert np.any(fill[:, 1] > 2.0) and np.any(fill[:, 0] < 4.0)  # both walls are filled


def test_degenerate_scans_give_no_points() -> None:
    pose = _pose((0.0, 0.0))
    for bearings, ranges in (
        ([], []),
        ([0.0], [2.0]),
        ([0.0, 0.1], [2.0, 2.1]),
        ([0.0, math.pi / 2, math.pi, 3 * math.pi / 2], [1.0, 1.0, 1.0, 1.0]),  # 90-degree "sectors"
        ([0.0, 0.0, 0.0, 0.0], [1.0, 2.0, 3.0, 4.0]),  # no increment
    ):
        scan = RangeScan(
            t_s=0.0,
            frame=ScanFrame.LOCAL_NED,
            bearings_rad=np.array(bearings),
            ranges_m=np.array(ranges),
            range_min_m=0.0,
            range_max_m=9.0,
        )
        assert surface_fill_points(scan, pose).shape == (0, 3)


# ---- separate objects ---------------------------------------------------------------------------------------
ROW = World.from_obstacles(
    circles_ne_m=[[3.0, e] for e in np.arange(-13.0, 13.1, 1.3)], radii_m=0.15
)  # trunks 0.3 m thick, 1.0 m surface gaps, in a row (their fronts are collinear)


def _free_points(world: World, pts: FloatArray, min_clearance_m: float) -> FloatArray:
    return pts[clearance_many_m(world, pts[:, :2]) > min_clearance_m] if pts.shape[0] else pts


def test_row_of_trunks_keeps_its_passable_gaps_near_the_vehicle() -> None:
    fronts = [PerceptionFrontEnd(PerceptionParams(memory_expiry_s=10.0, surface_fill=on)) for on in (True, False)]
    gap_centres = np.arange(-13.0 + 0.65, 13.0, 1.3)
    for front in fronts:
        front.on_attitude(0.0)
    for k in range(40):  # fly along the row 1.5 m in front of it, 0.2 m per scan
        pos, t_s = (1.5 - 0.15, -4.0 + 0.2 * k), 0.1 * k
        for front in fronts:
            assert front.on_local_position(1000 + 100 * k, (pos[0], pos[1], -5.0), t_s) is not None
            front.on_scan(_scan(ROW, pos, t_s=t_s))
        pts, plain = (front.points(t_s) for front in fronts)
        # Each 1.0 m gap beside the vehicle stays passable: nothing within 0.35 m of its centre...
        for e in gap_centres[np.abs(gap_centres - pos[1]) <= 2.0]:
            assert np.hypot(pts[:, 0] - 3.0, pts[:, 1] - e).min() > PASSABLE_M / 2, (k, e)
        # ... and the fill adds nothing in free space. The sector returns themselves sit off a trunk by up to the
        # window error, range x sin(2.5 deg), 0.35 m at 8 m: the memory keeps a point where it was first seen until a
        # return twice as precise supersedes it (measured: 0.15 m).
        near, near_plain = (p[np.abs(p[:, 1] - pos[1]) <= 2.0] for p in (pts, plain))
        for off_m in (0.1, 0.15):
            assert _free_points(ROW, near, off_m).shape[0] <= _free_points(ROW, near_plain, off_m).shape[0]
        assert _free_points(ROW, near, 8.0 * math.sin(math.radians(2.5))).shape[0] == 0


def test_dense_forest_gets_no_fill_in_free_space() -> None:
    world = load_world(example_world_path("forest-dense"))
    rng = np.random.default_rng(7)
    placed = one_side_free = 0
    while placed < 60:
        pos = rng.uniform([-2.0, -8.0], [24.0, 8.0])
        if clearance_many_m(world, pos)[0] < 0.3:
            continue
        placed += 1
        scan, pose = _scan(world, (pos[0], pos[1])), _pose((pos[0], pos[1]))
        assert _free_points(world, surface_fill_points(scan, pose), 0.2).shape[0] == 0
        one_side_free += _free_points(world, surface_fill_points(scan, pose, both_sides=False), 0.2).shape[0]
    # Three collinear returns (one side) are not enough: trunks line up that way and get bridged.
    assert one_side_free > 0


def _ray_scan(world: World, pos_ne: tuple[float, float], t_s: float) -> RangeScan:
    """A lidar-like scan: one exact ray per 5-degree element (no window)."""
    ranges = world.ray_cast_m(pos_ne, SECTORS_RAD)
    return RangeScan(
        t_s=t_s,
        frame=ScanFrame.LOCAL_NED,
        bearings_rad=SECTORS_RAD,
        ranges_m=np.where(ranges > 8.0, np.inf, ranges),
        range_min_m=0.2,
        range_max_m=8.0,
    )


def test_wrong_fill_across_a_doorway_is_cleared_by_a_scan_through_it() -> None:
    # A wall with a 0.9 m doorway (east 2.8-3.7 m), passable. Seen from 1 m off at east 0, the 70 and 75 degree
    # rays hit the wall either side of it (2.75 m and 3.73 m along), the four returns around are collinear and
    # the chord across the doorway is filled; flying to the doorway, the scans that see through it clear those
    # points, while the wall either side stays.
    door = World.from_obstacles(walls_ne_m=[[[10.0, -20.0], [10.0, 2.8]], [[10.0, 3.7], [10.0, 20.0]]])

    def in_door(p: FloatArray) -> int:
        return int(np.count_nonzero((np.abs(p[:, 0] - 10.0) < 0.2) & (p[:, 1] > 2.85) & (p[:, 1] < 3.65)))

    front = PerceptionFrontEnd(PerceptionParams(memory_expiry_s=30.0))
    front.on_attitude(0.0)
    plain = PerceptionFrontEnd(PerceptionParams(memory_expiry_s=30.0, surface_fill=False))
    plain.on_attitude(0.0)
    for k, east in enumerate([0.0, 1.0, 2.0, 3.25]):  # at about 1 m/s: the pose gate refuses faster jumps
        for fe in (front, plain):
            assert fe.on_local_position(1000 + 1000 * k, (9.0, east, -5.0), 1.0 * k) is not None
            fe.on_scan(_ray_scan(door, (9.0, east), 1.0 * k))
        if k == 0:
            assert in_door(front.points(0.0)) >= 3  # wrongly closed: this scan could not tell
            assert in_door(plain.points(0.0)) == 0  # (the sector returns alone leave it open)
    pts = front.points(3.0)
    assert in_door(pts) == 0
    along_m = pts[np.abs(pts[:, 0] - 10.0) < 0.2, 1]  # east of the remembered wall points
    assert np.any(along_m < 2.8) and np.any(along_m > 3.7)


# ---- properties ---------------------------------------------------------------------------------------------
@st.composite
def _scans(draw: st.DrawFn) -> tuple[RangeScan, Pose]:
    n = draw(st.integers(0, 90))
    inc_deg = draw(st.sampled_from([1.0, 2.5, 5.0, -5.0, 10.0, 360.0 / max(n, 1), 45.0]))
    offset = draw(st.floats(-math.pi, math.pi))
    bearings = offset + np.deg2rad(inc_deg) * np.arange(n)
    # Returns on a random line (so that fills happen), random returns, free and unknown elements.
    d = draw(st.floats(0.2, 5.0))
    phi = draw(st.floats(-math.pi, math.pi))
    kinds = np.array(draw(st.lists(st.sampled_from([0, 0, 0, 1, 2, 3]), min_size=n, max_size=n)), dtype=np.intp)
    noise = np.array(draw(st.lists(st.floats(0.0, 0.03), min_size=n, max_size=n)))
    cos = np.cos(bearings - phi)
    with np.errstate(divide="ignore"):
        on_line = np.where(cos > 0.05, d / np.maximum(cos, 1e-12), np.inf) + noise
    rnd = np.array(draw(st.lists(st.floats(0.2, 9.0), min_size=n, max_size=n)))
    ranges = np.choose(kinds, [on_line, rnd, np.full(n, np.inf), np.full(n, np.nan)]) if n else np.zeros(0)
    frame = draw(st.sampled_from(list(ScanFrame)))
    scan = RangeScan(
        t_s=0.0,
        frame=frame,
        bearings_rad=np.array(bearings),
        ranges_m=np.array(ranges),
        range_min_m=0.0,
        range_max_m=9.0,
    )
    pos = draw(st.tuples(st.floats(-1e3, 1e3), st.floats(-1e3, 1e3), st.floats(-50.0, 0.0)))
    pose = Pose(t_s=0.0, pos_ned_m=np.array(pos), yaw_rad=draw(st.floats(-4.0, 4.0)))
    return scan, pose


@settings(max_examples=150, deadline=None)
@given(_scans(), st.floats(0.05, 1.0), st.floats(0.1, 3.0), st.floats(0.0, 0.2), st.booleans())
def test_filled_points_lie_on_chords_between_adjacent_returns(
    scan_pose: tuple[RangeScan, Pose], spacing_m: float, max_gap_m: float, line_tol_m: float, both_sides: bool
) -> None:
    scan, pose = scan_pose
    kwargs = {"spacing_m": spacing_m, "max_gap_m": max_gap_m, "line_tol_m": line_tol_m}
    fill = surface_fill_points(scan, pose, **kwargs, both_sides=both_sides)
    assert fill.ndim == 2 and fill.shape[1] == 3 and np.all(np.isfinite(fill))
    assert _on_chord_of_adjacent_returns(scan, pose, fill, max_gap_m)
    # Each chord's points with its two returns are at most spacing_m apart: fewer than max_gap / spacing per chord.
    assert fill.shape[0] <= len(scan) * math.ceil(max_gap_m / spacing_m)
    if both_sides:  # the rule's chords are a subset of the one-side chords
        loose = surface_fill_points(scan, pose, **kwargs, both_sides=False)
        assert {tuple(p) for p in fill.round(9)} <= {tuple(p) for p in loose.round(9)}


@pytest.mark.parametrize(
    "function_name",
    [
        "surface_fill_points",
        "_adjacent_steps",
        "_check_fill_params",
        "_line_deviation_m",
        "_same_surface",
        "_chord_samples_ne_m",
    ],
)
def test_the_hot_path_has_no_python_loop(function_name: str) -> None:
    tree = ast.parse(textwrap.dedent(inspect.getsource(getattr(geometry_module, function_name))))
    loops = [node for node in ast.walk(tree) if isinstance(node, ast.For | ast.While | ast.comprehension)]
    assert loops == []


def test_the_loop_check_covers_every_surface_fill_helper() -> None:
    """Every function surface_fill_points calls in geometry.py is in the loop check above."""
    tree = ast.parse(textwrap.dedent(inspect.getsource(geometry_module.surface_fill_points)))
    called = {node.func.id for node in ast.walk(tree) if isinstance(node, ast.Call) and isinstance(node.func, ast.Name)}
    local = {name for name in called if inspect.isfunction(getattr(geometry_module, name, None))}
    local -= {"scan_bearings_ned_rad"}  # not part of the fill (one vectorised expression, tested elsewhere)
    helpers = {"_adjacent_steps", "_check_fill_params", "_same_surface", "_chord_samples_ne_m"}
    assert local == helpers


# ---- configuration --------------------------------------------------------------------------------------------
def test_config_keys_reach_the_front_end() -> None:
    cfg = config_from_mapping(
        {"sensors": {"surface_fill": False, "surface_fill_spacing_m": 0.1, "surface_fill_max_gap_m": 1.0}}
    )
    params = perception_params(cfg)
    assert params.surface_fill is False
    assert params.surface_fill_spacing_m == 0.1 and params.surface_fill_max_gap_m == 1.0
    assert params.surface_fill_line_tol_m == 0.05
    assert perception_params(config_from_mapping({})).surface_fill is True


def test_bad_front_end_fill_params_fail_at_construction() -> None:
    for kwargs in (
        {"surface_fill_spacing_m": 0.0},
        {"surface_fill_max_gap_m": math.inf},
        {"surface_fill_line_tol_m": -1.0},
    ):
        with pytest.raises(ConfigError, match="surface fill"):
            PerceptionParams(**kwargs)  # type: ignore[arg-type]


@pytest.mark.parametrize(
    ("key", "value"),
    [
        ("surface_fill_spacing_m", 0.0),
        ("surface_fill_spacing_m", math.nan),
        ("surface_fill_max_gap_m", 10.0),
        ("surface_fill_line_tol_m", -0.01),
        ("surface_fill", "yes"),
    ],
)
def test_bad_surface_fill_config_names_the_key(key: str, value: object) -> None:
    with pytest.raises(ConfigError, match=rf"sensors\.{key}"):
        config_from_mapping({"sensors": {key: value}})
