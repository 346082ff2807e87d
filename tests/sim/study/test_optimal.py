"""The full-knowledge grid optimum (sim/study/optimal.py) and the bundled worlds it must solve."""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest

from apf_companion.planning.area import leaves_area
from sim.study.optimal import optimal_path, optimal_path_points
from sim.world import World, load_world
from sim.world.files import EXAMPLES_DIR
from sim.world.geometry import clearance_many_m, segment_clearance_m, surface_samples_ne_m

BUNDLED = sorted(p.stem for p in EXAMPLES_DIR.glob("*.toml"))
NEW_WORLDS = ("u-trap-goal", "wall-gap", "corridor-bend", "rooms", "forest-dense", "slit")


def test_new_worlds_are_bundled() -> None:
    assert set(NEW_WORLDS) <= set(BUNDLED)


def test_empty_world_optimum_is_the_straight_line() -> None:
    o = optimal_path(World.empty(), (3.0, 3.0), (22.0, 22.0))
    assert o.length_m == pytest.approx(math.hypot(19.0, 19.0), abs=1e-9)
    # The 16-connected grid path alone is within its 2.7 % bound of the straight line.
    assert math.hypot(19.0, 19.0) <= o.grid_length_m <= 1.027 * math.hypot(19.0, 19.0)


def test_detour_around_one_disc_matches_the_analytic_optimum() -> None:
    # Tangent - arc - tangent around a disc of radius rho = radius + clearance, start and goal d from its centre.
    radius, clearance, d = 0.5, 0.35, 5.0
    rho = radius + clearance
    alpha = math.acos(rho / d)
    exact = 2.0 * math.sqrt(d * d - rho * rho) + rho * (math.pi - 2.0 * alpha)
    world = World.from_obstacles([[5.0, 0.0]], radius)
    o = optimal_path(world, (0.0, 0.0), (10.0, 0.0), clearance_m=clearance, resolution_m=0.1)
    assert exact - 1e-6 <= o.length_m <= 1.001 * exact
    assert segment_clearance_m(world, o.path_ne_m[:-1], o.path_ne_m[1:]).min() >= clearance - 1e-9


def test_wrapping_a_large_disc_stays_within_half_a_percent() -> None:
    # Start and goal 3 m either side of a 1 m disc: the path wraps 53 degrees of the 1.35 m clearance circle.
    rho, d = 1.35, 3.0
    exact = 2.0 * math.sqrt(d * d - rho * rho) + rho * (math.pi - 2.0 * math.acos(rho / d))
    world = World.from_obstacles([[0.0, 0.0]], 1.0)
    for resolution in (0.1, 0.2):
        o = optimal_path(world, (-3.0, 0.0), (3.0, 0.0), clearance_m=0.35, resolution_m=resolution)
        assert exact - 1e-6 <= o.length_m <= 1.005 * exact


@pytest.mark.parametrize("name", BUNDLED)
def test_every_bundled_world_is_solvable_with_clearance(name: str) -> None:
    world = load_world(name)
    assert world.start_ne_m is not None
    assert world.goal_ne_m is not None
    # Start and goal themselves are clear of the collision radius.
    assert clearance_many_m(world, [world.start_ne_m, world.goal_ne_m]).min() > 0.25
    o = optimal_path(world)
    assert math.isfinite(o.length_m)
    assert o.length_m >= math.dist(world.start_ne_m, world.goal_ne_m) - 1e-9
    assert o.length_m <= o.grid_length_m + 1e-9
    # Each segment keeps the clearance (shortcuts exactly; a leftover grid edge may sag by its sagitta).
    assert segment_clearance_m(world, o.path_ne_m[:-1], o.path_ne_m[1:]).min() >= o.clearance_m - 0.02
    assert surface_samples_ne_m(world).shape[0] > 0


def test_slit_is_too_narrow_at_the_default_clearance_but_not_at_a_small_one() -> None:
    world = load_world("slit")
    wide = optimal_path(world)
    assert wide.length_m > 20.0  # the detour round the east end
    narrow = optimal_path(world, clearance_m=0.15)  # 0.4 m slit > 2 * 0.15 m
    assert narrow.length_m == pytest.approx(16.0, abs=1e-6)


