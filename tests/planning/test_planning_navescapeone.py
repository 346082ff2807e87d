"""bapf-nav's single-agent ESCAPE path (``navescapeone``: what ``step`` runs in ESCAPE mode and when it enters it)
decides exactly as the batch path (``step_batch``): every field of every decision and every state field, the
escape field's cells and distances included, bit for bit, along noisy flights through traps, gaps, thickets and
a boxed goal (a growing memory: outdated fields, stall and dead-end refreshes, frame shifts), in
2D and 3D and with the optional rules switched off."""

from __future__ import annotations

import dataclasses
from collections.abc import Iterator
from typing import Any

import numpy as np
import pytest

from apf_companion.planning import BapfNavPlanner, Decision, GiveUp, NavMode, NavState, PlannerParams
from apf_companion.planning.navescapeone import FieldSampler
from apf_companion.planning.navfield import NavGrid
from apf_companion.planning.navstate import NavField
from tests.planning.same_decision import NAV_STATE_FIELDS, assert_same_decision

_PARAMS = {
    "defaults": PlannerParams(),
    "no trail closure": PlannerParams(nav_seen_m=0.0),
    "no sight, replan often": PlannerParams(nav_sight_m=0.0, nav_replan_steps=3),
    "no clearance term": PlannerParams(nav_clearance_gain_m=0.0),
    # Holds every start, target and point of ``_worlds`` (the thickets reach 28 m): a grid of 100 x 120 cells.
    "a flying area": PlannerParams(nav_area_ne_m=(-4.0, -8.0, 26.0, 28.0)),
    # The same bounds less a slot (north 3-4.5, east 1-28) that the straight line of the wall world crosses: a
    # line that leaves the polygon starts an escape (``area.leaves_area``), on both paths.
    # Two keep-out zones across the worlds' lines (a moving grid: their cells per corner): one on the first
    # metres of the straight line from (0, 0), one in the thickets.
    "keep-out zones": PlannerParams(
        nav_keepout_ne_m=(((1.0, 0.5), (2.5, 0.5), (2.5, 3.5), (1.0, 3.5)), ((14.0, 14.0), (17.0, 15.0), (15.0, 18.0)))
    ),
    # The same polygon reaching 100 m north: wider than the fixed grid's 256 cells, so planned on the moving grid
    # with the cells outside the polygon closed per corner (``NavGrid``), on both paths.
    "a wide polygonal area": PlannerParams(
        nav_area_ne_m=(
            (-4.0, -8.0),
            (100.0, -8.0),
            (100.0, 28.0),
            (4.5, 28.0),
            (4.5, 1.0),
            (3.0, 1.0),
            (3.0, 28.0),
            (-4.0, 28.0),
        )
    ),
    "a polygonal area": PlannerParams(
        nav_area_ne_m=(
            (-4.0, -8.0),
            (26.0, -8.0),
            (26.0, 28.0),
            (4.5, 28.0),
            (4.5, 1.0),
            (3.0, 1.0),
            (3.0, 28.0),
            (-4.0, 28.0),
        )
    ),
}


def _assert_same_state(single: NavState, batch: NavState) -> None:
    for name in NAV_STATE_FIELDS:
        assert getattr(single, name).tobytes() == getattr(batch, name).tobytes(), name
    a, b = single.field[0], batch.field[0]
    assert (a is None) == (b is None)
    if a is not None and b is not None:
        for name in ("origin_m", "blocked", "dist_m", "virtual"):
            assert getattr(a, name).tobytes() == getattr(b, name).tobytes(), name
        assert [key for key, _ in a.memo] == [key for key, _ in b.memo]
        assert a.occupancy is not None and b.occupancy is not None
        assert a.occupancy[0] == b.occupancy[0]
        assert (a.loose is None) == (b.loose is None)
        if a.loose is not None and b.loose is not None:
            assert a.loose.tobytes() == b.loose.tobytes()


def _segment(a: tuple[float, float], b: tuple[float, float]) -> np.ndarray:
    """Points every 0.2 m from a to b (a sampled surface)."""
    n = max(2, int(np.hypot(b[0] - a[0], b[1] - a[1]) / 0.2) + 1)
    return np.linspace(a, b, n)


