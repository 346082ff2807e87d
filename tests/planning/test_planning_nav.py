"""bapf-nav and the bendyruler baseline: clearance, escape, give-up, batch equality, determinism, study rows."""

from __future__ import annotations

import dataclasses
import heapq
import math
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from apf_companion.errors import ConfigError
from apf_companion.planning import (
    ALL_PLANNER_NAMES,
    BapfNavPlanner,
    BendyRulerPlanner,
    DecisionReason,
    GiveUp,
    NavMode,
    NavState,
    PlannerName,
    PlannerParams,
    StatefulPlanner,
    get_planner,
    inside_area,
)
from apf_companion.planning.clearance import near_obstacles, segment_clearance_sq
from apf_companion.planning.navescape import EscapeMaps
from apf_companion.planning.navfield import NavGrid
from apf_companion.planning.navsight import LineOfSight
from sim.study.config import Density, StudyConfig
from sim.study.engine import SerialExecutor, chunk_generators, run_study, simulate
from sim.study.metrics import Outcome, summarize
from sim.study.worlds import WorldBatch, draw_worlds
from sim.world.files import example_world_path, load_world
from sim.world.geometry import surface_samples_ne_m
from sim.world.scan import ScanMemory

PRODUCT = ("bapf-nav", "bendyruler")


def _segment_clearance(p: np.ndarray, q: np.ndarray, obstacles: np.ndarray) -> float:
    """Exact min distance from the segment p -> q to the points (reference, one obstacle at a time)."""
    v = q - p
    best = math.inf
    for o in obstacles:
        t = min(1.0, max(0.0, float(np.dot(o - p, v) / np.dot(v, v))))
        best = min(best, float(np.linalg.norm(p + t * v - o)))
    return best


# --- names and parameters -----------------------------------------------------------------------------------


def test_names_are_defined_once_and_strings_still_work() -> None:
    assert tuple(ALL_PLANNER_NAMES[-2:]) == PRODUCT
    assert isinstance(get_planner("bapf-nav"), BapfNavPlanner)
    assert isinstance(get_planner(PlannerName.BENDYRULER), BendyRulerPlanner)
    with pytest.raises(ConfigError, match="bapf-nav"):
        get_planner("bapf-nvа")


@pytest.mark.parametrize(
    ("field", "value"),
    [
        ("vehicle_radius_m", 0.0),
        ("safety_margin_m", -0.1),
        ("noise_std_m", math.nan),
        ("noise_k", -1.0),
        ("nav_hold_ratio", 0.5),
        ("nav_hold_angle_deg", 200.0),
        ("nav_cell_m", 0.0),
        ("nav_grid_m", 1.0),
        ("nav_patience_steps", 0),
        ("nav_replan_steps", 2.5),
        ("nav_sight_m", -1.0),
        ("br_cont_ratio", 0.9),
        ("br_margin_max_m", 0.0),
    ],
)
def test_product_parameters_are_validated(field: str, value: object) -> None:
    with pytest.raises(ConfigError, match=field):
        PlannerParams(**{field: value})  # type: ignore[arg-type]


def test_clearance_is_radius_plus_margins() -> None:
    p = PlannerParams(vehicle_radius_m=0.3, safety_margin_m=0.2, noise_std_m=0.1, noise_k=2.0)
    assert p.clearance_m == pytest.approx(0.7)


# --- the sweep ----------------------------------------------------------------------------------------------

_coords = st.floats(min_value=-1.6, max_value=1.6, allow_nan=False)


@settings(max_examples=150, deadline=None)
@given(
    dim=st.sampled_from([2, 3]),
    obstacles=st.lists(st.tuples(_coords, _coords, _coords), min_size=1, max_size=40),
    goal=st.tuples(st.floats(-30, 30), st.floats(-30, 30), st.floats(-5, 5)),
    steps=st.integers(1, 4),
)
def test_no_move_ends_or_passes_within_the_clearance(
    dim: int, obstacles: list[tuple[float, float, float]], goal: tuple[float, float, float], steps: int
) -> None:
    """From a point outside the clearance, every move (several in a row) keeps radius + margins on its whole
    segment, whatever the obstacles and the goal; only when no move keeps them (boxed in) is the noise margin
    spent, never the radius + safety margin."""
    params = PlannerParams(dim=dim)
    planner = get_planner("bapf-nav", params)
    obs = np.asarray(obstacles, dtype=np.float64)[:, :dim]
    pos = np.zeros(dim)
    target = np.asarray(goal, dtype=np.float64)[:dim]
    clearance = params.clearance_m
    if np.min(np.linalg.norm(obs - pos, axis=1)) < clearance:
        obs = obs[np.linalg.norm(obs - pos, axis=1) >= clearance]
        if obs.shape[0] == 0:
            return
    for _ in range(steps):
        decision = planner.step(pos, target, obs)
        if decision.next_point_m is None:
            break
        swept = _segment_clearance(pos, decision.next_point_m, obs)
        assert swept >= params.vehicle_radius_m + params.safety_margin_m - 1e-9
        if decision.n_safe > 0:  # a squeeze may have left the agent inside C: then it gets no closer
            start = float(np.min(np.linalg.norm(obs - pos, axis=1)))
            assert swept >= min(clearance, start) - 1e-9
        pos = decision.next_point_m


# Obstacles at least 1 mm from the agent: the sweep works on squared distances, |rel|^2 - t (2 rel.o - t |o|^2),
# whose rounding is ~1e-17 m^2 (a few nanometres); a point within that of the vehicle's centre (it has collided;
# ranges never come closer than a sensor's range_min) makes "no closer than d0" meaningless (docs/planner.md).
_not_on_the_agent = st.tuples(_coords, _coords).filter(lambda p: math.hypot(p[0], p[1]) >= 1e-3)


@settings(max_examples=80, deadline=None)
@given(obstacles=st.lists(_not_on_the_agent, min_size=1, max_size=20))
def test_from_inside_the_clearance_a_move_never_gets_closer(obstacles: list[tuple[float, float]]) -> None:
    """Noise may put the agent inside the clearance: its next move gets no closer anywhere and ends farther out."""
    params = PlannerParams()
    obs = np.vstack([[0.3, 0.0], np.asarray(obstacles)])  # one obstacle inside the 0.6 m clearance
    d0 = float(np.min(np.linalg.norm(obs, axis=1)))
    decision = get_planner("bapf-nav", params).step(np.zeros(2), np.array([20.0, 0.0]), obs)
    if decision.next_point_m is not None and decision.n_safe > 0:
        assert _segment_clearance(np.zeros(2), decision.next_point_m, obs) >= d0 - 1e-9
        assert float(np.min(np.linalg.norm(obs - decision.next_point_m, axis=1))) > d0
    elif decision.next_point_m is not None:  # boxed in: squeezes out, keeping radius + safety margin
        swept = _segment_clearance(np.zeros(2), decision.next_point_m, obs)
        assert swept >= params.vehicle_radius_m + params.safety_margin_m - 1e-9


