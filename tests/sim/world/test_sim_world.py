"""sim.world: geometry against hand-computed values, world files, the paper's random field."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest
from hypothesis import example, given, settings
from hypothesis import strategies as st

from apf_companion.errors import ConfigError
from apf_companion.planning import inside_area
from apf_companion.planning.area import is_polygon
from sim.world import (
    EXAMPLES_DIR,
    PAPER_START_NE_M,
    PAPER_TARGET_NE_M,
    World,
    load_world,
    paper_field,
    parse_field_spec,
    world_from_mapping,
)

SECTORS = np.deg2rad(np.arange(72) * 5.0)
HALF = math.radians(2.5)


def test_circle_windows_match_hand_geometry() -> None:
    # a 1 m cylinder 5 m north: sector 0 sees its front face at 4 m; the sector 5 deg right sees it along its
    # left edge ray (2.5 deg off the centre line): d cos(2.5) - sqrt(r^2 - (d sin 2.5)^2).
    w = World.from_obstacles([[5.0, 0.0]], 1.0)
    r = w.window_ranges_m([0.0, 0.0], SECTORS, HALF)
    assert r[0] == pytest.approx(4.0)
    d, a = 5.0, math.radians(2.5)
    assert r[1] == pytest.approx(d * math.cos(a) - math.sqrt(1 - (d * math.sin(a)) ** 2))
    assert r[71] == pytest.approx(r[1])
    a = math.radians(7.5)
    assert r[2] == pytest.approx(d * math.cos(a) - math.sqrt(1 - (d * math.sin(a)) ** 2))
    # asin(1/5) = 11.5 deg < 12.5 deg: sector 3 misses
    assert np.isinf(r[3:70]).all()


def test_point_obstacle_is_seen_only_by_its_sector() -> None:
    # bearing of (3, 4) from the origin: atan2(4, 3) = 53.13 deg -> sector 11 (52.5 .. 57.5) at 5 m
    w = World.from_obstacles([[3.0, 4.0]], 0.0)
    r = w.window_ranges_m([0.0, 0.0], SECTORS, HALF)
    assert r[11] == pytest.approx(5.0)
    assert np.isinf(np.delete(r, 11)).all()


def test_wall_windows_and_ray_cast() -> None:
    w = World.from_obstacles(walls_ne_m=[[[5.0, -5.0], [5.0, 5.0]]], wall_thickness_m=0.4)
    r = w.window_ranges_m([0.0, 0.0], SECTORS, HALF)
    assert r[0] == pytest.approx(5.0 - 0.2)  # perpendicular foot, minus half the thickness
    assert r[1] == pytest.approx(5.0 / math.cos(math.radians(2.5)) - 0.2)  # nearest window edge ray
    assert r[9] == pytest.approx(5.0 / math.cos(math.radians(42.5)) - 0.2)  # the end point (5, 5) at 45 deg
    assert np.isinf(r[10:63]).all()
    rays = w.ray_cast_m([0.0, 0.0], np.deg2rad([0.0, 30.0, 90.0]))
    assert rays[0] == pytest.approx(5.0)
    assert rays[1] == pytest.approx(5.0 / math.cos(math.radians(30.0)))
    assert np.isinf(rays[2])


@settings(max_examples=60, deadline=None)
@example(cx=0.0, cy=0.0, radius=1.0, wx=3.0, wy=0.015625, wl=1.0, wth=0.0)  # a wall grazing the rays
@given(
    cx=st.floats(-9, 9),
    cy=st.floats(-9, 9),
    radius=st.floats(0.05, 2.0),
    wx=st.floats(-9, 9),
    wy=st.floats(-9, 9),
    wl=st.floats(0.5, 6.0),
    wth=st.floats(0.0, 2 * math.pi),
)
def test_windows_equal_dense_ray_minimum(
    cx: float, cy: float, radius: float, wx: float, wy: float, wl: float, wth: float
) -> None:
    # The exact window minimum must equal a brute-force minimum: for the circle over many rays inside each
    # window, for the wall over many points along it (rays graze a wall nearly parallel to them).
    circle = World.from_obstacles([[cx, cy]], radius)
    end = [wx + wl * math.cos(wth), wy + wl * math.sin(wth)]
    wall = World.from_obstacles(walls_ne_m=[[[wx, wy], end]])
    if circle.clearance_m([0.0, 0.0]) > 0.05:
        exact = circle.window_ranges_m([0.0, 0.0], SECTORS, HALF)
        fine = np.linspace(-HALF, HALF, 801)
        rays = circle.ray_cast_m([0.0, 0.0], (SECTORS[:, None] + fine[None, :]).ravel()).reshape(72, -1)
        check_close(exact, rays.min(axis=1))
    if wall.clearance_m([0.0, 0.0]) > 0.05:
        exact = wall.window_ranges_m([0.0, 0.0], SECTORS, HALF)
        t = np.linspace(0.0, 1.0, 20001)
        pts = np.array([wx, wy]) + t[:, None] * (np.array(end) - np.array([wx, wy]))
        bearing = np.arctan2(pts[:, 1], pts[:, 0])
        off = np.abs((bearing[None, :] - SECTORS[:, None] + np.pi) % (2 * np.pi) - np.pi)
        dist = np.where(off <= HALF, np.hypot(pts[:, 0], pts[:, 1])[None, :], np.inf)
        check_close(exact, dist.min(axis=1))


def check_close(exact: np.ndarray, sampled: np.ndarray) -> None:
    both = np.isfinite(exact) & np.isfinite(sampled)
    assert np.all(exact[both] <= sampled[both] + 1e-9)  # never farther than any sample
    assert np.all(sampled[both] - exact[both] < 0.02)  # and attained, up to the sampling step
    assert not np.any(np.isinf(exact) & np.isfinite(sampled))  # a window with a hit is never empty


def test_clearance_heights_and_nearest() -> None:
    w = World.from_obstacles([[10.0, 0.0], [0.0, 3.0]], [1.0, 0.5], heights_m=[math.inf, 2.0])
    assert w.clearance_m([0.0, 0.0]) == pytest.approx(2.5)
    assert w.clearance_m([0.0, 0.0], alt_m=3.0) == pytest.approx(9.0)  # above the short one
    idx, dist = w.nearest_obstacle([0.0, 0.0])
    assert idx == 1 and dist == pytest.approx(2.5)
    assert World.empty().clearance_m([0.0, 0.0]) == math.inf
    pts, d = w.nearest_points_ne_m([0.0, 0.0])
    np.testing.assert_allclose(pts, [[9.0, 0.0], [0.0, 2.5]])
    np.testing.assert_allclose(d, [9.0, 2.5])


def test_invalid_worlds_raise() -> None:
    with pytest.raises(ConfigError, match="radii"):
        World.from_obstacles([[0.0, 0.0]], -1.0)
    with pytest.raises(ConfigError, match="finite"):
        World.from_obstacles([[math.nan, 0.0]], 0.0)
    with pytest.raises(ConfigError, match="unknown top-level"):
        world_from_mapping({"cylinders": []})
    with pytest.raises(ConfigError, match=r"cylinder\[0\] has unknown keys"):
        world_from_mapping({"cylinder": [{"ne_m": [1, 2], "radius": 1}]})
    with pytest.raises(ConfigError, match="radius_m must be >= 0"):
        world_from_mapping({"cylinder": [{"ne_m": [1, 2], "radius_m": -1}]})
    with pytest.raises(ConfigError, match="no example world"):
        load_world("nonexistent-world")
    for bad in ([[0, 0]], [[0, 0], [0, 5]], [[0, 0], [5, "x"]], "0,0,5,5", [[0, 0], [5, math.inf]]):
        with pytest.raises(ConfigError, match="area_ne_m"):
            world_from_mapping({"area_ne_m": bad})
    with pytest.raises(ConfigError, match=r"goal_ne_m = \[12.0, 1.0\] lies outside area_ne_m"):
        world_from_mapping({"area_ne_m": [[0, 0], [10, 10]], "start_ne_m": [1, 1], "goal_ne_m": [12, 1]})


def test_world_file_polygon_area() -> None:
    """Three or more pairs are a polygon's vertices (``area_ne_m``): kept in order, checked (no crossing edges, an
    area, finite), and the start and goal must lie in it, the concave notch being outside."""
    l_shape = [[0, 0], [20, 0], [20, 8], [8, 8], [8, 20], [0, 20]]
    w = world_from_mapping({"area_ne_m": l_shape, "start_ne_m": [18, 2], "goal_ne_m": [2, 18]})
    assert w.area_ne_m == tuple((float(n), float(e)) for n, e in l_shape)
    assert w.describe()["area_ne_m"] == [[float(n), float(e)] for n, e in l_shape]
    with pytest.raises(ConfigError, match=r"goal_ne_m = \[15.0, 15.0\] lies outside area_ne_m = \[\[0.0, 0.0\]"):
        world_from_mapping({"area_ne_m": l_shape, "start_ne_m": [18, 2], "goal_ne_m": [15, 15]})
    for bad in ([[0, 0], [5, 5], [5, 0], [0, 5]], [[0, 0], [5, 0], [10, 0]], [[0, 0], [5, 0], [5, math.nan]]):
        with pytest.raises(ConfigError, match="area_ne_m"):
            world_from_mapping({"area_ne_m": bad})


def test_world_file_keep_out_zones() -> None:
    """``[[keepout]]`` tables: polygons kept in order, checked, and no start or goal in one."""
    data = {
        "keepout": [{"points_ne_m": [[7, -3], [13, -3], [13, 3], [7, 3]]}],
        "start_ne_m": [0, 0],
        "goal_ne_m": [20, 0],
    }
    w = world_from_mapping(data)
    assert w.keepouts_ne_m == (((7.0, -3.0), (13.0, -3.0), (13.0, 3.0), (7.0, 3.0)),)
    assert w.describe()["keepouts_ne_m"] == [[[7.0, -3.0], [13.0, -3.0], [13.0, 3.0], [7.0, 3.0]]]
    assert w.n_obstacles == 0  # no obstacle: nothing marks it
    with pytest.raises(ConfigError, match=r"goal_ne_m = \[10.0, 0.0\] lies in a keep-out zone"):
        world_from_mapping({**data, "goal_ne_m": [10, 0]})
    for bad in ([{"points_ne_m": [[0, 0], [1, 1]]}], [{"points_ne_m": [[0, 0], [1, 1], [1, 0]], "height_m": 3}]):
        with pytest.raises(ConfigError, match="keep"):
            world_from_mapping({"keepout": bad})


def test_examples_load_and_start_is_clear() -> None:
    names = sorted(p.stem for p in EXAMPLES_DIR.glob("*.toml"))
    assert names == [
        "corridor",
        "corridor-bend",
        "forest",
        "forest-dense",
        "rooms",
        "slit",
        "u-trap",
        "u-trap-goal",
        "wall",
        "wall-gap",
        "yard-l",
    ]
    for name in names:
        w = load_world(name)
        assert w.n_obstacles > 0
        assert w.start_ne_m is not None and w.goal_ne_m is not None
        assert w.clearance_m(w.start_ne_m) > 1.0
        assert w.clearance_m(w.goal_ne_m) > 1.0
        if w.area_ne_m is not None:  # a flying area holds the start and the goal
            for n, e in (w.start_ne_m, w.goal_ne_m):
                assert inside_area(w.area_ne_m, n, e)
    # the closed arenas, and the L-shaped yard (a polygon)
    assert {n for n in names if load_world(n).area_ne_m is not None} == {"rooms", "wall-gap", "yard-l"}
    assert is_polygon(load_world("yard-l").area_ne_m or (0.0, 0.0, 1.0, 1.0))


def test_world_file_format(tmp_path: Path) -> None:
    path = tmp_path / "w.toml"
    path.write_text(
        """
