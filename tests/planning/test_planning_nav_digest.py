"""Decisions of bapf-nav and bendyruler pinned by a digest: speed work must not change what they choose.

The digests hash the chosen bacteria point of every step (single-agent ``step`` on a bundled world and on
crowded random scenes, 2D and 3D) and the outcome and iteration count of every trial of a small study (lockstep
``step_batch`` with state, 2D and 3D, with noise). They were recorded before the planners were optimised
(commit 0dc893d) and must stay equal. ``python tests/planning/test_planning_nav_digest.py`` prints them, plus
an exact digest of the float outputs (next points, path lengths) that shows whether results are bit-identical.
"""

from __future__ import annotations

import dataclasses
import hashlib

import numpy as np
import pytest

from apf_companion.planning import Decision, PlannerParams, get_planner
from sim.study.config import Density, StudyConfig
from sim.study.engine import simulate
from sim.study.worlds import draw_worlds
from sim.world.files import example_world_path, load_world
from sim.world.scan import ScanMemory

# bapf-nav re-pinned on branch pathratio (was 2f2d1b990ae7b400): the early escape by sight (nav_sight_m), the
# refresh of outdated fields, the seen exits (nav_seen_m) and the quarter-step progress rule change its decisions
# on purpose (docs/planner.md, Design items 4 and 7). Re-pinned in session 16 (was 93ef69b61fde5ce3): any known
# point within C of the line of sight's first ``nav_sight_points_m`` blocks it too, not only surfaces
# (``EscapeMaps.sight_blocked``). Re-pinned in session 22 (was 0883da6fed753d07): a field that closes the agent in
# is computed again at C - h / 2 (``EscapeMaps.loose_m``); of the scenarios only the 2D walks in thickets of 300
# points changed (agents enclosed by their 8 m ball of points); the world flights and the studies hash the same.
# Then (was 687321b0f5a5709f) dead ends whose cells are blocked already mark the free corners of the refused
# points' stencils (``navescape.mark_dead_end``), and (was 3936c9e1c0c13ae9) an agent with no value on its field
# gives up when its own cell is free (closed in) instead of backing out: again only the 2D thicket walks changed.
# bendyruler unchanged.
PINNED = {
    "bapf-nav": "93ea50c065f5690c",
    "bendyruler": "549eac0d9465ed7b",
}


class _Digest:
    def __init__(self) -> None:
        self.decisions = hashlib.sha256()
        self.floats = hashlib.sha256()

    def add(self, decisions: np.ndarray, floats: np.ndarray) -> None:
        """Hash integer decisions and, separately, the exact bytes of float outputs."""
        self.decisions.update(np.ascontiguousarray(decisions, dtype=np.int64).tobytes())
        self.floats.update(np.ascontiguousarray(floats, dtype=np.float64).tobytes())


def _add_decision(digest: _Digest, d: Decision, pos: np.ndarray) -> None:
    index = -1 if d.chosen_index is None else d.chosen_index
    digest.add(np.array([index, int(d.reason)]), d.next_point_m if d.next_point_m is not None else pos)


def _world_flight(name: str, planner_name: str, dim: int, steps: int, digest: _Digest) -> None:
    """``step`` along a bundled world with a remembered scan cloud (hundreds of wall points), no noise."""
    world = load_world(example_world_path(name))
    planner = get_planner(planner_name, PlannerParams(dim=dim))
    start = np.asarray(world.start_ne_m if world.start_ne_m is not None else (3.0, 3.0), dtype=np.float64)
    goal = np.asarray(world.goal_ne_m if world.goal_ne_m is not None else (22.0, 22.0), dtype=np.float64)
    pos = np.concatenate([start, [5.0]])[:dim]
    target = np.concatenate([goal, [5.0]])[:dim]
    scanner = ScanMemory(world)
    for _ in range(steps):
        cloud = scanner.scan(pos)
        if dim == 3:
            cloud = np.concatenate([cloud, np.full((cloud.shape[0], 1), 5.0)], axis=1)
        d = planner.step(pos, target, cloud)
        _add_decision(digest, d, pos)
        if d.next_point_m is None:
            break
        pos = d.next_point_m


def _scene_walks(planner_name: str, dim: int, n_points: int, digest: _Digest) -> None:
    """``step`` runs of 12 moves from 12 crowded random scenes (obstacles fixed, in the 8 m ball)."""
    rng = np.random.default_rng(n_points * 10 + dim)
    planner = get_planner(planner_name, PlannerParams(dim=dim))
    target = np.full(dim, 22.0)
    for _ in range(12):
        pos = rng.uniform(4.0, 20.0, dim)
        direction = rng.normal(size=(n_points, dim))
        direction /= np.linalg.norm(direction, axis=1, keepdims=True)
        obstacles = pos + np.maximum(8.0 * rng.random((n_points, 1)) ** (1.0 / dim), 0.7) * direction
        planner.reset()  # type: ignore[attr-defined]
        for _ in range(12):
            d = planner.step(pos, target, obstacles)
            _add_decision(digest, d, pos)
            if d.next_point_m is None:
                break
            pos = d.next_point_m


def _study(planner_name: str, dim: int, trials: int, digest: _Digest) -> None:
    """Lockstep study trials with noise (``step_batch`` with state) at a low and a high density."""
    cfg = StudyConfig.reference()
    if dim == 3:
        cfg = dataclasses.replace(
            cfg,
            planner_params=dataclasses.replace(cfg.planner_params, dim=3),
            start_m=(3.0, 3.0, 3.0),
            target_m=(22.0, 22.0, 22.0),
        )
    for i, density in enumerate((Density(n_low=20, n_high=45), Density(n_low=70, n_high=95))):
        worlds = draw_worlds(
            np.random.default_rng(100 + i), trials, density, cfg.obstacle_box_m, dim, cfg.obstacle_sampling
        )
        rec = simulate(cfg, planner_name, worlds, np.random.default_rng(200 + i)).records
        digest.add(np.stack([rec.outcome, rec.iterations]), rec.path_m if rec.path_m is not None else np.zeros(0))


def digests(planner_name: str, trials: int = 40) -> tuple[str, str]:
    """(decision digest, exact float digest) of one planner over all the scenarios above."""
    digest = _Digest()
    for dim in (2, 3):
        _world_flight("u-trap", planner_name, dim, 150, digest)
        for n_points in (30, 300):
            _scene_walks(planner_name, dim, n_points, digest)
        _study(planner_name, dim, trials, digest)
    return digest.decisions.hexdigest()[:16], digest.floats.hexdigest()[:16]


@pytest.mark.parametrize("planner_name", sorted(PINNED))
def test_decisions_equal_the_pinned_digest(planner_name: str) -> None:
    assert digests(planner_name)[0] == PINNED[planner_name]


if __name__ == "__main__":
    import sys

    n_trials = int(sys.argv[1]) if len(sys.argv) > 1 else 40
    for name in sorted(PINNED):
        print(name, n_trials, *digests(name, n_trials))