def test_hundreds_of_wall_points_are_respected() -> None:
    """A dense wall of 400 points across the way: the planner slides along it at the clearance, never closer."""
    wall = np.stack([np.full(400, 5.0), np.linspace(-20.0, 20.0, 400)], axis=1)
    planner = get_planner("bapf-nav")
    pos = np.zeros(2)
    for _ in range(60):
        d = planner.step(pos, np.array([10.0, 0.5]), wall)
        if d.next_point_m is None:
            break
        assert d.n_safe > 0
        assert _segment_clearance(pos, d.next_point_m, wall) >= planner.params.clearance_m - 1e-9
        pos = d.next_point_m


# --- the navigation potential -------------------------------------------------------------------------------


def _dijkstra(grid: NavGrid, origin: np.ndarray, blocked: np.ndarray, goal: np.ndarray) -> np.ndarray:
    n, h = grid.n, grid.cell_m
    blk = blocked.copy()
    gi, gj = (int(v) for v in np.floor((goal - origin) / h))
    inside = 0 <= gi < n and 0 <= gj < n
    if inside:
        blk[gi * n + gj] = False
    dist = np.full(n * n, np.inf)
    heap: list[tuple[float, int]] = []
    for i in range(n):
        for j in range(n):
            near = inside and abs(i - gi) <= 1 and abs(j - gj) <= 1
            edge = i in (0, n - 1) or j in (0, n - 1)
            if not blk[i * n + j] and (near or edge):
                v = math.hypot(origin[0] + (i + 0.5) * h - goal[0], origin[1] + (j + 0.5) * h - goal[1])
                if edge and not near:
                    v += n * h if inside else 0.0
                elif edge and near:
                    v = min(v, v + (n * h if inside else 0.0))
                dist[i * n + j] = v
                heap.append((v, i * n + j))
    heapq.heapify(heap)
    while heap:
        v, c = heapq.heappop(heap)
        if v > dist[c]:
            continue
        i, j = divmod(c, n)
        for di in (-1, 0, 1):
            for dj in (-1, 0, 1):
                ii, jj = i + di, j + dj
                if (di or dj) and 0 <= ii < n and 0 <= jj < n and not blk[ii * n + jj]:
                    nv = v + h * (math.sqrt(2.0) if di and dj else 1.0)
                    if nv < dist[ii * n + jj] - 1e-12:
                        dist[ii * n + jj] = nv
                        heapq.heappush(heap, (nv, ii * n + jj))
    return dist


def test_blocked_cells_are_those_within_the_radius_for_each_radius() -> None:
    """One stencil for several radii marks, per radius, exactly the cells whose centre lies closer than it to a
    valid point (brute force over all cells), points near and beyond the grid's sides included."""
    grid = NavGrid(0.5, 12.0)
    rng = np.random.default_rng(5)
    origins = np.array([[0.0, 0.0], [-3.0, 2.0]])
    obs = rng.uniform(-5.0, 17.0, size=(2, 90, 2))  # some far beyond the sides
    valid = rng.random((2, 90)) < 0.8
    radii = (0.8, 1.3)
    centres = (np.stack(np.divmod(np.arange(grid.size), grid.n), axis=1) + 0.5) * grid.cell_m
    for radius, got in zip(radii, grid.blocked_within(origins, obs, valid, radii), strict=True):
        for b in range(2):
            gap = origins[b] + centres[:, None, :] - obs[b][valid[b]][None, :, :]
            ref = (np.einsum("cpd,cpd->cp", gap, gap) < radius * radius).any(axis=1)
            assert np.array_equal(got[b], ref)
        assert np.array_equal(got, grid.blocked(origins, obs, valid, radius))


@pytest.mark.parametrize(
    "goal",
    [(10.0, 9.0), (40.0, -3.0), (5.25, 7.75), (0.1, 6.1)],
    ids=["goal-inside", "goal-outside", "goal-on-a-cell-centre", "goal-in-an-edge-cell"],
)
def test_fields_equal_a_plain_dijkstra(goal: tuple[float, float]) -> None:
    """scipy's Dijkstra over the prepared graph equals a heap search cell by cell, including a seed of value 0
    (the goal on a cell centre: an explicit zero weight is an edge) and an edge cell near the goal (two seeds)."""
    grid = NavGrid(0.5, 12.0)
    rng = np.random.default_rng(3)
    origins = np.zeros((3, 2))
    obs = rng.uniform(0.0, 12.0, size=(3, 40, 2))
    blocked = grid.blocked(origins, obs, np.ones((3, 40), dtype=bool), 0.8)
    goals = np.tile(goal, (3, 1))
    dist = grid.distances(origins, blocked, goals)
    for b in range(3):
        ref = _dijkstra(grid, origins[b], blocked[b], goals[b])
        assert np.array_equal(np.isfinite(ref), np.isfinite(dist[b]))
        finite = np.isfinite(ref)
        np.testing.assert_allclose(dist[b][finite], ref[finite], atol=1e-7)


# --- escape and give-up on worlds ---------------------------------------------------------------------------


def _fly_world(
    name: str, dim: int = 2, max_steps: int = 1500, shift_east_m: float = 0.0, area: bool = False
) -> tuple[str, np.ndarray, float]:
    """Fly a bundled world with a simulated 8 m range scanner (72 rays) and a remembered point cloud (no noise);
    ``shift_east_m`` moves its start and goal east; ``area``: plan over the world file's flying area.

    Returns (how it ended, final position, lowest clearance to the remembered points)."""
    world = load_world(example_world_path(name))
    params = PlannerParams(dim=dim, nav_area_ne_m=world.area_ne_m if area else None)
    planner = get_planner("bapf-nav", params)
    shift = np.array([0.0, shift_east_m])
    start = np.array(world.start_ne_m if world.start_ne_m is not None else (3.0, 3.0), dtype=np.float64) + shift
    goal = np.array(world.goal_ne_m if world.goal_ne_m is not None else (22.0, 22.0), dtype=np.float64) + shift
    pos = np.concatenate([start, [5.0]])[:dim]
    target = np.concatenate([goal, [5.0]])[:dim]
    scanner = ScanMemory(world)
    lowest = math.inf
    for _ in range(max_steps):
        if np.linalg.norm(pos[:2] - goal) <= 0.7:
            return "arrived", pos, lowest
        cloud = scanner.scan(pos)
        if dim == 3:
            cloud = np.concatenate([cloud, np.full((cloud.shape[0], 1), 5.0)], axis=1)
        d = planner.step(pos, target, cloud)
        if d.reason is DecisionReason.GAVE_UP:
            return "gave-up", pos, lowest
        if d.next_point_m is not None:
            if cloud.shape[0]:
                lowest = min(lowest, _segment_clearance(pos, d.next_point_m, cloud))
            pos = d.next_point_m
    return "running", pos, lowest