name = "t"
start_ne_m = [1, 2]
area_ne_m = [[-1, -2], [30, 31.5]]
[[cylinder]]
ne_m = [5, 5]
radius_m = 0.5
height_m = 3
[[wall]]
from_ne_m = [0, 10]
to_ne_m = [10, 10]
thickness_m = 0.2
[[polygon]]
points_ne_m = [[20, 20], [20, 25], [25, 25]]
[random_field]
preset = "reference"
obstacles = 7
seed = 3
"""
    )
    w = load_world(path)
    assert w.name == "t" and w.start_ne_m == (1.0, 2.0)
    assert w.area_ne_m == (-1.0, -2.0, 30.0, 31.5)  # kept when the random field is merged in
    assert w.describe()["area_ne_m"] == [-1.0, -2.0, 30.0, 31.5]
    assert w.n_circles == 1 + 7
    assert w.n_walls == 1 + 3  # a closed triangle has 3 sides
    assert w.circle_heights_m[0] == 3.0 and np.isinf(w.circle_heights_m[1:]).all()
    np.testing.assert_allclose(w.circles_ne_m[1:], paper_field("reference", 7, np.random.default_rng(3)).circles_ne_m)


def test_paper_field_presets_are_seeded_and_bounded() -> None:
    a = paper_field("reference", 40, np.random.default_rng(5))
    b = paper_field("reference", 40, np.random.default_rng(5))
    np.testing.assert_array_equal(a.circles_ne_m, b.circles_ne_m)
    assert a.n_circles == 40 and ((a.circles_ne_m >= 5) & (a.circles_ne_m <= 20)).all()
    p = paper_field("paper", 500, np.random.default_rng(1))
    assert ((p.circles_ne_m >= 0) & (p.circles_ne_m <= 30)).all()
    assert p.circles_ne_m.min() < 1 and p.circles_ne_m.max() > 29
    assert a.start_ne_m == PAPER_START_NE_M and a.goal_ne_m == PAPER_TARGET_NE_M
    counts = {paper_field("reference", "mid", np.random.default_rng(s)).n_circles for s in range(40)}
    assert min(counts) >= 45 and max(counts) <= 70 and len(counts) > 5
    assert parse_field_spec("paper:mid") == ("paper", "mid")
    assert parse_field_spec("reference:40") == ("reference", 40)
    with pytest.raises(ConfigError, match="PRESET"):
        parse_field_spec("nope:3")
