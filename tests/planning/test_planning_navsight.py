"""bapf-nav's batch line-of-sight test (``navsight.sight_blocked``) runs in 2D on the coordinate planes with the
sums of two products written out; it answers exactly what the einsum form of the test answers (kept here as the
reference), on batches of lattice scenes full of points exactly C from the line, with masks and unknown non-finite
rows, in 2D and 3D."""

from __future__ import annotations

import numpy as np
import numpy.typing as npt
import pytest

from apf_companion.planning import BapfNavPlanner, NavState, PlannerParams
from apf_companion.planning.navescape import EscapeMaps
from apf_companion.planning.navsight import _line_offsets_sq, sight_blocked

FloatArray = npt.NDArray[np.float64]
BoolArray = npt.NDArray[np.bool_]


def _reference(
    positions: FloatArray,
    targets: FloatArray,
    obstacles: FloatArray,
    mask: BoolArray | None,
    reach_m: tuple[float, float, float],
) -> BoolArray:
    """The einsum form of the test (one group): any known point within C of the segment of the line."""
    sight_m, step_m, clearance_m = reach_m
    if sight_m <= 0.0 or obstacles.shape[1] == 0:
        return np.zeros(positions.shape[0], dtype=bool)
    to_goal = targets - positions
    dist = np.sqrt(np.einsum("ad,ad->a", to_goal, to_goal))
    unit = to_goal / np.maximum(dist, np.finfo(np.float64).tiny)[:, None]
    end = np.minimum(dist, sight_m)
    start = np.minimum(step_m, end)
    rel = obstacles - positions[:, None, :]
    with np.errstate(invalid="ignore", over="ignore"):
        along = np.einsum("amd,ad->am", rel, unit)
        t = np.clip(along, start[:, None], end[:, None])
        off = rel - t[:, :, None] * unit[:, None, :]
        hit = np.einsum("amd,amd->am", off, off) < clearance_m**2
    if mask is not None:
        hit &= mask
    out: BoolArray = hit.any(axis=1)
    return out


def _batch(rng: np.random.Generator, n_agents: int, dim: int) -> tuple[FloatArray, FloatArray, FloatArray, BoolArray]:
    """Agents on a 0.1 m lattice with targets along an axis (exact ties along the line) or anywhere, points on the
    lattice ahead of them (walls of neighbours, pairs, isolated points), 0-60 known per agent, unknown rows NaN."""
    pos = np.round(rng.uniform(-3.0, 3.0, (n_agents, dim)), 1)
    along_axis = rng.random(n_agents) < 0.5
    ahead = np.where(along_axis[:, None], np.eye(dim)[0] * 20.0, np.round(rng.uniform(-12.0, 12.0, (n_agents, dim)), 1))
    targets = pos + ahead
    width = 60
    spread = np.r_[1.0, np.full(dim - 1, 0.15)]
    obstacles = pos[:, None, :] + np.round(rng.uniform(-1.0, 9.0, (n_agents, width, dim)) * spread, 1)
    known = np.arange(width)[None, :] < rng.integers(0, width + 1, n_agents)[:, None]
    known &= rng.random((n_agents, width)) < 0.9
    obstacles[~known] = np.nan
    return pos, targets, obstacles, known


@pytest.mark.parametrize("dim", [2, 3])
@pytest.mark.parametrize("sight_m", [8.0, 3.0])
def test_the_batch_sight_equals_the_einsum_test(dim: int, sight_m: float) -> None:
    params = PlannerParams(dim=dim, nav_sight_m=sight_m)
    reach = (params.nav_sight_m, params.step_m, params.clearance_m)
    rng = np.random.default_rng(11 + dim)
    answers = []
    for _ in range(30):
        pos, targets, obstacles, known = _batch(rng, 200, dim)
        active = rng.random(200) < 0.8
        got = sight_blocked(active, pos, targets, obstacles, known, reach)
        want = _reference(pos, targets, obstacles, known, reach) & active
        assert got.tolist() == want.tolist()
        # Without a mask the unknown (NaN) rows compare False in both.
        got = sight_blocked(active, pos, targets, obstacles, None, reach)
        assert got.tolist() == (_reference(pos, targets, obstacles, None, reach) & active).tolist()
        answers.extend(got[active].tolist())
    assert any(answers) and not all(answers)  # the scenes do block, and not always


