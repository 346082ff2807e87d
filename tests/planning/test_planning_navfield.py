"""``NavGrid.distances`` writes the infinite weights of the edges into blocked cells through a table of each cell's
incoming edges, and the seeds into fixed slots of one graph kept by the grid; its fields equal, bit for bit, those
of a graph built for each field, whose every edge weight is looked up from its destination cell and whose source
lists only the seeds (the construction before), with the goal inside, outside, on an edge cell and on a blocked
cell, one field after another in the same grid."""

from __future__ import annotations

import copy
import pickle

import numpy as np
import numpy.typing as npt
import pytest
from scipy.sparse import csr_matrix
from scipy.sparse.csgraph import dijkstra

from apf_companion.planning.navfield import NavGrid

FloatArray = npt.NDArray[np.float64]


def _plain_seeds(
    grid: NavGrid, origin: FloatArray, blocked: npt.NDArray[np.bool_], goal: FloatArray
) -> tuple[npt.NDArray[np.intp], FloatArray]:
    """The seed rule written out: the goal's cell (freed) and its in-grid neighbours at the straight-line distance
    when the goal lies in the grid, and every edge cell at its straight-line distance plus the grid's side (plus
    nothing when the goal lies outside); no blocked cell."""
    n, h = grid.n, grid.cell_m
    gi, gj = grid.cell_of_one(origin, goal)
    edge = np.zeros((n, n), dtype=bool)
    edge[0, :] = edge[-1, :] = edge[:, 0] = edge[:, -1] = True
    cells = np.flatnonzero(edge)
    detour = np.zeros(cells.size)
    if 0 <= gi < n and 0 <= gj < n:
        blocked[gi * n + gj] = False
        near = np.array(
            [i * n + j for i in range(gi - 1, gi + 2) for j in range(gj - 1, gj + 2) if 0 <= i < n and 0 <= j < n]
        )
        cells = np.concatenate([near, cells])
        detour = np.concatenate([np.zeros(near.size), np.full(detour.size, n * h)])
    keep = ~blocked[cells]
    cells, detour = cells[keep], detour[keep]
    i, j = np.divmod(cells, n)
    euclid = np.hypot(origin[0] + (i + 0.5) * h - goal[0], origin[1] + (j + 0.5) * h - goal[1])
    return cells, euclid + detour


def _plain_field(grid: NavGrid, origin: FloatArray, blocked: npt.NDArray[np.bool_], goal: FloatArray) -> FloatArray:
    """One field from a graph built for it alone: edge weights inf where the destination is blocked, else the step
    cost, and a source row that lists only the seeds."""
    blk = blocked.copy()
    cells, values = _plain_seeds(grid, origin, blk, goal)
    if cells.size == 0:
        return np.full(grid.size, np.inf)
    return _graph_field(grid, blk, cells, values)


def _graph_field(
    grid: NavGrid, blk: npt.NDArray[np.bool_], cells: npt.NDArray[np.intp], values: FloatArray
) -> FloatArray:
    """Dijkstra on a graph built for one field: edge weights inf into blocked cells, the seeds ``cells`` at
    ``values`` in the source's row."""
    weights = np.where(blk[grid.search.indices], np.inf, grid.search.edge_cost)
    indptr = np.append(grid.search.indptr, np.int32(grid.search.indptr[-1] + cells.size))
    graph = csr_matrix(
        (np.concatenate([weights, values]), np.concatenate([grid.search.indices, cells.astype(np.int32)]), indptr),
        shape=(grid.size + 1, grid.size + 1),
    )
    field: FloatArray = dijkstra(graph, directed=True, indices=grid.size, limit=1e300)[: grid.size]
    return field


@pytest.mark.parametrize("goal", [(7.0, 9.1), (40.0, -3.0), (0.1, 6.1), (12.05, 3.95)])
def test_fields_equal_the_graph_weighted_by_destination(goal: tuple[float, float]) -> None:
    grid = NavGrid(0.3, 16.0)
    rng = np.random.default_rng(5)
    for density in (0.0, 0.1, 0.3, 0.6):
        blocked = rng.random((4, grid.size)) < density
        blocked[:, 40 * grid.n + 13] = True  # (12.05, 3.95) lies in this cell: a blocked goal cell is freed
        origins = np.round(rng.uniform(-1.0, 1.0, (4, 2)), 1)
        goals = np.tile(goal, (4, 1))
        dist = grid.distances(origins, blocked, goals)
        for b in range(4):
            want = _plain_field(grid, origins[b], blocked[b], goals[b])
            assert np.array_equal(dist[b], want)
        assert np.isfinite(dist).any()


