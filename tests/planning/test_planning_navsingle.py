"""bapf-nav's single-agent prologue (``navsingle``: the sight, trail and progress rules that ``step`` runs) gives
exactly what the batch path's ``_start`` gives: the line-of-sight answer on scenes full of near-ties, and every
state field, bit for bit, from random states in 2D and 3D; non-finite obstacles take the batch test, silently."""

from __future__ import annotations

import warnings
from typing import Any

import numpy as np
import pytest

from apf_companion.planning import BapfNavPlanner, GiveUp, NavMode, NavState, PlannerParams
from apf_companion.planning.navsingle import SightLine
from tests.planning.same_decision import NAV_STATE_FIELDS


def _lattice_scene(rng: np.random.Generator, dim: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(position, target, obstacles): points on a 0.1 m lattice along the line (ties along it, points exactly C
    from it, walls of neighbours and isolated points), or a crowded 8 m ball."""
    pos = np.round(rng.uniform(-3.0, 3.0, dim), 1)
    axis = rng.integers(0, 3)
    if axis == 0:  # along the first axis: "along" is the exact coordinate difference, so ties are common
        target = pos + np.eye(dim)[0] * rng.choice([0.0, 0.3, 5.0, 20.0])
    elif axis == 1:
        target = pos + np.round(rng.uniform(-12.0, 12.0, dim), 1)
    else:
        target = pos + np.ones(dim) * rng.choice([4.0, 15.0])
    if rng.random() < 0.7:
        n = int(rng.integers(0, 120))
        obstacles = pos + np.round(rng.uniform(-1.0, 9.0, (n, dim)) * np.r_[1.0, np.full(dim - 1, 0.15)], 1)
    else:
        n = int(rng.choice([5, 30, 300]))
        direction = rng.normal(size=(n, dim))
        direction /= np.linalg.norm(direction, axis=1, keepdims=True)
        obstacles = pos + 8.0 * rng.random((n, 1)) ** (1.0 / dim) * direction
    return pos, target, obstacles


@pytest.mark.parametrize("dim", [2, 3])
@pytest.mark.parametrize("sight_m", [8.0, 3.0, 0.0])
@pytest.mark.parametrize("points_m", [2.0, 0.0, 8.0])
def test_the_single_agent_sight_equals_the_batch_test(dim: int, sight_m: float, points_m: float) -> None:
    params = PlannerParams(dim=dim, nav_sight_m=sight_m, nav_sight_points_m=points_m)
    planner = BapfNavPlanner(params)
    maps, sight = planner._sight, SightLine(params, params.clearance_m)
    rng = np.random.default_rng(7 + dim)
    answers = []
    for _ in range(400):
        pos, target, obstacles = _lattice_scene(rng, dim)
        goal_vec = target - pos
        g0 = float(np.sqrt(np.einsum("ad,ad->a", goal_vec[None], goal_vec[None]))[0])
        single = sight(obstacles - pos, obstacles, goal_vec, g0)
        every = np.ones(1, dtype=bool)
        batch = maps.blocked(every, pos[None], target[None], obstacles[None], None)
        assert single == bool(batch[0])
        answers.append(single)
    assert any(answers) == (sight_m > 0.0)  # the scenes do block (and sometimes not)
    assert not all(answers)


def _random_state(rng: np.random.Generator, dim: int, target: np.ndarray, patience: int) -> NavState:
    state = NavState.empty(1, dim)
    state.target_m[0] = target
    state.mode[0] = rng.choice([NavMode.DIRECT, NavMode.ESCAPE, NavMode.GAVE_UP])
    state.hit_dist_m[0] = rng.choice([np.inf, rng.uniform(0.0, 30.0)])
    state.best_dist_m[0] = rng.choice([np.inf, rng.uniform(0.0, 30.0)])
    state.since_best[0] = rng.choice([0, patience - 1, patience, int(rng.integers(0, patience))])
    state.since_field[0] = rng.choice([0, 7, 2**30])
    filled = int(rng.integers(0, 70))
    state.trail_m[0, : min(filled, 64)] = rng.uniform(-3.0, 3.0, (min(filled, 64), 2))
    state.trail_next[0] = filled % 64
    if state.mode[0] == NavMode.GAVE_UP:  # a cause from before: kept, not overwritten by the patience rule
        state.gave_up[0] = rng.choice([GiveUp.NO_WAY, GiveUp.NO_PROGRESS, GiveUp.OUTSIDE_AREA])
    return state


#: A cross of two 8 m wide arms, 60 m long, over the scenes' positions (within 3 m of the centre): a concave flying
#: area whose corners hold targets outside it, and lines that leave it (``area.leaves_area``).
_CROSS = (
    (-4.0, -30.0), (4.0, -30.0), (4.0, -4.0), (30.0, -4.0), (30.0, 4.0), (4.0, 4.0),
    (4.0, 30.0), (-4.0, 30.0), (-4.0, 4.0), (-30.0, 4.0), (-30.0, -4.0), (-4.0, -4.0),
)  # fmt: skip


#: Keep-out zones among the scenes' lines: a square on the first axis, a triangle on the diagonal.
_KEEPOUTS = (((2.0, -1.0), (4.0, -1.0), (4.0, 1.0), (2.0, 1.0)), ((6.0, 5.0), (9.0, 6.0), (6.0, 9.0)))


@pytest.mark.parametrize(
    ("area", "keepouts"), [(None, ()), (_CROSS, ()), (None, _KEEPOUTS)], ids=["no area", "polygon", "keep-outs"]
)
@pytest.mark.parametrize("dim", [2, 3])
def test_the_single_agent_start_updates_the_state_as_the_batch_start(dim: int, area: Any, keepouts: Any) -> None:
    planner = BapfNavPlanner(PlannerParams(dim=dim, nav_area_ne_m=area, nav_keepout_ne_m=keepouts))
    patience = planner.params.nav_patience_steps
    rng = np.random.default_rng(dim)
    modes = set()
    for _ in range(300):
        pos, target, obstacles = _lattice_scene(rng, dim)
        seed = int(rng.integers(0, 2**32))
        single = _random_state(np.random.default_rng(seed), dim, target, patience)
        batch = _random_state(np.random.default_rng(seed), dim, target, patience)
        goal_vec, g0, rel, r2 = planner._start_one(pos, target, obstacles, single)
        goal_b, g0_b = planner._start(pos[None], target[None], obstacles[None], None, batch)
        assert goal_vec.tobytes() == goal_b[0].tobytes() and np.float64(g0).tobytes() == g0_b[0].tobytes()
        assert rel.tobytes() == (obstacles - pos).tobytes()
        assert r2.tobytes() == np.einsum("nd,nd->n", rel, rel).tobytes()
        for name in NAV_STATE_FIELDS:
            assert getattr(single, name).tobytes() == getattr(batch, name).tobytes(), name
        modes.add(int(batch.mode[0]))
    assert modes == {NavMode.DIRECT, NavMode.ESCAPE, NavMode.GAVE_UP}


@pytest.mark.parametrize("bad", [np.nan, np.inf, -np.inf, 1e200])
def test_non_finite_or_huge_obstacles_take_the_batch_sight_test_without_warnings(bad: float) -> None:
    """A wall across the line with one unusable point: the same answer as the batch test (blocked), no
    RuntimeWarning from the single-agent rules."""
    planner = BapfNavPlanner(PlannerParams())
    wall = np.stack([np.full(21, 5.0), np.linspace(-2.0, 2.0, 21)], axis=1)
    wall[3, 1] = bad
    target = np.array([20.0, 0.0])
    single, batch = planner.initial_state(1), planner.initial_state(1)
    single.target_m[0] = batch.target_m[0] = target
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        planner._start_one(np.zeros(2), target, wall, single)
        planner._start(np.zeros((1, 2)), target[None], wall[None], None, batch)
    assert single.mode[0] == batch.mode[0] == NavMode.ESCAPE  # the wall blocks
    assert single.hit_dist_m[0] == batch.hit_dist_m[0] == 20.0


def test_the_trail_is_recorded_as_by_the_batch_rule_at_the_spacing() -> None:
    """Positions about 1 m (the spacing) from the last trail point, on and either side of it."""
    planner = BapfNavPlanner(PlannerParams())
    rng = np.random.default_rng(3)
    recorded = set()
    for _ in range(400):
        last = rng.uniform(-50.0, 50.0, 2)
        angle = rng.uniform(0.0, 2.0 * np.pi)
        radius = rng.choice([1.0, np.nextafter(1.0, 0.0), np.nextafter(1.0, 2.0), rng.uniform(0.9, 1.1)])
        pos = last + radius * np.array([np.cos(angle), np.sin(angle)])
        if rng.random() < 0.2:
            pos = last + np.array([0.6, 0.8]) * rng.choice([-1.0, 1.0])
        single, batch = NavState.empty(1, 2), NavState.empty(1, 2)
        for state in (single, batch):
            state.trail_m[0, 5] = last
            state.trail_next[0] = 6
        planner._start_one._record(pos, single)
        batch.record(pos[None], 1.0)
        assert single.trail_m.tobytes() == batch.trail_m.tobytes()
        assert single.trail_next.tobytes() == batch.trail_next.tobytes()
        recorded.add(int(batch.trail_next[0]))
    assert recorded == {6, 7}