def test_enclosed_goal_has_no_path() -> None:
    box = World.polygon_segments([[8, -2], [12, -2], [12, 2], [8, 2]])
    world = World.from_obstacles(walls_ne_m=box, wall_thickness_m=0.2)
    o = optimal_path(world, (0.0, 0.0), (10.0, 0.0))
    assert math.isinf(o.length_m)
    assert o.path_ne_m.shape == (0, 2)


def test_point_field_optimum_keeps_clearance_from_every_point() -> None:
    rng = np.random.default_rng(3)
    pts = rng.uniform(5.0, 20.0, size=(70, 2))
    o = optimal_path_points(pts, (3.0, 3.0), (22.0, 22.0))
    assert math.hypot(19, 19) <= o.length_m < 1.2 * math.hypot(19, 19)
    world = World.from_obstacles(pts, 0.0)
    assert segment_clearance_m(world, o.path_ne_m[:-1], o.path_ne_m[1:]).min() >= 0.35 - 0.02


def test_surface_samples_lie_on_the_true_surfaces() -> None:
    for name in ("rooms", "forest-dense", "slit"):
        world = load_world(name)
        pts = surface_samples_ne_m(world, 0.2)
        d = clearance_many_m(world, pts)
        # On its own obstacle's surface; where walls meet, a sample may lie inside the other wall.
        assert d.max() < 1e-9
        assert np.mean(np.abs(d) < 1e-9) > 0.95
        # No two neighbours along an outline farther apart than the spacing.
        nearest = np.linalg.norm(pts[:, None] - pts[None], axis=-1)
        np.fill_diagonal(nearest, np.inf)
        assert nearest.min(axis=1).max() <= 0.2 + 1e-9


#: A 6 m square keep-out zone across the straight line (0, 0) -> (20, 0), nothing in it to see.
SQUARE = ((7.0, -3.0), (13.0, -3.0), (13.0, 3.0), (7.0, 3.0))


def test_the_optimum_goes_round_keep_out_zones_and_stays_in_the_flying_area() -> None:
    """Zones bound the optimum as walls of no thickness: round the square at the clearance (tangent - arc of
    0.35 m round its corner - edge - arc - tangent, within 0.1 %); in an L-shaped area the optimum turns round the
    inner corner instead of cutting across the neighbour's plot; --no-area's case drops the zones."""
    from sim.study.worldstudy import WorldCase, without_area

    world = World(start_ne_m=(0.0, 0.0), goal_ne_m=(20.0, 0.0), keepouts_ne_m=(SQUARE,))
    o = optimal_path(world, clearance_m=0.35)
    d, r = math.hypot(7.0, 3.0), 0.35
    arc = math.atan2(3.0, 7.0) + math.asin(r / d)  # from the tangent's heading to the edge's
    exact = 2.0 * (math.sqrt(d * d - r * r) + r * arc) + 6.0
    assert exact - 1e-6 <= o.length_m <= 1.001 * exact
    walls = World(walls_ne_m=World.polygon_segments(SQUARE), wall_thickness_m=np.zeros(4), wall_heights_m=np.ones(4))
    assert segment_clearance_m(walls, o.path_ne_m[:-1], o.path_ne_m[1:]).min() >= 0.35 - 1e-9
    case = WorldCase(label="sq", world=world, samples_ne_m=np.zeros((0, 2)), optimum_m=o.length_m)
    assert without_area(case).optimum_m == pytest.approx(20.0)
    ell = ((-3.0, -3.0), (23.0, -3.0), (23.0, 6.0), (9.0, 6.0), (9.0, 23.0), (-3.0, 23.0))
    yard = World(start_ne_m=(20.0, 1.0), goal_ne_m=(2.0, 20.0), area_ne_m=ell)
    inner = np.array([9.0, 6.0])
    by_corner = float(np.hypot(*(inner - (20.0, 1.0))) + np.hypot(*(inner - (2.0, 20.0))))
    o = optimal_path(yard)
    assert by_corner < o.length_m < 1.01 * by_corner  # a bend 0.35 m inside the corner, not an arc
    assert not leaves_area(ell, o.path_ne_m[:-1], o.path_ne_m[1:], 0.0).any()
    assert optimal_path(dataclasses.replace(yard, area_ne_m=None)).length_m == pytest.approx(math.hypot(18.0, 19.0))
