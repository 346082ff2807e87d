"""bapf-nav's batch line-of-sight test (``navsight.sight_blocked``) runs in 2D on the coordinate planes with the
sums of two products written out; it answers exactly what the einsum form of the test answers (kept here as the
reference), on batches of lattice scenes full of points exactly C from the line, with masks and unknown non-finite
rows, in 2D and 3D."""

from __future__ import annotations

import numpy as np
import numpy.typing as npt
import pytest

from apf_companion.planning import PlannerParams
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