def _worlds() -> list[tuple[np.ndarray, np.ndarray, np.ndarray]]:
    """(start, target, surface points) in 2D: a U open towards the agent, a wall with a gap, a box around the
    goal (the way out of the map and back), and thickets of random points (the benchmark's scene: escapes out
    of enclosures)."""
    rng = np.random.default_rng(11)
    u_trap = np.vstack([_segment((3.0, -2.5), (7.0, -2.5)), _segment((7.0, -2.5), (7.0, 2.5))])
    u_trap = np.vstack([u_trap, _segment((7.0, 2.5), (3.0, 2.5))])
    wall = np.vstack([_segment((5.0, -8.0), (5.0, -0.8)), _segment((5.0, 0.8), (5.0, 8.0))])
    box = np.vstack(
        [
            _segment((8.0, -2.0), (12.0, -2.0)),
            _segment((12.0, -2.0), (12.0, 2.0)),
            _segment((12.0, 2.0), (8.0, 2.0)),
            _segment((8.0, 2.0), (8.0, -2.0)),
        ]
    )
    out = [
        (np.zeros(2), np.array([12.0, 0.3]), u_trap),
        (np.zeros(2), np.array([10.0, 3.0]), wall),
        (np.zeros(2), np.array([10.0, 0.0]), box),
    ]
    for _ in range(3):
        pos = rng.uniform(4.0, 20.0, 2)
        direction = rng.normal(size=(300, 2))
        direction /= np.linalg.norm(direction, axis=1, keepdims=True)
        out.append((pos, np.full(2, 22.0), pos + np.maximum(8.0 * rng.random((300, 1)) ** 0.5, 0.5) * direction))
    return out


class _Counting:
    """Counts the calls of the planner's single-agent escape step (the test must exercise it)."""

    def __init__(self, inner: Any) -> None:
        self.inner, self.calls = inner, 0

    def __call__(self, *args: Any) -> Decision:
        self.calls += 1
        result: Decision = self.inner(*args)
        return result


def _fly(
    params: PlannerParams,
    start: np.ndarray,
    target: np.ndarray,
    surface: np.ndarray,
    seed: int,
    junk: bool = False,
    noise_m: float = 0.05,
    steps: int = 140,
    stop_at_goal: bool = False,
) -> dict[str, int]:
    """Fly ``step`` and ``step_batch`` side by side (the batch one replays the single one's positions), with the
    points seen so far within 8 m and position noise (``junk``: plus non-finite rows); returns counts of what
    happened, "arrived" (within 0.7 m of the target; ``stop_at_goal``: the flight ends there) and "gave up"
    among them."""
    single, batch = BapfNavPlanner(params), BapfNavPlanner(params)
    counting = _Counting(single._escape_one)
    single._escape_one = counting  # type: ignore[assignment]
    state = batch.initial_state(1)
    rng = np.random.default_rng(seed)
    dim = params.dim
    if dim == 3:  # surfaces as walls from 0 to 4 m high: points at three heights
        surface = np.vstack([np.hstack([surface, np.full((len(surface), 1), z)]) for z in (0.5, 1.5, 2.5)])
        start, target = np.append(start, 1.5), np.append(target, 1.5)
    seen = np.zeros(len(surface), dtype=bool)
    pos = start
    counts = {"escape steps": 0}
    for _ in range(steps):
        if stop_at_goal and np.linalg.norm(pos[:2] - target[:2]) <= 0.7:
            break
        seen |= np.linalg.norm(surface[:, :2] - pos[:2], axis=1) <= 8.0
        obstacles = surface[seen]
        if junk:  # rows a broken sensor might report: not finite, ignored by both paths
            obstacles = np.vstack([obstacles, np.full((1, dim), np.nan), np.full((1, dim), np.inf)])
        d = single.step(pos, target, obstacles)
        row = batch.step_batch(
            pos[None], target[None], obstacles[None], np.ones((1, len(obstacles)), bool), state=state
        ).row(0)
        assert_same_decision(d, row)
        own = single.own_state
        assert isinstance(own, NavState)
        _assert_same_state(own, state)
        counts["escape steps"] += int(state.mode[0] == NavMode.ESCAPE)
        if d.next_point_m is None:
            if state.mode[0] == NavMode.GAVE_UP:
                break
            pos = pos + rng.normal(0.0, noise_m, dim)
        else:
            pos = d.next_point_m + rng.normal(0.0, noise_m, dim)  # noise: sometimes inside the clearance
    counts["single escape steps"] = counting.calls
    counts["arrived"] = int(np.linalg.norm(pos[:2] - target[:2]) <= 0.7)
    counts["gave up"] = int(state.mode[0] == NavMode.GAVE_UP)
    counts["cause"] = int(single.give_up_cause())
    return counts