@pytest.mark.parametrize("name", ["u-trap", "wall", "corridor"])
def test_escape_reaches_the_goal_of_each_bundled_world(name: str) -> None:
    outcome, _, lowest = _fly_world(name)
    assert outcome == "arrived"
    assert lowest >= PlannerParams().clearance_m - 1e-9


@pytest.mark.parametrize("shift_east_m", [-8.0, -6.0, -5.0, 0.0])
def test_wall_gap_from_the_closed_side_comes_back_and_arrives(shift_east_m: float) -> None:
    """wall-gap with start and goal moved west along the crossing wall: the nearer end is the closed one, so the
    agent tries it first and has to come back past where it met the wall. The edge cells it passed on its way
    are no exits (``nav_seen_m``). Session 20 tried them as exits at a cost of 2 m and 4 m more (wall-gap's
    study path 1.627 -> 1.531 / 1.542): from -5 to -8 m the agent then walked to and fro and gave up."""
    outcome, pos, lowest = _fly_world("wall-gap", shift_east_m=shift_east_m)
    assert outcome == "arrived", pos
    assert lowest >= PlannerParams().clearance_m - 1e-9


@pytest.mark.parametrize("shift_east_m", [-8.0, -5.0, 0.0, 4.0])
@pytest.mark.parametrize("name", ["wall-gap", "rooms"])
def test_worlds_with_a_flying_area_arrive_from_either_side(name: str, shift_east_m: float) -> None:
    """The same flights over the world file's flying area (``nav_area_ne_m``): the grid holds the whole arena and
    has no exits, so the closed end is closed once it is seen and the agent turns back there. Starts and goals
    moved along the walls, so that either end is the nearer one."""
    outcome, pos, lowest = _fly_world(name, shift_east_m=shift_east_m * (0.25 if name == "rooms" else 1.0), area=True)
    assert outcome == "arrived", pos
    assert lowest >= PlannerParams().clearance_m - 1e-9


#: yard-l's flying area: an L whose notch (north 9-23, east 6-23) lies across the straight line.
_YARD_L = ((-3.0, -3.0), (23.0, -3.0), (23.0, 6.0), (9.0, 6.0), (9.0, 23.0), (-3.0, 23.0))


def _outside_m(polygon: tuple[tuple[float, float], ...], point: np.ndarray) -> float:
    """How far ``point`` lies outside ``polygon`` (0 inside) [m]: its distance to the nearest edge."""
    return 0.0 if inside_area(polygon, point[0], point[1]) else _edge_distance_m(polygon, point)


def _edge_distance_m(polygon: tuple[tuple[float, float], ...], point: np.ndarray) -> float:
    """The distance from ``point`` (north, east, ...) to the nearest edge of ``polygon`` [m]."""
    a = np.array(polygon)
    b = np.roll(a, -1, axis=0)
    t = np.clip(np.einsum("vd,vd->v", point[:2] - a, b - a) / np.einsum("vd,vd->v", b - a, b - a), 0.0, 1.0)
    return float(np.min(np.linalg.norm(a + t[:, None] * (b - a) - point[:2], axis=1)))


@pytest.mark.parametrize("dim", [2, 3])
def test_a_concave_area_with_nothing_to_see_is_flown_round_its_notch(dim: int) -> None:
    """yard-l without its hedge: a property line that no sensor sees. The straight line from start to goal
    crosses the notch, so it is blocked from the first step (``area.leaves_area``) and the agent follows the
    area's field round the inner corner, inside the polygon and never nearer its edges than C less a cell
    (``navzones``, ``leaves_area``'s margin round the inner corner); without the area it cuts straight across the
    notch, 3 m inside it."""
    start, goal = np.array([20.0, 1.0, 5.0])[:dim], np.array([2.0, 20.0, 5.0])[:dim]
    none = np.zeros((0, dim))
    worst, nearest = {}, math.inf
    for area in (_YARD_L, None):
        planner = get_planner("bapf-nav", PlannerParams(dim=dim, nav_area_ne_m=area))
        pos, worst[area is None], path = start, 0.0, 0.0
        for _ in range(200):
            if np.linalg.norm(pos[:2] - goal[:2]) <= 0.7:
                break
            d = planner.step(pos, goal, none)
            assert d.next_point_m is not None, d.reason
            path += float(np.linalg.norm(d.next_point_m - pos))
            pos = d.next_point_m
            worst[area is None] = max(worst[area is None], _outside_m(_YARD_L, pos))
            if area is not None:
                nearest = min(nearest, _edge_distance_m(_YARD_L, pos))
        assert np.linalg.norm(pos[:2] - goal[:2]) <= 0.7
        if area is not None:  # round the corner at (9, 6): 12.1 m + 15.7 m, straight 26.2 m
            assert 27.0 <= path <= 29.5, path
    assert worst[False] == 0.0, worst  # inside all the way: the area's edges are kept at C, less a cell
    assert nearest >= PlannerParams().clearance_m - PlannerParams().nav_cell_m
    assert worst[True] >= 2.5


@pytest.mark.parametrize("dim", [2, 3])
def test_an_area_wider_than_the_fixed_grid_is_planned_on_the_moving_grid(dim: int) -> None:
    """yard-l's L four times as large (104 m across, over the fixed grid's 256 cells of 0.3 m): the grid moves
    with the agent, its cells outside the L closed, and the agent goes round the inner corner all the same,
    inside the L and never nearer its edges than C less a cell, within 5 % of the corner route."""
    area = tuple((4.0 * n, 4.0 * e) for n, e in _YARD_L)
    params = PlannerParams(dim=dim, nav_area_ne_m=area)
    planner = get_planner("bapf-nav", params)
    grid = NavGrid(params.nav_cell_m, params.nav_grid_m, area)
    assert grid.fixed_origin_m is None and grid.exits and grid.n == 54  # nav_grid_m's 16 m, not 104 m
    start, goal = np.array([80.0, 4.0, 5.0])[:dim], np.array([8.0, 80.0, 5.0])[:dim]
    pos, path, nearest = start, 0.0, math.inf
    for _ in range(600):
        if np.linalg.norm(pos[:2] - goal[:2]) <= 0.7:
            break
        d = planner.step(pos, goal, np.zeros((0, dim)))
        assert d.next_point_m is not None, d.reason
        path += float(np.linalg.norm(d.next_point_m - pos))
        pos = d.next_point_m
        assert _outside_m(area, pos) == 0.0
        nearest = min(nearest, _edge_distance_m(area, pos))
    assert np.linalg.norm(pos[:2] - goal[:2]) <= 0.7
    corner = math.dist((80.0, 4.0), (36.0, 24.0)) + math.dist((36.0, 24.0), (8.0, 80.0))  # 48.3 + 62.6 m
    assert corner <= path <= 1.05 * corner, (path, corner)
    assert nearest >= params.clearance_m - params.nav_cell_m