def test_the_squared_offsets_equal_einsum_bit_for_bit() -> None:
    """2D: the written-out sums give einsum's squared distances to the line, every bit (NaN rows NaN in both)."""
    rng = np.random.default_rng(5)
    for _ in range(20):
        pos, targets, obstacles, _ = _batch(rng, 100, 2)
        obstacles += rng.normal(0.0, 1e-3, obstacles.shape)  # off the lattice too
        to_goal = targets - pos
        dist = np.sqrt(np.einsum("ad,ad->a", to_goal, to_goal))
        unit = to_goal / dist[:, None]
        end = np.minimum(dist, 8.0)
        start = np.minimum(0.4, end)
        rel = obstacles - pos[:, None, :]
        t = np.clip(np.einsum("amd,ad->am", rel, unit), start[:, None], end[:, None])
        off = rel - t[:, :, None] * unit[:, None, :]
        want = np.einsum("amd,amd->am", off, off)
        got = _line_offsets_sq(obstacles, pos, unit, start, end)
        assert np.array_equal(got, want, equal_nan=True)


def _outdated_per_row(
    maps: EscapeMaps,
    rows: npt.NDArray[np.intp],
    pos: FloatArray,
    obstacles: FloatArray,
    mask: BoolArray,
    state: NavState,
) -> list[bool]:
    """``EscapeMaps.outdated`` as it was, one agent at a time."""
    grid, out = maps.grid, []
    for r in rows:
        f = state.field[r]
        rel = obstacles[r] - pos[r]
        with np.errstate(over="ignore", invalid="ignore"):
            d2 = np.einsum("md,md->m", rel, rel)
        near = (d2 <= maps.params.nav_sight_m**2) & mask[r]
        if maps.params.dim == 3:
            near &= np.abs(rel[:, 2]) <= maps.clearance_m
        if f is None or not near.any():
            out.append(False)
            continue
        ci, cj = grid.cell_of(f.origin_m[None], obstacles[r][near, :2][None])
        inside = (ci[0] >= 0) & (ci[0] < grid.n) & (cj[0] >= 0) & (cj[0] < grid.n)
        cells = ci[0][inside] * grid.n + cj[0][inside]
        new = ~f.blocked[cells]
        if not new.any():
            out.append(False)
            continue
        here = grid.sample(f.origin_m, f.dist_m, pos[r, :2][None])[0]
        way = np.sqrt(d2[near][inside][new]) + f.dist_m[cells[new]]
        out.append(not np.isfinite(here) or bool((way <= here + 2.0 * maps.clearance_m + grid.cell_m).any()))
    return out


@pytest.mark.parametrize("dim", [2, 3])
def test_outdated_fields_equal_the_per_agent_test(dim: int) -> None:
    """``EscapeMaps.outdated`` over all agents at once answers what the per-agent loop answered, on the fields of
    agents that fly lockstep through a crowded random field and see its points as they come within 8 m."""
    planner = BapfNavPlanner(PlannerParams(dim=dim))
    rng = np.random.default_rng(21 + dim)
    n_agents, n_obs = 40, 90
    obstacles = rng.uniform(0.0, 25.0, (n_agents, n_obs, dim))
    obstacles[..., 2:] = rng.uniform(-0.5, 0.5, (n_agents, n_obs, dim - 2))
    pos = np.zeros((n_agents, dim)) + np.r_[3.0, 3.0, np.zeros(dim - 2)]
    target = np.tile(np.r_[22.0, 22.0, np.zeros(dim - 2)], (n_agents, 1))
    state = planner.initial_state(n_agents)
    known = np.zeros((n_agents, n_obs), dtype=bool)
    checked = 0
    for _ in range(60):
        known |= np.linalg.norm(obstacles - pos[:, None, :], axis=2) <= 8.0
        decision = planner.step_batch(pos, target, obstacles, known, state=state)
        moved = ~np.isnan(decision.next_points_m[:, 0])
        pos[moved] = decision.next_points_m[moved]
        rows = np.arange(n_agents)
        got = planner._escape.outdated(rows, pos, obstacles, known, state).tolist()
        assert got == _outdated_per_row(planner._escape, rows, pos, obstacles, known, state)
        checked += sum(got)
    assert checked > 0  # some fields were outdated