@pytest.mark.parametrize("dim", [2, 3])
@pytest.mark.parametrize("which", sorted(_PARAMS))
def test_escape_steps_equal_the_batch_rows_and_states(dim: int, which: str) -> None:
    params = dataclasses.replace(_PARAMS[which], dim=dim)
    totals: dict[str, int] = {}
    for i, (start, target, surface) in enumerate(_worlds()):
        for key, value in _fly(params, start, target, surface, seed=i).items():
            totals[key] = totals.get(key, 0) + value
    assert totals["single escape steps"] >= 100  # the path under test decided many steps
    assert totals["escape steps"] >= 100


@pytest.mark.parametrize("dim", [2, 3])
def test_non_finite_points_are_ignored_as_on_the_batch_path(dim: int) -> None:
    params = PlannerParams(dim=dim)
    start, target, surface = _worlds()[0]
    counts = _fly(params, start, target, surface, seed=0, junk=True)
    assert counts["single escape steps"] >= 50


def _thicket(seed: int, dim: int) -> np.ndarray:
    """The step benchmark's scene around an agent at the origin: 100, 300 or 600 points within 8 m (0.5 m at least)."""
    rng = np.random.default_rng(seed)
    n = int(rng.choice([100, 300, 600]))
    direction = rng.normal(size=(n, dim))
    direction /= np.linalg.norm(direction, axis=1, keepdims=True)
    return np.asarray(np.maximum(8.0 * rng.random((n, 1)) ** (1.0 / dim), 0.5) * direction)


def _thicket_steps(params: PlannerParams, seed: int) -> Iterator[tuple[NavState, NavState]]:
    """Three steps from the origin in ``_thicket(seed)`` on both paths (the same decisions and states, checked):
    the single path's state and the batch path's after each."""
    dim = params.dim
    obstacles = _thicket(seed, dim)
    target, mask = np.full(dim, 22.0), np.ones((1, len(obstacles)), bool)
    single, batch = BapfNavPlanner(params), BapfNavPlanner(params)
    state = batch.initial_state(1)
    for _ in range(3):
        d = single.step(np.zeros(dim), target, obstacles)
        assert_same_decision(
            d, batch.step_batch(np.zeros((1, dim)), target[None], obstacles[None], mask, state=state).row(0)
        )
        own = single.own_state
        assert isinstance(own, NavState)
        _assert_same_state(own, state)
        yield own, state


@pytest.mark.parametrize("dim", [2, 3])
def test_repeated_steps_in_thickets_equal_the_batch_path(dim: int) -> None:
    """The benchmark's pattern: steps from one position in a thicket (the stall and dead-end refreshes, the
    dead-end cells marked as virtual obstacles), the same decisions and states as the batch path."""
    params = PlannerParams(dim=dim)
    marked = 0
    for seed in range(300, 330):
        field = list(_thicket_steps(params, seed))[-1][1].field[0]
        marked += int(field is not None and bool(field.virtual.any()))
    assert marked >= (1 if dim == 2 else 0)  # in 2D a dead end was marked on the single path (seed 312)


@pytest.mark.parametrize("dim", [2])  # in 3D none of these thickets closes the agent in (the slice at its altitude)
def test_a_second_closed_in_refresh_from_the_same_points_reuses_the_loosened_cells(dim: int) -> None:
    """Closed in at C (the thicket of the benchmark's scene): the loosened cells (``NavField.loose``) are computed
    once and a refresh from the same points in the same frame takes them from the field, on both paths; they are
    the cells a fresh ``NavGrid.blocked`` at ``loose_m`` gives, and the steps stay the batch path's."""
    params = PlannerParams(dim=dim)
    found = 0
    for seed in range(300, 330):
        kept: list[tuple[object, object]] = []
        for own, state in _thicket_steps(params, seed):
            a, b = own.field[0], state.field[0]
            if a is not None and b is not None and a.loose is not None and b.loose is not None:
                kept.append((a.loose, b.loose))
        if len(kept) < 2:
            continue
        found += 1
        assert kept[-1][0] is kept[0][0] and kept[-1][1] is kept[0][1]  # reused, not computed again
        field = state.field[0]
        escape = BapfNavPlanner(params)._escape
        xy = _thicket(seed, dim)  # 2D: every point is valid
        fresh = escape.grid.blocked(field.origin_m[None], xy[None], np.ones((1, len(xy)), bool), escape.loose_m)[0]
        assert field.loose is not None and field.loose.tobytes() == fresh.tobytes()
    assert found >= 1