#: A 6 m x 6 m keep-out square across the straight line from (0, 0) to (20, 0), with nothing in it to see.
_SQUARE = ((7.0, -3.0), (13.0, -3.0), (13.0, 3.0), (7.0, 3.0))


@pytest.mark.parametrize("area", [None, (-5.0, -12.0, 25.0, 12.0)], ids=["moving-grid", "over-an-area"])
@pytest.mark.parametrize("dim", [2, 3])
def test_a_keep_out_zone_with_nothing_to_see_is_flown_round(dim: int, area: Any) -> None:
    """A keep-out zone (a fence's exclusion zone) across the straight line, with no obstacle in it: the line
    meets the zone from the first step (``area.meets_keepout``), and the agent goes round on the field, whose
    cells in the zone and within C of its edges are blocked, never nearer than C less a cell; without the zone it
    flies straight through.
    A target in the zone gives up at once."""
    start, goal = np.zeros(dim), np.array([20.0, 0.0, 0.0])[:dim]
    none = np.zeros((0, dim))
    deepest = {}
    for keepouts in ((_SQUARE,), ()):
        planner = get_planner("bapf-nav", PlannerParams(dim=dim, nav_area_ne_m=area, nav_keepout_ne_m=keepouts))
        pos, depth = start, -math.inf
        for _ in range(200):
            if np.linalg.norm(pos[:2] - goal[:2]) <= 0.7:
                break
            d = planner.step(pos, goal, none)
            assert d.next_point_m is not None, d.reason
            pos = d.next_point_m
            n, e = float(pos[0]), float(pos[1])
            depth = max(depth, min(n - 7.0, 13.0 - n, e + 3.0, 3.0 - e))  # > 0: inside, by this much
        assert np.linalg.norm(pos[:2] - goal[:2]) <= 0.7
        deepest[bool(keepouts)] = depth
    assert deepest[True] <= -(PlannerParams().clearance_m - PlannerParams().nav_cell_m)  # kept at C, less a cell
    assert deepest[False] >= 2.5  # through the middle (3 m in on the straight line)
    zoned = get_planner("bapf-nav", PlannerParams(dim=dim, nav_area_ne_m=area, nav_keepout_ne_m=(_SQUARE,)))
    assert zoned.step(start, np.array([10.0, 0.0, 0.0])[:dim], none).reason is DecisionReason.GAVE_UP
    assert isinstance(zoned, BapfNavPlanner) and zoned.give_up_cause() is GiveUp.OUTSIDE_AREA


@pytest.mark.parametrize("target", [(30.0, 0.0), (10.0, -12.5), (-3.5, 0.0), (10.0, 12.5)])
def test_a_target_outside_the_flying_area_gives_up_at_once(target: tuple[float, float]) -> None:
    """A target outside ``nav_area_ne_m`` has no way: the first step gives up (the caller reports STUCK) instead
    of flying straight out of the area, on the single-agent and the batch path alike; a target inside moves."""
    params = PlannerParams(nav_area_ne_m=(-3.0, -12.0, 23.0, 12.0))
    single = get_planner("bapf-nav", params)
    batch = BapfNavPlanner(params)
    state = batch.initial_state(2)
    targets = np.array([target, (20.0, 0.0)])
    none = np.zeros((0, 2))
    assert single.step(np.zeros(2), np.array(target), none).reason is DecisionReason.GAVE_UP
    assert isinstance(single, BapfNavPlanner) and single.give_up_cause() is GiveUp.OUTSIDE_AREA
    assert single.step(np.zeros(2), np.array([20.0, 0.0]), none).reason is DecisionReason.GREEDY
    assert single.give_up_cause() is GiveUp.NONE
    for _ in range(2):  # and it stays given up
        bd = batch.step_batch(np.zeros((2, 2)), targets, np.zeros((2, 0, 2)), np.zeros((2, 0), bool), state=state)
        assert [r.reason for r in (bd.row(0), bd.row(1))] == [DecisionReason.GAVE_UP, DecisionReason.GREEDY]
        assert bd.row(0).next_point_m is None
        assert state.gave_up.tolist() == [GiveUp.OUTSIDE_AREA, GiveUp.NONE]


def test_the_line_of_sight_is_blocked_by_surfaces_and_by_near_points() -> None:
    """``LineOfSight.blocked``: a wall across the line blocks it; a lone point on it only within
    ``nav_sight_points_m`` (2 m); a wall beside the line (farther than C) does not, unknown (masked, non-finite)
    rows are ignored, and ``nav_sight_m`` = 0 or a wall beyond it is no block."""
    params = PlannerParams()
    maps = LineOfSight(params, params.clearance_m)
    wall = np.stack([np.full(21, 5.0), np.linspace(-2.0, 2.0, 21)], axis=1)  # north 5, 0.2 m apart
    point = np.array([[5.0, 0.5]])  # 0.5 m east of the line (within C = 0.6 m), 5 m ahead: beyond 2 m
    near = np.array([[1.9, 0.5]])  # the same, 1.9 m ahead
    beside = wall + np.array([0.0, 2.61])  # east 0.61..4.61: just farther than C from the line along east 0
    far = wall + np.array([10.0, 0.0])  # north 15, beyond 8 m
    scenes = [wall, point, near, beside, far, np.full_like(wall, np.nan)]
    width = max(len(x) for x in scenes)
    obstacles = np.full((len(scenes), width, 2), np.nan)
    mask = np.zeros((len(scenes), width), dtype=bool)
    for a, pts in enumerate(scenes):
        obstacles[a, : len(pts)] = pts
        mask[a, : len(pts)] = np.isfinite(pts[:, 0])
    positions = np.zeros((len(scenes), 2))
    targets = np.tile([20.0, 0.0], (len(scenes), 1))
    active = np.ones(len(scenes), dtype=bool)
    blocked = maps.blocked(active, positions, targets, obstacles, mask)
    assert blocked.tolist() == [True, False, True, False, False, False]
    points_off = PlannerParams(nav_sight_points_m=0.0)
    surfaces = LineOfSight(points_off, points_off.clearance_m)
    assert surfaces.blocked(active, positions, targets, obstacles, mask).tolist()[:3] == [True, False, False]
    assert not maps.blocked(~active, positions, targets, obstacles, mask).any()
    off = LineOfSight(PlannerParams(nav_sight_m=0.0), params.clearance_m)
    assert not off.blocked(active, positions, targets, obstacles, mask).any()