def test_the_goal_cell_of_one_point_equals_cell_of() -> None:
    """``cell_of_one`` (Python floats) equals ``cell_of`` (arrays): on cell borders, off the grid either side, huge
    and non-finite coordinates (-1)."""
    grid = NavGrid(0.3, 16.0)
    rng = np.random.default_rng(9)
    special = [np.nan, np.inf, -np.inf, 1e300, -1e300, 0.0, -0.3, 16.2, 15.9]
    points = np.concatenate([rng.uniform(-2.0, 18.0, (300, 2)), np.round(rng.uniform(-1.0, 17.0, (300, 2)), 1)])
    points = np.concatenate([points, np.array([(x, y) for x in special for y in special])])
    for origin in (np.zeros(2), np.array([-0.3, 2.1]), np.array([1e5, -7.5])):
        i, j = grid.cell_of(origin[None], (points + origin)[None])
        got = [grid.cell_of_one(origin, p + origin) for p in points]
        assert got == list(zip(i[0].tolist(), j[0].tolist(), strict=True))


def test_fields_in_turn_do_not_inherit_the_last_ones_seeds() -> None:
    """One call over goals inside, outside, at a corner and inside again: every field equals its own graph's (the
    goal slots a field does not use are reset)."""
    grid = NavGrid(0.3, 16.0)
    rng = np.random.default_rng(11)
    goals = np.array([(7.0, 9.1), (40.0, -3.0), (0.05, 0.05), (15.95, 0.1), (8.0, 8.0), (-5.0, 30.0)])
    origins = np.zeros((goals.shape[0], 2))
    blocked = rng.random((goals.shape[0], grid.size)) < 0.2
    dist = grid.distances(origins, blocked, goals)
    for b in range(goals.shape[0]):
        assert np.array_equal(dist[b], _plain_field(grid, origins[b], blocked[b], goals[b]))


def test_a_copied_grid_computes_the_same_fields() -> None:
    """The grid keeps one graph whose weights it writes through views; a deep copy or a pickled grid (views
    copied into separate arrays) still computes the fields of the original."""
    grid = NavGrid(0.3, 16.0)
    rng = np.random.default_rng(13)
    origins = np.zeros((3, 2))
    goals = np.array([(7.0, 9.1), (40.0, -3.0), (0.05, 0.05)])
    blocked = rng.random((3, grid.size)) < 0.2
    want = grid.distances(origins, blocked, goals)
    for other in (copy.deepcopy(grid), pickle.loads(pickle.dumps(grid))):
        assert np.array_equal(other.distances(origins, blocked, goals), want)


_AREA = (-3.0, -12.0, 23.0, 12.05)  # north_min, east_min, north_max, east_max: a corner off the cell lattice


def test_a_grid_over_a_flying_area_has_a_fixed_corner_and_no_exits() -> None:
    """``nav_area_ne_m``: the grid's corner is the area's south-west corner on the cell lattice, wherever the
    agent and the goal are; the square holds the whole area; the edge cells are no exits."""
    grid = NavGrid(0.3, 16.0, _AREA)
    assert grid.fixed_origin_m is not None and not grid.exits
    assert np.allclose(grid.fixed_origin_m, [-3.0, -12.0])
    assert grid.n * grid.cell_m >= max(_AREA[2] - _AREA[0], _AREA[3] - _AREA[1]) - 1e-9
    assert grid.n == 87  # ceil(26 / 0.3)
    rng = np.random.default_rng(3)
    agents, goals = rng.uniform(-20.0, 30.0, (5, 2)), rng.uniform(-20.0, 30.0, (5, 2))
    assert np.array_equal(grid.origins(agents, goals, 2.0), np.tile(grid.fixed_origin_m, (5, 1)))
    moving = NavGrid(0.3, 16.0)
    assert moving.fixed_origin_m is None and moving.exits


