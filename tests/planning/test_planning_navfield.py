"""``NavGrid.distances`` writes the infinite weights of the edges into blocked cells through a table of each cell's
incoming edges; its fields equal, bit for bit, those of the graph whose every edge weight is looked up from its
destination cell (the construction before), with the goal inside, outside, on an edge cell and on a blocked cell."""

from __future__ import annotations

import numpy as np
import numpy.typing as npt
import pytest
from scipy.sparse import csr_matrix
from scipy.sparse.csgraph import dijkstra

from apf_companion.planning.navfield import NavGrid

FloatArray = npt.NDArray[np.float64]


def _plain_field(grid: NavGrid, origin: FloatArray, blocked: npt.NDArray[np.bool_], goal: FloatArray) -> FloatArray:
    """One field from a graph whose edge weights are inf where the destination is blocked, else the step cost."""
    blk = blocked.copy()
    cells, values = grid._seeds(origin, blk, goal)
    if cells.size == 0:
        return np.full(grid.size, np.inf)
    weights = np.where(blk[grid._indices], np.inf, grid._edge_cost)
    indptr = np.append(grid._indptr, np.int32(grid._indptr[-1] + cells.size))
    graph = csr_matrix(
        (np.concatenate([weights, values]), np.concatenate([grid._indices, cells.astype(np.int32)]), indptr),
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
    """``_cell_of_one`` (Python floats) equals ``cell_of`` (arrays): on cell borders, off the grid either side, huge
    and non-finite coordinates (-1)."""
    grid = NavGrid(0.3, 16.0)
    rng = np.random.default_rng(9)
    special = [np.nan, np.inf, -np.inf, 1e300, -1e300, 0.0, -0.3, 16.2, 15.9]
    points = np.concatenate([rng.uniform(-2.0, 18.0, (300, 2)), np.round(rng.uniform(-1.0, 17.0, (300, 2)), 1)])
    points = np.concatenate([points, np.array([(x, y) for x in special for y in special])])
    for origin in (np.zeros(2), np.array([-0.3, 2.1]), np.array([1e5, -7.5])):
        i, j = grid.cell_of(origin[None], (points + origin)[None])
        got = [grid._cell_of_one(origin, p + origin) for p in points]
        assert got == list(zip(i[0].tolist(), j[0].tolist(), strict=True))
