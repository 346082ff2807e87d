"""bapf-nav's single-agent path (``navone.DirectStep``, what ``step`` runs in DIRECT mode) decides exactly as the
batch path (``step_batch``): every field of the decision, bit for bit, over open, crowded, boxed-in and
inside-the-clearance scenes, in 2D and 3D and with the optional terms switched off."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from apf_companion.planning import BapfNavPlanner, Decision, NavMode, NavState, PlannerParams
from apf_companion.planning.navone import DirectStep, einsum
from tests.planning.same_decision import assert_same_decision

_PARAMS = {
    "defaults": PlannerParams(),
    "no look-ahead": PlannerParams(nav_lookahead_m=0.0),
    "no clearance term": PlannerParams(nav_clearance_gain_m=0.0),
}


def _direct(
    one: DirectStep, position: np.ndarray, obstacles: np.ndarray, target: np.ndarray, prev_dir: np.ndarray
) -> Decision | None:
    """``one``'s step with the obstacles relative to the agent and the goal vector, as ``step`` passes them."""
    rel = obstacles - position
    goal_vec = target - position
    return one(position, rel, np.einsum("nd,nd->n", rel, rel), goal_vec, float(np.linalg.norm(goal_vec)), prev_dir)


def _pocket(dim: int) -> np.ndarray:
    """A ring of 7 points 0.7 m around the origin: no 0.4 m move keeps C = 0.6 m (boxed in)."""
    angles = 2.0 * np.pi * (np.arange(7) + 0.3) / 7.0
    ring = 0.7 * np.stack([np.cos(angles), np.sin(angles)], axis=1)
    return ring if dim == 2 else np.concatenate([ring, np.zeros((7, 1))], axis=1)


def _scenes(dim: int) -> list[tuple[np.ndarray, np.ndarray, np.ndarray]]:
    """(start, target, obstacles): crowded 8 m balls (the benchmark's scenes; noise-free agents often start inside
    the clearance there), a boxed-in pocket, one obstacle inside the clearance, none, and a target within a step."""
    rng = np.random.default_rng(dim)
    target = np.full(dim, 22.0)
    out = []
    for n_points in (5, 30, 300):
        for _ in range(6):
            pos = rng.uniform(4.0, 20.0, dim)
            direction = rng.normal(size=(n_points, dim))
            direction /= np.linalg.norm(direction, axis=1, keepdims=True)
            radius = np.maximum(8.0 * rng.random((n_points, 1)) ** (1.0 / dim), 0.5)
            out.append((pos, target, pos + radius * direction))
    origin = np.zeros(dim)
    out.append((origin, target, _pocket(dim)))
    out.append((origin, target, np.eye(dim)[:1] * 0.3))
    out.append((origin, target, np.zeros((0, dim))))
    out.append((origin, np.eye(dim)[0] * 0.2, np.eye(dim)[1:2] * 1.5))
    return out


@pytest.mark.parametrize("dim", [2, 3])
@pytest.mark.parametrize("which", sorted(_PARAMS))
def test_step_equals_the_batch_row_in_every_field(dim: int, which: str) -> None:
    params = dataclasses.replace(_PARAMS[which], dim=dim)
    single, batch = BapfNavPlanner(params), BapfNavPlanner(params)
    for start, target, obstacles in _scenes(dim):
        single.reset()
        state = batch.initial_state(1)
        pos = start
        for _ in range(8):
            d = single.step(pos, target, obstacles)
            row = batch.step_batch(
                pos[None], target[None], obstacles[None], np.ones((1, len(obstacles)), bool), state=state
            ).row(0)
            assert_same_decision(d, row)
            if d.next_point_m is None:
                break
            pos = d.next_point_m


@pytest.mark.parametrize("dim", [2, 3])
def test_the_single_agent_path_decides_boxed_in_and_inside_the_clearance(dim: int) -> None:
    """The squeeze-out and the inside-the-clearance rule are the single-agent path's own (no batch fallback)."""
    planner = BapfNavPlanner(PlannerParams(dim=dim))
    p = planner.params
    one = DirectStep(p, planner.bacteria_offsets_m, planner.bacteria_offsets_m / p.step_m, p.clearance_m, 2.2)
    target = np.full(dim, 20.0)
    origin = np.zeros(dim)
    for obstacles in (_pocket(dim), np.eye(dim)[:1] * 0.3):
        d = _direct(one, origin, obstacles, target, np.zeros((1, dim)))
        assert d is not None and d.moved
    if dim == 2:  # the pocket boxes a 2D agent in: no move keeps C, it squeezes out
        d = _direct(one, origin, _pocket(2), target, np.zeros((1, 2)))
        assert d is not None and d.n_safe == 0 and d.n_passing == 0


def test_a_step_that_enters_escape_falls_back_to_the_batch_path() -> None:
    """A wall across the way: no point passes, the agent enters ESCAPE, which the batch path decides."""
    planner = BapfNavPlanner(PlannerParams())
    wall = np.stack([np.full(81, 1.0), np.linspace(-4.0, 4.0, 81)], axis=1)
    p = planner.params
    one = DirectStep(p, planner.bacteria_offsets_m, planner.bacteria_offsets_m / p.step_m, p.clearance_m, 2.2)
    target = np.array([3.0, 0.0])
    assert _direct(one, np.zeros(2), wall, target, np.zeros((1, 2))) is None
    planner.step(np.zeros(2), target, wall)
    state = planner._own
    assert isinstance(state, NavState) and state.mode[0] == NavMode.ESCAPE


def test_the_single_agent_einsum_is_numpys_bit_for_bit() -> None:
    """``navone.einsum`` (numpy's C einsum without its wrapper) gives np.einsum's bytes on the path's layouts."""
    rng = np.random.default_rng(5)
    for dim in (2, 3):
        rel = rng.normal(size=(300, dim)) * 7.0
        unit = rng.normal(size=dim)
        for subscripts, operands in (
            ("nd,nd->n", (rel, rel)),
            ("amd,ad->am", (rel[None], unit[None])),
            ("amd,amd->am", (rel[None], rel[None])),
            ("ad,ad->a", (unit[None], unit[None])),
            ("kd,kd->k", (rel[:60], rel[:60])),
        ):
            assert einsum(subscripts, *operands).tobytes() == np.einsum(subscripts, *operands).tobytes()