def _line(a: tuple[float, float], b: tuple[float, float], spacing_m: float = 0.2) -> np.ndarray:
    n = int(math.hypot(b[0] - a[0], b[1] - a[1]) / spacing_m) + 1
    return np.linspace(a, b, n)


def _room_with_door(shift_m: float) -> np.ndarray:
    """A box 0..16 north x 0..11.9 east split at north 8 by a wall from east 0 to 10.3, the door's other side the
    box's east wall: a 1.6 m door, 0.4 m wide at C = 0.6 m (free cell centres east 10.95 and 11.25). ``shift_m``
    moves the door's two sides east (what range noise does to the points that remember them)."""
    box = [_line((0, 0), (16, 0)), _line((16, 0), (16, 11.9)), _line((0, 0), (0, 11.9))]
    box.append(_line((0, 11.9 + shift_m), (16, 11.9 + shift_m)))  # the east wall, one side of the door
    return np.vstack([*box, _line((8, 0), (8, 10.3 + shift_m))])


def test_a_narrow_door_stays_open_when_its_points_jitter_and_forgotten_walls_stay() -> None:
    """Refreshed potentials keep remembered obstacle cells only where no point known now is near them: the union
    of two fields whose inflated door edges sit a cell apart would close the door (seen in ``apf-sim fly --world
    rooms``: the vehicle turned back in the door and wandered until the service's progress limit). Cells of a
    wall the memory has forgotten, and dead ends the planner marked, are kept."""
    params = PlannerParams()
    maps = EscapeMaps(params, BapfNavPlanner(params).bacteria_offsets_m, params.clearance_m)
    state = NavState.empty(1, 2)
    agent, goal = np.array([[5.0, 10.5]]), np.array([[12.0, 6.0]])
    rows = np.array([0])

    def refresh(points: np.ndarray) -> float:
        maps.refresh(rows, agent, goal, points[None], None, state)
        f = state.field[0]
        return float(maps.grid.sample(f.origin_m, f.dist_m, agent)[0])

    through_door_m = 12.0  # the potential at the agent through the door (about 10 m; any other way is > 30 m)
    assert refresh(_room_with_door(0.0)) < through_door_m
    # the door's points moved by 0.45 m: its free cells are now east 11.55 only (the union of both fields: none)
    assert refresh(_room_with_door(0.45)) < through_door_m
    # A wall the memory forgot (its points gone) stays blocked; the door, still seen, stays open.
    inner = _line((4.0, 2.0), (4.0, 9.0))
    refresh(np.vstack([_room_with_door(0.0), inner]))
    i, j = maps.grid.cell_of(state.field[0].origin_m[None], np.array([[[4.0, 5.0]]]))
    cell = int(i[0, 0]) * maps.grid.n + int(j[0, 0])
    assert state.field[0].blocked[cell]
    assert refresh(_room_with_door(0.0)) < through_door_m and state.field[0].blocked[cell]
    # A dead end the planner marked stays blocked under points known now.
    door = maps.grid.cell_of(state.field[0].origin_m[None], np.array([[[8.0, 11.3]]]))
    door_cell = int(door[0][0, 0]) * maps.grid.n + int(door[1][0, 0])
    state.field[0].virtual[door_cell] = state.field[0].blocked[door_cell] = True
    refresh(_room_with_door(0.0))
    assert state.field[0].blocked[door_cell]


class _CountingGrid(NavGrid):
    """The real grid, counting its occupancy and field computations."""

    def __init__(self, cell_m: float, side_m: float) -> None:
        super().__init__(cell_m, side_m)
        self.counts = {"blocked": 0, "fields": 0}

    def blocked_within(
        self, origins_m: np.ndarray, obstacles_xy_m: np.ndarray, valid: np.ndarray, radii_m: tuple[float, ...]
    ) -> list[np.ndarray]:
        self.counts["blocked"] += origins_m.shape[0]
        return super().blocked_within(origins_m, obstacles_xy_m, valid, radii_m)

    def distances(self, origins_m: np.ndarray, blocked: np.ndarray, goals_xy_m: np.ndarray) -> np.ndarray:
        self.counts["fields"] += origins_m.shape[0]
        return super().distances(origins_m, blocked, goals_xy_m)


def test_a_refresh_from_an_unchanged_map_reuses_its_cells_and_field_and_a_changed_map_computes_them() -> None:
    """The memo of an agent's fields (``NavField.memo``, ``NavField.occupancy``): the same input (corner, goal,
    points) gives the cells and the field computed before, equal to ones computed afresh; a new point computes new
    ones; the memo stays short."""
    params = PlannerParams()
    offsets = BapfNavPlanner(params).bacteria_offsets_m
    maps = EscapeMaps(params, offsets, params.clearance_m)
    maps.grid = _CountingGrid(params.nav_cell_m, params.nav_grid_m)
    state = NavState.empty(1, 2)
    agent, goal, rows = np.array([[5.0, 10.5]]), np.array([[12.0, 6.0]]), np.array([0])
    room = _room_with_door(0.0)
    maps.refresh(rows, agent, goal, room[None], None, state)
    first = state.field[0]
    maps.refresh(rows, agent, goal, room[None], None, state)
    again = state.field[0]
    assert [k for k, _ in again.memo] == [k for k, _ in first.memo] and len(first.memo) >= 1
    assert maps.grid.counts == {"blocked": 1, "fields": len(first.memo)}  # nothing computed the second time
    fresh = NavState.empty(1, 2)
    EscapeMaps(params, offsets, params.clearance_m).refresh(rows, agent, goal, room[None], None, fresh)
    assert np.array_equal(again.dist_m, fresh.field[0].dist_m) and fresh.field[0].dist_m is not again.dist_m
    assert np.array_equal(again.blocked, fresh.field[0].blocked)
    for k in range(1, 8):  # each new point changes the blocked cells: a new field each time
        maps.refresh(rows, agent, goal, np.vstack([room, [[6.0 + 0.5 * k, 3.0]]])[None], None, state)
        keys = [key for key, _ in state.field[0].memo]
        assert len(set(keys)) == len(keys) <= 2
        assert maps.grid.counts["blocked"] == 1 + k and maps.grid.counts["fields"] >= len(first.memo) + k
    assert keys[-1] not in [key for key, _ in first.memo]


