"""apf-sim fly with world files: negative start coordinates reach the vehicle, every bundled world loads."""

from __future__ import annotations

import json
import os
import subprocess
import sys
import tomllib
from pathlib import Path

import pytest

from apf_companion.builders import build_planner
from apf_companion.config import config_from_mapping
from sim.cli import build_parser
from sim.fly import FlyOptions, _service_toml, _sim_argv
from sim.flycli import _route
from sim.world import EXAMPLES_DIR, load_world


def test_negative_start_is_one_word_for_the_vehicle() -> None:
    argv = _sim_argv(FlyOptions(start_ne_m=(-12.0, 0.0), world="slit"), 14550, 14551)
    assert "--start=-12.0,0.0" in argv
    assert "--start" not in argv
    # The vehicle's own parser (everything after "python -m sim") reads it back.
    args = build_parser().parse_args(argv[3:])
    assert args.start == (-12.0, 0.0)
    assert args.world == "slit"


@pytest.mark.parametrize(
    "words",
    [["--start", "-12.0,0.0"], ["--start=-12.0,0.0"], ["--start", "-12,0", "--goal", "4.5,-2"]],
)
def test_fly_cli_takes_negative_pairs(words: list[str]) -> None:
    args = build_parser().parse_args(["fly", "--world", "slit", *words])
    route = _route(args)
    assert route.start_ne_m[0] == -12.0 and route.area_ne_m is None  # slit has no flying area
    assert route.goal_ne_m == ((4.5, -2.0) if "--goal" in words else (16.0, 0.0))


def test_fly_cli_still_rejects_a_missing_value() -> None:
    with pytest.raises(SystemExit):
        build_parser().parse_args(["fly", "--start", "--quiet"])


@pytest.mark.parametrize("name", sorted(p.stem for p in EXAMPLES_DIR.glob("*.toml")))
def test_every_bundled_world_gives_fly_its_start_and_goal(name: str) -> None:
    args = build_parser().parse_args(["fly", "--world", name])
    world = load_world(name)
    route = _route(args)
    assert (route.start_ne_m, route.goal_ne_m, route.area_ne_m) == (world.start_ne_m, world.goal_ne_m, world.area_ne_m)
    assert route.keepouts_ne_m == world.keepouts_ne_m
    argv = _sim_argv(FlyOptions(world=name, start_ne_m=route.start_ne_m), 1, 2)
    assert build_parser().parse_args(argv[3:]).start == world.start_ne_m


@pytest.mark.parametrize("words", [[], ["--no-area"], ["--planner", "bendyruler"]])
def test_a_world_s_flying_area_reaches_the_service_s_planner(tmp_path: Path, words: list[str]) -> None:
    """``apf-sim fly --world wall-gap`` writes the world file's flying area into the service's config as
    ``planner.params.nav_area_ne_m``, and the service's planner gets it; ``--no-area`` and the other planners
    (which have no such parameter) fly without it."""
    args = build_parser().parse_args(["fly", "--world", "wall-gap", *words])
    r = _route(args)
    start, goal, area = r.start_ne_m, r.goal_ne_m, r.area_ne_m
    opt = FlyOptions(planner=args.planner, world="wall-gap", start_ne_m=start, goal_ne_m=goal, area_ne_m=area)
    text = _service_toml(opt, 14550, tmp_path / "c.tlog")
    planner = build_planner(config_from_mapping(tomllib.loads(text)))
    want = None if words else (-3.0, -12.0, 23.0, 12.0)
    assert planner.params.nav_area_ne_m == want
    assert ("nav_area_ne_m" in text) == (want is not None)


def test_a_world_s_polygonal_area_reaches_the_service_s_planner(tmp_path: Path) -> None:
    """yard-l's flying area is a polygon: written into the service's config as TOML pairs, read back the same."""
    args = build_parser().parse_args(["fly", "--world", "yard-l"])
    r = _route(args)
    start, goal, area = r.start_ne_m, r.goal_ne_m, r.area_ne_m
    assert area is not None and len(area) == 6
    opt = FlyOptions(planner=args.planner, world="yard-l", start_ne_m=start, goal_ne_m=goal, area_ne_m=area)
    planner = build_planner(config_from_mapping(tomllib.loads(_service_toml(opt, 14550, tmp_path / "c.tlog"))))
    assert planner.params.nav_area_ne_m == area