def _room(door_from_m: float, door_to_m: float) -> np.ndarray:
    """A room (north -1..6, east -1..5) whose north wall has a door from east ``door_from_m`` to ``door_to_m``
    (its jambs' last points), surfaces sampled every 0.2 m."""
    return np.vstack(
        [
            _segment((-1.0, -1.0), (-1.0, 5.0)),
            _segment((-1.0, -1.0), (6.0, -1.0)),
            _segment((-1.0, 5.0), (6.0, 5.0)),
            _segment((6.0, -1.0), (6.0, door_from_m)),
            _segment((6.0, door_to_m), (6.0, 5.0)),
        ]
    )


def _door_open(params: PlannerParams, surface: np.ndarray, radius_m: float) -> bool:
    """Whether the grid's cells at ``radius_m`` from the points leave a way through the north wall (north 6)."""
    grid = NavGrid(params.nav_cell_m, 15.0)
    origin = np.array([-3.0, -3.0])  # on the lattice of cell multiples, as every grid's corner; room inside
    blocked = grid.blocked(origin[None], surface[None], np.ones((1, len(surface)), bool), radius_m)[0]
    dist = grid.distances(origin[None], blocked[None], np.array([[11.0, 2.0]]))[0]
    return bool(np.isfinite(grid.sample(origin, dist, np.array([[2.0, 2.0]])))[0])


@pytest.mark.parametrize("dim", [2, 3])
@pytest.mark.parametrize("which", ["defaults", "a flying area"])
def test_a_door_the_lattice_closes_at_c_is_passed_on_the_loosened_field(dim: int, which: str) -> None:
    """A 1.45 m door (the vehicle needs 2 C = 1.2 m) placed so that no cell centre lies in its 0.25 m of free
    centres: at C the room is closed and the agent had no way (it backed out and dithered, as in the rooms
    world, both paths alike). The field computed again at C - h / 2 (``EscapeMaps.loose_m``) opens it: both
    paths agree and the agent flies through to a target beyond the wall."""
    params = dataclasses.replace(_PARAMS[which], dim=dim)
    surface = _room(1.375, 2.825)
    assert not _door_open(params, surface, params.clearance_m)  # the case under test: closed at C
    assert _door_open(params, surface, BapfNavPlanner(params)._escape.loose_m)
    counts = _fly(
        params, np.array([1.0, 0.5]), np.array([10.0, 0.5]), surface, seed=5, noise_m=0.0, steps=300, stop_at_goal=True
    )
    # 14 escape steps in 2D and 3D. Without the loosened field, in 2D: 300 escape steps, neither through nor
    # given up (in 3D the agent climbed over the walls, 117 steps).
    assert counts["arrived"] == 1 and counts["escape steps"] <= 40, counts


def test_a_door_narrower_than_2c_less_a_cell_stays_closed_and_the_agent_gives_up() -> None:
    """A 0.8 m door (narrower than 2 C - h = 0.9 m) is closed at C and at C - h / 2: the agent in the room gives
    up (GAVE_UP) at its first escape step, the same on both paths, and never gets through (2D: in 3D it climbs
    over). Before session 22 it backed out on the clearance term, as from inside an obstacle, and walked the
    room for 310 steps until its patience ran out: its own cell was free, only closed in."""
    params = PlannerParams()
    surface = _room(1.6, 2.4)
    assert not _door_open(params, surface, BapfNavPlanner(params)._escape.loose_m)
    counts = _fly(
        params, np.array([1.0, 0.5]), np.array([10.0, 0.5]), surface, seed=6, noise_m=0.0, steps=600, stop_at_goal=True
    )
    assert counts["gave up"] == 1 and counts["arrived"] == 0 and counts["single escape steps"] == 1, counts
    assert counts["cause"] == GiveUp.NO_WAY