def test_the_grid_moves_before_the_trail_closes_the_side_the_agent_walks_to() -> None:
    """A refresh keeps the old grid only while the agent is ``nav_seen_m`` + 1 m inside every side. Within
    ``nav_seen_m`` of a side the trail closes that side's edge cells as seen, so a grid kept longer would show
    no way on past that side, even when the sensor saw one just beyond it (`apf-sim fly --world wall-gap` paced
    the wall 1.5 m short of its gap)."""
    params = PlannerParams()
    maps = EscapeMaps(params, BapfNavPlanner(params).bacteria_offsets_m, params.clearance_m)
    side = maps.grid.n * maps.grid.cell_m
    goal, rows, wall = np.array([[30.0, 0.0]]), np.array([0]), np.empty((1, 0, 2))
    state = NavState.empty(1, 2)
    maps.refresh(rows, np.array([[0.0, 0.0]]), goal, wall, None, state)
    corner = state.field[0].origin_m.copy()
    inside = params.nav_seen_m + 1.0
    for east_gap_m, kept in ((side / 2.0, True), (inside + 0.1, True), (inside - 0.5, False)):
        agent = corner + np.array([side / 2.0, side - east_gap_m])  # east_gap_m from the east side
        maps.refresh(rows, agent[None], goal, wall, None, state)
        assert np.array_equal(state.field[0].origin_m, corner) is kept, east_gap_m
        if not kept:  # re-centred: the agent now has more than nav_seen_m + 1 m ahead of it to the east
            assert state.field[0].origin_m[1] + side - agent[1] > inside
        state.field[0] = dataclasses.replace(state.field[0], origin_m=corner.copy())


def test_marking_dead_ends_reports_only_rows_that_gained_a_blocked_cell() -> None:
    """``mark_dead_ends`` says which rows' maps changed: the dead-end rule skips the refresh of the others (it would
    give the same field again)."""
    params = PlannerParams()
    offsets = BapfNavPlanner(params).bacteria_offsets_m
    maps = EscapeMaps(params, offsets, params.clearance_m)
    state = NavState.empty(1, 2)
    agent, goal, rows = np.array([[5.0, 10.5]]), np.array([[12.0, 6.0]]), np.array([0])
    maps.refresh(rows, agent, goal, _room_with_door(0.0)[None], None, state)
    refused = np.zeros((1, offsets.shape[0]), dtype=bool)  # every point refused and downhill
    g_k, g0 = np.zeros((1, offsets.shape[0])), np.ones(1)
    before = state.field[0].blocked.copy()
    assert maps.mark_dead_ends(rows, agent, refused, g_k, g0, state).tolist() == [True]
    marked = state.field[0].blocked.copy()
    assert marked.sum() > before.sum()
    # The points' own cells are blocked now: the free corners of their bilinear stencils are marked next.
    assert maps.mark_dead_ends(rows, agent, refused, g_k, g0, state).tolist() == [True]
    assert state.field[0].blocked.sum() > marked.sum()
    assert maps.mark_dead_ends(rows, agent, refused, g_k, g0, state).tolist() == [False]
    assert maps.mark_dead_ends(rows, agent, refused, np.full_like(g_k, 2.0), g0, state).tolist() == [False]


@pytest.mark.parametrize(("density", "trial"), [((45, 70), 3192), ((70, 95), 16), ((70, 95), 1100), ((70, 95), 2143)])
def test_study_trials_that_sat_beside_a_refused_gap_arrive(density: tuple[int, int], trial: int) -> None:
    """Noise-free study trials (seed 0) that gave up before session 22: the agent sat beside a gap between two
    obstacles that the grid passes diagonally and the sweep refuses, every downhill point in a cell already
    marked as a dead end, yet downhill on the free corners of its bilinear stencil; no point moved it, until its
    patience ran out. The dead-end rule now marks those corners (``navescape.mark_dead_end``)."""
    cfg = dataclasses.replace(StudyConfig.reference(), noise_std_m=0.0)
    d = Density(n_low=density[0], n_high=density[1])
    chunk, k = divmod(trial, cfg.chunk_trials)
    world_rng, motion_rng = chunk_generators(0, d, chunk)
    worlds = draw_worlds(world_rng, cfg.chunk_trials, d, cfg.obstacle_box_m, cfg.dim, cfg.obstacle_sampling)
    one = WorldBatch(obstacles_m=worlds.obstacles_m[k : k + 1], mask=worlds.mask[k : k + 1])
    records = simulate(cfg, "bapf-nav", one, motion_rng).records
    assert Outcome(int(records.outcome[0])) is Outcome.SUCCESS, records.iterations


def _fly_u_trap_goal(params: PlannerParams) -> tuple[float, float]:
    """Fly ``u-trap-goal`` noise-free, seeing the study's surface samples within 8 m (remembered).

    Returns (north where the agent first descends the geodesic potential, path length on arrival)."""
    world = load_world(example_world_path("u-trap-goal"))
    samples = surface_samples_ne_m(world)
    planner = BapfNavPlanner(params)
    state = planner.initial_state(1)
    pos = np.asarray(world.start_ne_m, dtype=np.float64)
    goal = np.asarray(world.goal_ne_m, dtype=np.float64)
    seen = np.zeros(samples.shape[0], dtype=bool)
    first_escape, path = math.inf, 0.0
    for _ in range(600):
        if np.linalg.norm(pos - goal) <= 0.7:
            return first_escape, path
        seen |= np.linalg.norm(samples - pos, axis=1) <= 8.0
        d = planner.step_batch(pos[None], goal[None], samples[None], seen[None], state=state)
        if state.mode[0] == NavMode.ESCAPE and math.isinf(first_escape):
            first_escape = float(pos[0])
        assert d.moved[0]
        path += float(np.linalg.norm(d.next_points_m[0] - pos))
        pos = d.next_points_m[0]
    pytest.fail("did not arrive")


def test_a_closed_u_in_sight_is_avoided_before_the_agent_enters_it() -> None:
    """The straight line to the goal crosses the U's closed end, which the 8 m sensor shows from north 4: the agent
    switches to the geodesic potential there, before the U's mouth (north 6), and goes round. Without the
    sight rule (``nav_sight_m`` = 0) it is trapped at the bottom of the U first (37.2 m when this was written)."""
    switch_north, path = _fly_u_trap_goal(PlannerParams())
    assert switch_north < 6.0
    assert path < 30.0  # 28.0 m; the optimum at 0.35 m clearance is 22.7 m
    late_north, late_path = _fly_u_trap_goal(PlannerParams(nav_sight_m=0.0))
    assert late_north > 10.0  # at the bottom of the U (closed end at north 12)
    assert late_path > path + 5.0


def test_escape_in_3d_on_the_u_trap() -> None:
    outcome, _, _ = _fly_world("u-trap", dim=3)
    assert outcome == "arrived"


