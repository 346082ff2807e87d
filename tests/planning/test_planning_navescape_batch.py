"""bapf-nav's batch escape maps: ``EscapeMaps.outdated`` over all agents at once answers what the per-agent loop
answered (kept here as the reference), on the fields of agents flying lockstep through crowded random fields, in
2D and 3D."""

from __future__ import annotations

import numpy as np
import numpy.typing as npt
import pytest

from apf_companion.planning import BapfNavPlanner, NavState, PlannerParams
from apf_companion.planning.navescape import EscapeMaps
from apf_companion.planning.navsight import LineOfSight

FloatArray = npt.NDArray[np.float64]
BoolArray = npt.NDArray[np.bool_]


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


def _sight_all_points(
    maps: LineOfSight, pos: FloatArray, target: FloatArray, obs: FloatArray, mask: BoolArray
) -> BoolArray:
    """``LineOfSight.blocked`` before the neighbour prefilter: each pick against every known point (one group,
    every agent looking)."""
    p, c2 = maps.params, maps.clearance_m**2
    to_goal = target - pos
    dist = np.sqrt(np.einsum("ad,ad->a", to_goal, to_goal))
    unit = to_goal / np.maximum(dist, np.finfo(np.float64).tiny)[:, None]
    rel = obs - pos[:, None, :]

    def hits(end: FloatArray) -> BoolArray:
        start = np.minimum(p.step_m, end)
        with np.errstate(invalid="ignore", over="ignore"):
            t = np.clip(np.einsum("amd,ad->am", rel, unit), start[:, None], end[:, None])
            off = rel - t[:, :, None] * unit[:, None, :]
            out: BoolArray = (np.einsum("amd,amd->am", off, off) < c2) & mask
        return out

    near_m = min(p.nav_sight_points_m, p.nav_sight_m)
    out: BoolArray = np.zeros(pos.shape[0], dtype=bool)
    if near_m > 0.0:
        out |= hits(np.minimum(dist, near_m)).any(axis=1)
    hit = hits(np.minimum(dist, p.nav_sight_m))
    with np.errstate(invalid="ignore", over="ignore"):
        along = np.einsum("amd,ad->am", rel, unit)
    for a in np.flatnonzero(hit.any(axis=1) & ~out):
        order = np.where(hit[a], along[a], np.inf)
        picks = np.argpartition(order, min(3, obs.shape[1]) - 1)[: min(3, obs.shape[1])]
        with np.errstate(invalid="ignore", over="ignore"):
            gap = obs[a][None, :, :] - obs[a][picks][:, None, :]
            d2 = np.einsum("fmd,fmd->fm", gap, gap)
        close = (d2 < 0.45**2) & (d2 > 0.0) & mask[a][None, :]
        out[a] = bool(((close.sum(axis=1) >= 2) & hit[a][picks]).any())
    return out


@pytest.mark.parametrize("dim", [2, 3])
def test_the_sight_test_equals_the_all_points_test(dim: int) -> None:
    """Each pick compared only with the points near the line answers what comparing it with every known point
    answered: agents on a 0.1 m lattice (ties along the line), walls of neighbours and isolated points, masks."""
    maps = BapfNavPlanner(PlannerParams(dim=dim))._sight
    rng = np.random.default_rng(31 + dim)
    answers: list[bool] = []
    for _ in range(20):
        n_agents, width = 150, 60
        pos = np.round(rng.uniform(-3.0, 3.0, (n_agents, dim)), 1)
        along_axis = rng.random(n_agents) < 0.5
        ahead = np.where(along_axis[:, None], np.eye(dim)[0] * 20.0, np.round(rng.uniform(-12, 12, (n_agents, dim)), 1))
        spread = np.r_[1.0, np.full(dim - 1, 0.15)]
        obs = pos[:, None, :] + np.round(rng.uniform(-1.0, 9.0, (n_agents, width, dim)) * spread, 1)
        known = rng.random((n_agents, width)) < 0.8
        obs[~known] = np.nan
        got = maps.blocked(np.ones(n_agents, dtype=bool), pos, pos + ahead, obs, known)
        assert got.tolist() == _sight_all_points(maps, pos, pos + ahead, obs, known).tolist()
        answers.extend(got.tolist())
    assert any(answers) and not all(answers)