def _enclosed_state(planner: BapfNavPlanner, position: np.ndarray, target: np.ndarray) -> NavState:
    """An escaping agent whose remembered cells close every cell around its own (virtual dead ends), the goal in
    its own cell: its potential is finite, every candidate point's infinite."""
    planner.reset()
    planner.step(position, target, np.zeros((0, position.size)))
    state = planner.own_state
    assert isinstance(state, NavState)
    grid = planner._escape.grid
    origin = grid.origins(position[None, :2], target[None, :2], planner._escape._pad_m)[0]
    centres = origin + (np.stack(np.divmod(np.arange(grid.size), grid.n), axis=1) + 0.5) * grid.cell_m
    near = np.linalg.norm(centres - position[:2], axis=1)
    blocked = (near < 3.0) & (near > 0.5 * grid.cell_m)
    dist = grid.distances(origin[None], blocked[None], target[None, :2])[0]
    state.mode[0], state.hit_dist_m[0], state.since_field[0] = NavMode.ESCAPE, 0.0, 1
    state.field[0] = NavField(origin_m=origin, blocked=blocked, dist_m=dist, virtual=blocked.copy())
    return state


@pytest.mark.parametrize("dim", [2, 3])
def test_no_way_from_any_candidate_gives_up_as_the_batch_path(dim: int) -> None:
    """Every feasible point off the free cells, the agent's own cell on the way: GAVE_UP (``lost``), the same
    decision and state on both paths. Steps of 0.8 m: no candidate point in 2D samples the agent's own cell."""
    params = PlannerParams(dim=dim, step_m=0.8)
    single, batch = BapfNavPlanner(params), BapfNavPlanner(params)
    grid = single._escape.grid
    position = np.full(dim, 10.0)
    position[:2] = (np.floor(position[:2] / grid.cell_m) + 0.5) * grid.cell_m  # a cell centre
    target = position + 0.01
    _enclosed_state(single, position, target)
    state = _enclosed_state(batch, position, target)
    d = single.step(position, target, np.zeros((0, dim)))
    row = batch.step_batch(position[None], target[None], np.zeros((1, 0, dim)), np.ones((1, 0), bool), state=state)
    assert_same_decision(d, row.row(0))
    own = single.own_state
    assert isinstance(own, NavState)
    _assert_same_state(own, state)
    if dim == 2:  # (in 3D the points above and below the agent sample its own cell)
        assert d.reason.name == "GAVE_UP" and own.mode[0] == NavMode.GAVE_UP


def test_the_single_field_sampler_equals_sample_many_bit_for_bit() -> None:
    """``FieldSampler`` (fast, masked interior and clamped paths) against ``NavGrid.sample_many``: fields with
    blocked (inf) cells and a goal cell at 0, points inside, on and beyond the grid's sides and corners."""
    grid = BapfNavPlanner(PlannerParams())._escape.grid
    sampler = FieldSampler(grid.n, grid.cell_m)
    rng = np.random.default_rng(11)
    side = grid.n * grid.cell_m
    paths = set()
    for trial in range(300):
        origin = np.floor(rng.uniform(-20.0, 20.0, 2) / grid.cell_m) * grid.cell_m
        dist = rng.uniform(0.0, 30.0, grid.size)
        dist[rng.random(grid.size) < rng.choice([0.0, 0.05, 0.5, 1.0])] = np.inf
        dist[rng.integers(grid.size)] = 0.0
        centre = origin + rng.choice([side / 2.0, 0.0, side, rng.uniform(0.0, side)])
        points = centre + rng.uniform(-0.6, 0.6, (61, 2))
        if trial % 7 == 0:  # on cell centres and the grid's lines: fractions of exactly 0
            points = origin + (rng.integers(-1, grid.n + 1, (61, 2)) + rng.choice([0.0, 0.5], (61, 2))) * grid.cell_m
        single = sampler(origin, dist, points)
        batch = grid.sample_many(origin[None], dist[None], points[None])[0]
        assert single.tobytes() == batch.tobytes()
        paths.add((bool(np.isfinite(single).all()), bool(np.isinf(single).any())))
    assert len(paths) >= 2  # finite and masked results both occur