def test_an_enclosed_goal_ends_in_a_bounded_give_up() -> None:
    """The goal inside a closed ring of points: no path on the remembered map -> GAVE_UP, not an endless walk."""
    angles = np.linspace(0.0, 2.0 * np.pi, 120, endpoint=False)
    ring = np.array([10.0, 10.0]) + 2.0 * np.stack([np.cos(angles), np.sin(angles)], axis=1)
    planner = get_planner("bapf-nav", PlannerParams(nav_patience_steps=200))
    assert isinstance(planner, StatefulPlanner)
    pos = np.zeros(2)
    steps = 0
    while steps < 400:
        steps += 1
        d = planner.step(pos, np.array([10.0, 10.0]), ring)
        if d.reason is DecisionReason.GAVE_UP:
            break
        if d.next_point_m is not None:
            pos = d.next_point_m
    assert steps <= 200 + 100  # patience + the way there
    assert isinstance(planner, BapfNavPlanner) and planner.give_up_cause() is GiveUp.NO_PROGRESS
    again = planner.step(pos, np.array([10.0, 10.0]), ring)
    assert again.reason is DecisionReason.GAVE_UP and again.next_point_m is None
    assert planner.give_up_cause() is GiveUp.NO_PROGRESS  # the first cause stays while the patience runs on
    planner.reset()
    assert planner.step(pos, np.array([-5.0, 0.0]), ring).reason is DecisionReason.GREEDY


def test_own_state_shows_the_single_agent_mode_and_reset_forgets_it() -> None:
    """``own_state`` (read by benchmarks/bench_planner_replay.py): None before the first step and after reset."""
    planner = get_planner("bapf-nav")
    assert isinstance(planner, StatefulPlanner) and planner.own_state is None
    wall = np.stack([np.full(41, 3.0), np.linspace(-4.0, 4.0, 41)], axis=1)  # across the way, 3 m ahead
    planner.step(np.zeros(2), np.array([10.0, 0.0]), wall)
    state = planner.own_state
    assert isinstance(state, NavState) and len(state) == 1
    assert NavMode(int(state.mode[0])) is NavMode.ESCAPE  # a surface blocks the line of sight
    planner.reset()
    assert planner.own_state is None


def test_boxed_in_it_squeezes_out_keeping_radius_and_safety_margin() -> None:
    """A ring of 7 points 0.7 m away (pockets like it occur in the study): no 0.4 m move keeps C = 0.6 m; it still
    moves, through a gap, along the move that keeps the most."""
    angles = 2.0 * np.pi * (np.arange(7) + 0.3) / 7.0
    pocket = 0.7 * np.stack([np.cos(angles), np.sin(angles)], axis=1)
    planner = get_planner("bapf-nav")
    d = planner.step(np.zeros(2), np.array([20.0, 20.0]), pocket)
    assert d.n_safe == 0 and d.next_point_m is not None
    swept = _segment_clearance(np.zeros(2), d.next_point_m, pocket)
    assert swept >= planner.params.vehicle_radius_m + planner.params.safety_margin_m
    assert swept == pytest.approx(
        max(_segment_clearance(np.zeros(2), o, pocket) for o in planner.bacteria_offsets_m), abs=1e-9
    )


def test_a_new_target_starts_afresh() -> None:
    planner = get_planner("bapf-nav")
    assert isinstance(planner, StatefulPlanner)
    state = planner.initial_state(1)
    assert isinstance(state, NavState)
    state.mode[0] = NavMode.GAVE_UP
    state.target_m[0] = (1.0, 1.0)
    d = planner.step_batch(
        np.zeros((1, 2)), np.array([[5.0, 0.0]]), np.zeros((1, 0, 2)), np.zeros((1, 0), bool), state=state
    )
    assert d.reason[0] == DecisionReason.GREEDY and state.mode[0] == NavMode.DIRECT


# --- batch == single ---------------------------------------------------------------------------------------


@pytest.mark.parametrize("name", PRODUCT)
@pytest.mark.parametrize("dim", [2, 3])
def test_step_equals_step_batch_rows_over_a_run(name: str, dim: int) -> None:
    """Five agents stepped together (one state object) and one by one (each planner's own memory) agree."""
    rng = np.random.default_rng(7)
    n_agents, n_obs = 5, 60
    params = PlannerParams(dim=dim)
    obstacles = rng.uniform(4.0, 16.0, size=(n_agents, n_obs, dim))
    mask = rng.random((n_agents, n_obs)) < 0.9
    pos = np.full((n_agents, dim), 2.0)
    target = np.full((n_agents, dim), 18.0)
    batch_planner = get_planner(name, params)
    state = batch_planner.initial_state(n_agents)  # type: ignore[attr-defined]
    singles = [get_planner(name, params) for _ in range(n_agents)]
    pos_single = pos.copy()
    for _ in range(40):
        bd = batch_planner.step_batch(pos, target, obstacles, mask, state=state)  # type: ignore[call-arg]
        for a in range(n_agents):
            d = singles[a].step(pos_single[a], target[a], obstacles[a][mask[a]])
            row = bd.row(a)
            assert d.reason is row.reason and d.chosen_index == row.chosen_index
            if d.next_point_m is not None:
                assert row.next_point_m is not None
                np.testing.assert_array_equal(d.next_point_m, row.next_point_m)
                pos_single[a] = d.next_point_m
        moved = bd.moved
        pos[moved] = bd.next_points_m[moved]
        np.testing.assert_array_equal(pos, pos_single)


# --- the study ----------------------------------------------------------------------------------------------


def _fields(density: Density, n: int, seed: int) -> WorldBatch:
    cfg = StudyConfig.reference()
    return draw_worlds(np.random.default_rng(seed), n, density, cfg.obstacle_box_m, 2, cfg.obstacle_sampling)


@pytest.mark.parametrize("density", [Density(n_low=45, n_high=70), Density(n_low=70, n_high=95)])
def test_random_fields_terminate_without_collisions_when_noise_free(density: Density) -> None:
    cfg = dataclasses.replace(StudyConfig.reference(), noise_std_m=0.0)
    res = simulate(cfg, "bapf-nav", _fields(density, 60, 11), np.random.default_rng(0))
    s = summarize(res.records)
    assert s.timeout == 0 and s.collision == 0
    assert s.R_s >= 0.95


def test_give_up_is_a_stuck_outcome_in_the_study() -> None:
    angles = np.linspace(0.0, 2.0 * np.pi, 90, endpoint=False)
    ring = np.array([22.0, 22.0]) + 2.0 * np.stack([np.cos(angles), np.sin(angles)], axis=1)
    worlds = WorldBatch(obstacles_m=ring[None], mask=np.ones((1, 90), dtype=bool))
    cfg = dataclasses.replace(StudyConfig.reference(), noise_std_m=0.0)
    res = simulate(cfg, "bapf-nav", worlds, np.random.default_rng(0))
    assert res.records.outcome[0] == Outcome.STUCK
    assert res.records.iterations[0] < cfg.max_iterations


