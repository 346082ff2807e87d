"""apf-sim fly sweeps: the study's rate on exactly the worlds the simulator flew."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from sim.cli import build_parser
from sim.fly import FlyOptions, _sim_argv, flown_world, paper_world, study_same_worlds
from sim.flysweep import _study_summary
from sim.vehicle.cli import _world as vehicle_world


@pytest.mark.parametrize(("obstacles", "seed"), [("low", 2000), ("high", 3018), ("37", 5)])
def test_paper_world_is_the_field_the_vehicle_flies(obstacles: str, seed: int, tmp_path: Path) -> None:
    opt = FlyOptions(seed=seed, obstacles=obstacles, out=tmp_path)
    # The simulator's own world builder, fed the exact argv fly starts it with.
    argv = _sim_argv(opt, 14550, 14551)
    args = build_parser().parse_args(argv[argv.index("-m") + 2 :])
    flown = np.asarray(vehicle_world(args).circles_ne_m)
    ours = np.asarray(paper_world(opt).circles_ne_m)
    assert flown.shape[0] >= 20
    np.testing.assert_array_equal(ours, flown)
    # A sim_result.json's world wins over the regenerated one (it is what collisions were checked against).
    sim_res = {"world": {"circles_ne_m": [[1.0, 2.0], [3.0, 4.0]]}}
    np.testing.assert_array_equal(flown_world(opt, sim_res), [[1.0, 2.0], [3.0, 4.0]])
    np.testing.assert_array_equal(flown_world(opt, None), flown)


def test_study_same_worlds_counts_per_world() -> None:
    empty = np.zeros((0, 2))
    # A wall of points 0.3 m apart on n + e = 35, across the way from (3, 3) to (22, 22): no safe point gets
    # through it; the empty field always succeeds.
    t = np.linspace(0.0, 1.0, 120)[:, None]
    wall = np.hstack([5.0 + 25.0 * t, 30.0 - 25.0 * t])
    succ = study_same_worlds([empty, wall], preset="reference", planner="cr-bapf*", replications=4, seed=1)
    assert succ.dtype == np.int64
    assert succ.tolist()[0] == 4
    assert succ.tolist()[1] == 0
    again = study_same_worlds([empty, wall], preset="reference", planner="cr-bapf*", replications=4, seed=1)
    np.testing.assert_array_equal(succ, again)


def test_sweep_summary_has_study_rate_on_the_same_worlds() -> None:
    base = FlyOptions(seed=2000, obstacles="low", planner="cr-bapf*")
    fields = [np.asarray(paper_world(FlyOptions(seed=2000 + k, obstacles="low")).circles_ne_m) for k in range(3)]
    records: list[dict[str, Any]] = [{"outcome": "arrived"}, {"outcome": "collision"}, {"outcome": "arrived"}]
    study = _study_summary(base, records, fields, replications=6)
    per_world = study_same_worlds(fields, preset="reference", planner="cr-bapf*", replications=6, seed=2000)
    assert [r["study_successes"] for r in records] == per_world.tolist()
    assert study["rate"] == pytest.approx(per_world.sum() / 18)
    assert study["replications"] == 6
    assert study["trials"] == 18
    lo, hi = study["ci95"]
    assert 0.0 <= lo <= study["rate"] <= hi <= 1.0
    fly_rate = 2 / 3
    assert study["fly_minus_study"] == pytest.approx(fly_rate - per_world.mean() / 6)
    assert all(0.0 <= r["study_rate_no_noise"] <= 1.0 for r in records)
    assert 0.0 <= study["no_noise"]["rate"] <= 1.0
    json.dumps(study)  # goes into sweep.json as it is