def _area_field(grid: NavGrid, blocked: npt.NDArray[np.bool_], goal: FloatArray) -> FloatArray:
    """The area's rule written out: the cells whose centre is outside the area blocked, the goal's cell (freed,
    even where its centre is outside) and its neighbours the only seeds, none when the goal is outside the
    area."""
    assert grid.fixed_origin_m is not None
    n, h, origin = grid.n, grid.cell_m, grid.fixed_origin_m
    inside_goal = _AREA[0] <= goal[0] <= _AREA[2] and _AREA[1] <= goal[1] <= _AREA[3]
    if not inside_goal:
        return np.full(grid.size, np.inf)
    i, j = np.divmod(np.arange(grid.size), n)
    north, east = origin[0] + (i + 0.5) * h, origin[1] + (j + 0.5) * h
    outside = (north < _AREA[0]) | (north > _AREA[2]) | (east < _AREA[1]) | (east > _AREA[3])
    gi, gj = grid.cell_of_one(origin, goal)
    blk = blocked | outside
    blk[gi * n + gj] = False  # the goal's own cell stays free, also where its centre is outside the area
    near = np.array(
        [a * n + b for a in range(gi - 1, gi + 2) for b in range(gj - 1, gj + 2) if 0 <= a < n and 0 <= b < n]
    )
    near = near[~blk[near]]
    a, b = np.divmod(near, n)
    values = np.hypot(origin[0] + (a + 0.5) * h - goal[0], origin[1] + (b + 0.5) * h - goal[1])
    return _graph_field(grid, blk, near, values)


@pytest.mark.parametrize("goal", [(20.0, 0.0), (22.9, 12.0), (-2.9, -11.9), (30.0, 0.0), (10.0, 12.2)])
def test_area_fields_seed_only_the_goal_and_block_outside(goal: tuple[float, float]) -> None:
    """Fields over a flying area equal the plain graph's whose only seeds are the goal's cells, with the cells
    outside the area blocked (the square is wider than the area to the north: 26 m against 24.05 m); a goal
    outside the area (the last two) has no way from anywhere."""
    grid = NavGrid(0.3, 16.0, _AREA)
    assert grid.fixed_origin_m is not None
    rng = np.random.default_rng(17)
    g = np.array(goal)
    for density in (0.0, 0.2):
        blocked = rng.random((2, grid.size)) < density
        dist = grid.distances(np.tile(grid.fixed_origin_m, (2, 1)), blocked, np.tile(g, (2, 1)))
        for b in range(2):
            assert np.array_equal(dist[b], _area_field(grid, blocked[b], g))
    inside = _AREA[0] <= goal[0] <= _AREA[2] and _AREA[1] <= goal[1] <= _AREA[3]
    assert np.isfinite(dist).any() == inside


def test_an_area_field_goes_round_a_wall_the_moving_grid_only_guesses_at() -> None:
    """wall-gap's geometry: a wall across the area from its west side to 1.6 m short of its east side. Over the
    area the potential south of the wall leads east, through the gap: the way round the west end does not exist
    (no exits). On a 16 m grid around the agent (east -8..8, the wall seen across it) the west edge is an exit,
    and from 2 m west of the middle it looks as short as the way east."""
    grid = NavGrid(0.3, 16.0, _AREA)
    origin = grid.fixed_origin_m
    assert origin is not None
    n, h = grid.n, grid.cell_m
    i, j = np.divmod(np.arange(grid.size), n)
    north, east = origin[0] + (i + 0.5) * h, origin[1] + (j + 0.5) * h
    wall = (np.abs(north - 10.0) < 0.7) & (east < 10.3 + 0.7)  # the wall inflated by C = 0.6 m plus a bit
    goal = np.array([20.0, 0.0])
    dist = grid.distances(origin[None], wall[None], goal[None])[0]
    agent = np.array([8.5, -2.0])
    gi, gj = grid.cell_of_one(origin, agent)
    via_gap = np.hypot(9.3 - agent[0], 11.15 - agent[1]) + 1.4 + np.hypot(20.0 - 10.7, 11.15)
    assert dist[gi * n + gj] == pytest.approx(via_gap, rel=0.06)
    west, east_side = dist[gi * n + gj - 10], dist[gi * n + gj + 10]  # 3 m west and east of the agent
    assert east_side < dist[gi * n + gj] < west