def test_same_seed_same_table_with_one_and_two_workers() -> None:
    cfg = dataclasses.replace(StudyConfig.reference(), chunk_trials=15)
    densities = (Density(n_low=70, n_high=95),)
    serial = run_study(cfg, PRODUCT, densities, 30, seed=4, executor=SerialExecutor())
    pooled = run_study(cfg, PRODUCT, densities, 30, seed=4, workers=2)
    for a, b in zip(serial, pooled, strict=True):
        assert a.planner_name == b.planner_name
        for field in ("outcome", "iterations", "safety_m", "n_detected"):
            np.testing.assert_array_equal(getattr(a.records, field), getattr(b.records, field))


# --- the baseline -------------------------------------------------------------------------------------------


def test_bendyruler_flies_straight_in_the_open_and_around_a_post() -> None:
    planner = get_planner("bendyruler")
    d = planner.step(np.zeros(2), np.array([10.0, 0.0]), np.zeros((0, 2)))
    assert d.next_point_m is not None
    np.testing.assert_allclose(d.next_point_m, np.array([0.4, 0.0]), atol=1e-12)
    pos = np.zeros(2)
    post = np.array([[3.0, 0.0]])
    for _ in range(40):
        d = planner.step(pos, np.array([6.0, 0.0]), post)
        assert d.next_point_m is not None
        assert _segment_clearance(pos, d.next_point_m, post) >= 0.35 - 1e-9
        pos = d.next_point_m
        if np.linalg.norm(pos - [6.0, 0.0]) < 0.7:
            break
    assert np.linalg.norm(pos - [6.0, 0.0]) < 0.7


def _bendyruler_probing_every_bearing(
    planner: BendyRulerPlanner, pos: np.ndarray, target: np.ndarray, obstacles: np.ndarray, prev_dir: np.ndarray
) -> np.ndarray:
    """The baseline's choice with every probe measured (the rule of the module docstring, written out)."""
    p = planner.params
    n_agents = pos.shape[0]
    goal_vec = target - pos
    g0 = np.linalg.norm(goal_vec, axis=1)
    rel, valid = near_obstacles(pos, obstacles, None, 2.0 * p.br_lookahead_m + p.br_margin_max_m)
    every = np.broadcast_to(np.arange(p.n_bacteria), (n_agents, p.n_bacteria))
    margin = planner._probe(rel, valid, goal_vec, g0, every)
    step2 = segment_clearance_sq(rel, valid, planner.bacteria_offsets_m)
    safe = np.sqrt(step2) >= p.vehicle_radius_m + p.safety_margin_m
    cos_goal = np.einsum("ad,kd->ak", goal_vec / g0[:, None], planner.bacteria_offsets_m / p.step_m)
    open_ = safe & (margin >= p.br_margin_max_m)
    first_open = np.argmax(np.where(open_, cos_goal, -np.inf), axis=1)
    widest = np.argmax(np.where(safe, margin, -np.inf), axis=1)
    chosen = np.where(open_.any(axis=1), first_open, planner._continuity(widest, margin, safe, prev_dir))
    return np.where(safe[np.arange(n_agents), chosen], chosen, -1)


def test_bendyruler_stops_probing_at_the_first_open_bearing_with_the_same_choice() -> None:
    """Probing in stages (and only until a bearing is open) chooses what measuring every bearing chooses."""
    rng = np.random.default_rng(11)
    planner = get_planner("bendyruler")
    assert isinstance(planner, BendyRulerPlanner)
    n_agents, n_obs = 400, 40
    pos = rng.uniform(0.0, 10.0, (n_agents, 2))
    target = pos + rng.normal(0.0, 6.0, (n_agents, 2))
    crowd = rng.uniform(0.5, 3.0, (n_agents, 1))  # from open space to boxed in
    angles = rng.uniform(0.0, 2.0 * np.pi, (n_agents, n_obs))
    radii = rng.uniform(0.45, 3.0, (n_agents, n_obs)) * crowd
    obstacles = pos[:, None, :] + radii[..., None] * np.stack([np.cos(angles), np.sin(angles)], axis=-1)
    state = planner.initial_state(n_agents)
    state.target_m[:] = target
    turned = rng.integers(0, planner.params.n_bacteria, n_agents)
    state.prev_dir[:] = np.where(rng.random((n_agents, 1)) < 0.5, planner.bacteria_offsets_m[turned] / 0.4, 0.0)
    expected = _bendyruler_probing_every_bearing(planner, pos, target, obstacles, state.prev_dir.copy())
    bd = planner.step_batch(pos, target, obstacles, np.ones((n_agents, n_obs), dtype=bool), state=state)
    np.testing.assert_array_equal(bd.chosen_index, expected)
    reasons = np.asarray(bd.reason)
    # The scenes cover every branch: an open bearing, only the widest, and no safe step.
    assert (bd.n_passing > 0).any() and ((bd.n_passing == 0) & (reasons == DecisionReason.GREEDY)).any()
    assert (reasons == DecisionReason.LOCAL_MINIMUM).any()
    assert np.all(bd.n_passing <= bd.n_safe)


def test_service_config_takes_the_product_parameters() -> None:
    """``[planner.params]`` reaches bapf-nav through the service's validated config (typos are refused)."""
    from apf_companion.config import config_from_mapping
    from apf_companion.service import build_planner

    cfg = config_from_mapping({"planner": {"params": {"vehicle_radius_m": 0.3, "safety_margin_m": 0.2}}})
    planner = build_planner(cfg)
    assert isinstance(planner, BapfNavPlanner)
    assert planner.clearance_m == pytest.approx(0.3 + 0.2 + 2.5 * 0.1)
    with pytest.raises(ConfigError, match="vehicle_radius_m"):
        build_planner(config_from_mapping({"planner": {"params": {"vehicle_radius_m": -1.0}}}))
    with pytest.raises(ConfigError, match="unknown planner parameter"):
        build_planner(config_from_mapping({"planner": {"params": {"vehicle_radius": 0.3}}}))


def test_study_cli_runs_the_new_rows_noise_free(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """``apf-sim study`` takes the two new planners and ``--noise-std 0``; rows without paper numbers show a dash."""
    import json

    from sim.cli import build_parser

    argv = ["study", "--trials", "6", "--densities", "70-95", "--planners", "bapf-nav,bendyruler"]
    argv += ["--noise-std", "0", "--workers", "1", "--no-progress", "--json", str(tmp_path / "s.json")]
    args = build_parser().parse_args(argv)
    assert args.func(args) == 0
    out = capsys.readouterr().out
    assert "noise std 0 m" in out
    rows = [line for line in out.splitlines() if line.startswith("| bapf-nav") or line.startswith("| bendyruler")]
    assert len(rows) == 2 and all("| – |" in row for row in rows)
    doc = json.loads((tmp_path / "s.json").read_text())
    assert doc["rules"]["noise_std_m"] == 0.0
    assert [r["planner"] for r in doc["results"]] == ["bapf-nav", "bendyruler"]