def test_a_world_s_keep_out_zones_reach_the_service_s_planner(tmp_path: Path) -> None:
    """Keep-out zones in the world file go into the service's config as ``nav_keepout_ne_m`` (TOML three deep)."""
    zones = (((7.0, -3.0), (13.0, -3.0), (13.0, 3.0), (7.0, 3.0)), ((20.0, 5.0), (22.0, 5.0), (21.0, 7.0)))
    opt = FlyOptions(world="wall-gap", start_ne_m=(0.0, 0.0), goal_ne_m=(20.0, 0.0), keepouts_ne_m=zones)
    planner = build_planner(config_from_mapping(tomllib.loads(_service_toml(opt, 14550, tmp_path / "c.tlog"))))
    assert planner.params.nav_keepout_ne_m == zones and planner.params.nav_area_ne_m is None


def test_fly_fence_serves_the_area_from_the_vehicle_instead_of_the_config(tmp_path: Path) -> None:
    """``apf-sim fly --world yard-l --fence``: the vehicle gets ``--fence`` (it serves the area as its fence) and
    the service's config has no area, so the service reads it from the vehicle (``planner.fence_area``)."""
    args = build_parser().parse_args(["fly", "--world", "yard-l", "--fence"])
    r = _route(args)
    start, goal, area = r.start_ne_m, r.goal_ne_m, r.area_ne_m
    opt = FlyOptions(world="yard-l", start_ne_m=start, goal_ne_m=goal, area_ne_m=area, fence=args.fence)
    assert "--fence" in _sim_argv(opt, 14550, 14551)
    config = config_from_mapping(tomllib.loads(_service_toml(opt, 14550, tmp_path / "c.tlog")))
    assert config.planner.fence_area and build_planner(config).params.nav_area_ne_m is None
    plain = FlyOptions(world="yard-l", start_ne_m=start, goal_ne_m=goal, area_ne_m=area)
    assert "--fence" not in _sim_argv(plain, 14550, 14551)
    proc = subprocess.run(
        [sys.executable, "-m", "sim.cli", "vehicle", "--world", "slit", "--fence", "--duration", "0.1"],
        capture_output=True, text=True, timeout=60, check=False,
    )  # fmt: skip
    assert proc.returncode != 0 and "--fence: the world has no flying area" in proc.stderr


def test_fly_passes_vehicle_parameters_on() -> None:
    """``--vehicle-param FENCE_MARGIN=0.5`` reaches the simulated autopilot as ``--param``, which checks it."""
    args = build_parser().parse_args(["fly", "--world", "wall-gap", "--fence", "--vehicle-param", "FENCE_MARGIN=0.5"])
    r = _route(args)
    opt = FlyOptions(
        world="wall-gap", start_ne_m=r.start_ne_m, goal_ne_m=r.goal_ne_m, area_ne_m=r.area_ne_m, fence=True,
        vehicle_params=tuple(args.vehicle_param),
    )  # fmt: skip
    argv = _sim_argv(opt, 14550, 14551)
    assert argv[argv.index("FENCE_MARGIN=0.5") - 1] == "--param"
    proc = subprocess.run(
        [sys.executable, "-m", "sim.cli", "vehicle", "--param", "FENCE_MARGIN=11", "--duration", "0.1"],
        capture_output=True, text=True, timeout=60, check=False,
    )  # fmt: skip
    assert proc.returncode != 0 and "FENCE_MARGIN 11 not in [0, 10]" in proc.stderr


@pytest.mark.slow
def test_fly_world_from_a_negative_start(tmp_path: Path) -> None:
    out = tmp_path / "out"
    proc = subprocess.run(
        [
            sys.executable, "-m", "sim", "fly", "--world", "slit", "--start", "-2.0,0.5", "--max-flight", "12",
            "--out", str(out), "--quiet", "--no-plot",
        ],
        capture_output=True,
        text=True,
        timeout=110,
        env=os.environ | {"OPENBLAS_NUM_THREADS": "1"},
        check=False,
    )  # fmt: skip
    sim_res = json.loads((out / "sim_result.json").read_text())
    assert sim_res["trajectory_ned_m"][0][:2] == [-2.0, 0.5], proc.stdout + proc.stderr
    assert sim_res["world"]["name"] == "slit"
