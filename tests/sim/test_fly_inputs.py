"""apf-sim fly refuses bad input before it starts anything (exit 2, a message naming the flag and what it takes),
and says what went wrong when a flight fails: the checks run in-process, the flights on loopback."""

from __future__ import annotations

import asyncio
import dataclasses
import tomllib
from pathlib import Path

import pytest

from apf_companion.config import config_from_mapping
from apf_companion.errors import ConfigError
from sim.cli import build_parser
from sim.cli import main as sim_main
from sim.fly import SPEEDUP_RANGE, FlyOptions, _service_toml, airborne, error_reason, fly, paper_world
from sim.flycli import _route, flight_summary, route_problem, vehicle_params
from sim.flysweep import _fault_summary
from sim.world import EXAMPLES_DIR, World


def _refused(argv: list[str], capsys: pytest.CaptureFixture[str]) -> str:
    """Run ``apf-sim ARGV`` in-process; it must exit 2 (argparse's usage error). Returns its stderr."""
    with pytest.raises(SystemExit) as exc:
        sim_main(argv)
    assert exc.value.code == 2
    return capsys.readouterr().err


@pytest.mark.parametrize("value", ["0", "-1", "nan", "inf", "100", "60.5", "0.05", "fast"])
def test_speedup_outside_what_the_service_accepts_is_refused(
    value: str, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    err = _refused(["fly", f"--speedup={value}", "--out", str(tmp_path / "out")], capsys)
    assert "argument --speedup: must be a number in [0.1, 60]" in err, err
    assert "link.heartbeat_timeout_s" in err
    assert not (tmp_path / "out").exists()


def test_the_speedup_range_is_what_the_service_config_accepts(tmp_path: Path) -> None:
    """At both ends of SPEEDUP_RANGE the service's config (heartbeat timeout, staleness limits, time scale) loads;
    just outside it does not: the range is derived from the config's limits, not a copy of them."""
    lo, hi = SPEEDUP_RANGE
    assert (lo, hi) == (0.1, 60.0)
    for speedup in (lo, 1.0, 5.0, hi):
        config = config_from_mapping(tomllib.loads(_service_toml(FlyOptions(speedup=speedup), 1, tmp_path / "t")))
        assert config.cycle.time_scale == speedup
    for speedup in (lo * 0.99, hi * 1.01):
        with pytest.raises(ConfigError):
            config_from_mapping(tomllib.loads(_service_toml(FlyOptions(speedup=speedup), 1, tmp_path / "t")))


def test_help_gives_the_speedup_range(capsys: pytest.CaptureFixture[str]) -> None:
    with pytest.raises(SystemExit) as exc:
        sim_main(["fly", "--help"])
    assert exc.value.code == 0
    assert "in [0.1, 60]" in " ".join(capsys.readouterr().out.split())


def test_a_service_config_error_shows_its_lines_not_only_the_count(tmp_path: Path) -> None:
    """The service prints ``config error: 4 config errors:`` and one ``  - ...`` line each: the flight's error
    carries the first ones (ERROR_DETAIL_LINES) and says how many more the log has."""
    errors = [f"  - cycle.key_{k} must be in [0, 1], got {k}" for k in range(7)]
    (tmp_path / "service.log").write_text(
        "\n".join(["apf-companion: config error: 7 config errors:", *errors, ""]), encoding="utf-8"
    )
    reason = error_reason(tmp_path, None, None, (2, -2))
    lines = reason.splitlines()
    assert lines[0] == "service: apf-companion: config error: 7 config errors:"
    assert lines[1:6] == [f"  {e.strip()}" for e in errors[:5]]
    assert lines[6] == "  ... and 2 more in service.log"
    # One error: its own line, as before.
    one = "apf-companion: config error: planner.name must be one of x"
    (tmp_path / "service.log").write_text(one + "\n")
    assert error_reason(tmp_path, None, None, (2, -2)) == f"service: {one}"


@pytest.mark.parametrize(
    ("words", "says"),
    [
        (["--start", "nan,3"], "argument --start: expected N,E (two finite numbers in metres), got 'nan,3'"),
        (["--goal=3,inf"], "argument --goal: expected N,E"),
        (["--start", "3"], "argument --start: expected N,E"),
        (["--noise", "-0.1"], "argument --noise: must be a number in [0, 5] m (the vehicle's SIM_POS_NOISE)"),
        (["--noise", "nan"], "argument --noise: must be a number in [0, 5]"),
        (["--trials", "0"], "argument --trials: must be an integer >= 1, got '0'"),
        (["--trials", "1.5"], "argument --trials: must be an integer >= 1"),
        (["--study-reps", "-1"], "argument --study-reps: must be an integer >= 0"),
        (["--seed", "-1"], "argument --seed: must be an integer >= 0"),
        (["--alt", "-5"], "argument --alt: must be a number in [1, 120] m (the service's takeoff height, goal"),
        (["--alt", "0.5"], "argument --alt: must be a number in [1, 120]"),  # below goal.min_altitude_m
        (["--alt", "121"], "argument --alt: must be a number in [1, 120]"),
        (["--rate", "0.5"], "argument --rate: must be a number in [1, 50] Hz (the service's cycle.rate_hz)"),
        (["--max-flight", "0"], "argument --max-flight: must be a number in (0, 86400] simulated s"),
        (["--max-flight", "inf"], "argument --max-flight: must be a number in (0, 86400]"),
        (["--obstacles", "extreme"], "argument --obstacles: must be an obstacle count in [0, 100000] or a density "),
        (["--obstacles", "low,-3"], "(low, mid, high), or a comma list of them, got 'low,-3'"),
        (["--vehicle-param", "FENCE_MARGIN=abc"], "argument --vehicle-param: must be NAME=VALUE with a finite number"),
        (["--vehicle-param", "FENCE_MARGIN"], "argument --vehicle-param: must be NAME=VALUE"),
    ],
)
def test_bad_flags_are_refused_at_parsing_naming_the_flag(
    words: list[str], says: str, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    err = _refused(["fly", *words, "--out", str(tmp_path / "out")], capsys)
    assert says in " ".join(err.split()), err
    assert not (tmp_path / "out").exists()


@pytest.mark.parametrize("words", [["--obstacles", "low,mid,high"], ["--obstacles", "0"], ["--noise", "0.1"]])
def test_good_flags_still_parse(words: list[str]) -> None:
    args = build_parser().parse_args(["fly", *words, "--trials", "2", "--seed", "0", "--alt", "7.5"])
    assert (args.trials, args.seed, args.alt) == (2, 0, 7.5)


@pytest.mark.parametrize("alt_m", [1.0, 120.0])
def test_the_lowest_and_highest_alt_are_goals_the_service_flies(alt_m: float, tmp_path: Path) -> None:
    """--alt is the takeoff height and the goal's: at its ends (1 m, 120 m) the service's config loads, and the goal
    is neither above goal.max_altitude_m nor below goal.min_altitude_m (which the service refuses at start)."""
    config = config_from_mapping(tomllib.loads(_service_toml(FlyOptions(alt_m=alt_m), 1, tmp_path / "t")))
    assert config.autopilot.takeoff_alt_m == alt_m and config.goal.down_m == -alt_m
    assert config.goal.min_altitude_m <= -config.goal.down_m <= config.goal.max_altitude_m


@pytest.mark.parametrize(
    ("param", "says"),
    [
        ("FENCE_MARGIN=11", "--vehicle-param for the ardupilot profile: FENCE_MARGIN 11 not in [0, 10]"),
        ("NO_SUCH=1", "--vehicle-param for the ardupilot profile: unknown parameter 'NO_SUCH'"),
    ],
)
def test_vehicle_parameters_are_checked_before_anything_starts(
    param: str, says: str, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """Names and ranges as the simulated autopilot checks them (per profile), before either process starts."""
    assert sim_main(["fly", "--vehicle-param", param, "--out", str(tmp_path / "out")]) == 2
    assert says in capsys.readouterr().err
    assert not (tmp_path / "out").exists()
    table = vehicle_params(FlyOptions(vehicle_params=("FENCE_MARGIN=0.5",), noise_m=0.1))
    assert (table["FENCE_MARGIN"], table["SIM_POS_NOISE"]) == (0.5, 0.1)


def test_the_vehicle_refuses_a_start_that_is_not_finite(capsys: pytest.CaptureFixture[str]) -> None:
    err = _refused(["vehicle", "--start", "nan,0", "--duration", "0.1"], capsys)
    assert "argument --start: expected N,E (two finite numbers in metres), got 'nan,0'" in err


def _options(words: list[str]) -> tuple[FlyOptions, World | None]:
    """The FlyOptions ``apf-sim fly WORDS`` flies (its route from the world file), and the world file's World."""
    args = build_parser().parse_args(["fly", *words])
    r = _route(args)
    opt = FlyOptions(
        world=args.world, start_ne_m=r.start_ne_m, goal_ne_m=r.goal_ne_m, area_ne_m=r.area_ne_m,
        keepouts_ne_m=r.keepouts_ne_m,
    )  # fmt: skip
    return opt, r.world


def test_a_start_outside_the_flying_area_is_refused_before_anything_starts(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """wall-gap's arena is its flying area: a start outside it flew 144 s and ended stuck; now it is refused the
    way the goal is, at once (exit 2), and --no-area still flies it."""
    out = tmp_path / "out"
    assert sim_main(["fly", "--world", "wall-gap", "--start", "-12,0", "--out", str(out)]) == 2
    err = capsys.readouterr().err
    assert "apf-sim fly: --start (north -12 m, east 0 m) lies outside the flying area of world wall-gap" in err
    assert "area_ne_m = [-3.0, -12.0, 23.0, 12.0]" in err and "--no-area" in err
    assert not out.exists()
    assert sim_main(["fly", "--world", "wall-gap", "--goal", "40,0", "--out", str(out)]) == 2
    assert "--goal (north 40 m, east 0 m) lies outside the flying area" in capsys.readouterr().err
    assert route_problem(*_options(["--world", "wall-gap", "--start", "-12,0", "--no-area"]), 0.25) is None


def test_a_start_or_goal_in_a_keep_out_zone_is_refused() -> None:
    zone = ((7.0, -3.0), (13.0, -3.0), (13.0, 3.0), (7.0, 3.0))
    opt = FlyOptions(world="w", start_ne_m=(8.0, 0.0), goal_ne_m=(20.0, 0.0), keepouts_ne_m=(zone,))
    assert route_problem(opt, None, 0.25) == (
        "--start (north 8 m, east 0 m) lies in a keep-out zone of world w: pick a point outside it, or --no-area"
    )
    opt = FlyOptions(world="w", start_ne_m=(0.0, 0.0), goal_ne_m=(10.0, 0.0), keepouts_ne_m=(zone,))
    assert "--goal (north 10 m, east 0 m) lies in a keep-out zone" in str(route_problem(opt, None, 0.25))


def test_a_start_within_the_collision_radius_of_an_obstacle_is_refused(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """--start 10,0 is inside wall-gap's crossing wall (it reported ``outcome: collision`` at t=0); 9.8,0 is 0.1 m
    from it, within SIM_VEH_RADIUS 0.25 m; 9.5,0 is clear, until --vehicle-param SIM_VEH_RADIUS=0.5."""
    out = tmp_path / "out"
    assert sim_main(["fly", "--world", "wall-gap", "--start", "10,0", "--out", str(out)]) == 2
    err = capsys.readouterr().err
    assert (
        "apf-sim fly: --start (north 10 m, east 0 m) lies inside wall 0 of world wall-gap, within the vehicle's " in err
    )
    assert "collision radius SIM_VEH_RADIUS = 0.25 m: the flight would end in a collision at once" in err
    assert not out.exists()
    opt, world = _options(["--world", "wall-gap", "--start", "9.8,0"])
    assert "is 0.10 m from wall 0 of world wall-gap" in str(route_problem(opt, world, 0.25))
    opt, world = _options(["--world", "wall-gap", "--start", "9.5,0"])
    assert route_problem(opt, world, 0.25) is None
    assert sim_main(["fly", "--world", "wall-gap", "--start", "9.5,0", "--vehicle-param", "SIM_VEH_RADIUS=0.5",
                     "--out", str(out)]) == 2  # fmt: skip
    assert "is 0.40 m from wall 0 of world wall-gap, within the vehicle's collision radius SIM_VEH_RADIUS = 0.5 m" in (
        capsys.readouterr().err
    )


@pytest.mark.parametrize("name", sorted(p.stem for p in EXAMPLES_DIR.glob("*.toml")))
def test_every_bundled_world_s_own_start_and_goal_fly(name: str) -> None:
    assert route_problem(*_options(["--world", name]), 0.25) is None


def test_the_paper_field_s_start_is_clear() -> None:
    for seed in range(5):
        opt = FlyOptions(seed=seed, obstacles="high")
        assert route_problem(opt, paper_world(opt), 0.25) is None


def test_a_collision_prints_the_simulator_s_crash_message(tmp_path: Path) -> None:
    """A flight that ends in a collision (here: set up in-process past fly's own checks, started inside a wall)
    keeps the simulator's crash record in its result and prints its message in the summary."""
    opt, _ = _options(["--world", "wall-gap", "--start", "10,0"])
    opt = dataclasses.replace(opt, out=tmp_path / "out", plot=False, progress=False)
    rec = asyncio.run(fly(opt))
    assert rec["outcome"] == "collision", rec
    assert rec["crash"]["reason"].startswith("Crash: hit wall 0")
    summary = flight_summary(rec, opt.out)
    lines = summary.splitlines()
    assert lines[0] == "outcome: collision"
    assert lines[1].startswith("crash: Crash: hit wall 0 clearance -0.10 m at t=0.0 s, north 10.00 m, east 0.00 m")


def test_the_output_line_lists_only_this_flight_s_files(tmp_path: Path) -> None:
    """A previous flight in the same --out left trajectory.png, companion.tlog and an .mcap; this flight fails at
    the service's config (a planner typo) and writes neither: the output line must not list them. The user's own
    files and the signing timestamp in --out stay."""
    out = tmp_path / "out"
    out.mkdir()
    for stale in ("trajectory.png", "companion.tlog", "apf-20250101T000000Z.mcap", "sim_result.json"):
        (out / stale).write_bytes(b"from the last flight")
    (out / "notes.txt").write_text("mine")
    (out / "signing.timestamp").write_text("123")
    opt = FlyOptions(planner="cr-bapff", out=out, plot=False, progress=False)
    rec = asyncio.run(fly(opt))  # the planner typo gets past the CLI (fly called directly): the service refuses it
    assert rec["outcome"] == "error" and rec["mcap"] is None, rec
    assert rec["error"].startswith("service: apf-companion: config error: planner.name must be one of"), rec
    listed = flight_summary(rec, out).split("output:")[1]
    assert "trajectory.png" not in listed and "companion.tlog" not in listed and ".mcap" not in listed
    assert "result.json" in listed and "service.log" in listed
    assert not (out / "trajectory.png").exists() and not (out / "companion.tlog").exists()
    assert (out / "notes.txt").read_text() == "mine" and (out / "signing.timestamp").read_text() == "123"


def test_a_flight_that_never_took_off_prints_no_clearance(tmp_path: Path) -> None:
    """The service refused its config before the takeoff: the vehicle stood at its start, and the clearance of
    that spot (2.9 m in wall-gap, when the vehicle sampled it before it was stopped) is no flight's clearance. A
    flight that took off keeps its number."""
    out = tmp_path / "out"
    opt = FlyOptions(planner="cr-bapff", world="wall-gap", start_ne_m=(0.0, 0.0), out=out, plot=False, progress=False)
    rec = asyncio.run(fly(opt))
    assert rec["outcome"] == "error" and rec["airborne"] is False, rec
    assert "min clearance: n/a (the vehicle never took off)\n" in flight_summary(rec, out)
    # The vehicle may or may not have sampled its clearance before it was stopped: either way no number is shown.
    standing = rec | {"min_clearance_m": 2.9}
    assert "min clearance: n/a (the vehicle never took off)\n" in flight_summary(standing, out)
    flown = rec | {"airborne": True, "min_clearance_m": 0.5}
    assert "min clearance: 0.500 m\n" in flight_summary(flown, out)
    assert airborne({"trajectory_ned_m": [[0.0, 0.0, 0.0], [0.0, 0.0, -0.05]]}) is False
    assert airborne({"trajectory_ned_m": [[0.0, 0.0, 0.0], [0.1, 0.0, -2.0]]}) is True
    # The sweep's lowest clearance leaves out flights that never took off, not collisions on the ground.
    ground = {"outcome": "error", "min_clearance_m": 0.1, "airborne": False}
    crash = {"outcome": "collision", "min_clearance_m": -0.1, "airborne": False}
    assert _fault_summary([ground, flown])["min_clearance_m"] == 0.5
    assert _fault_summary([ground, crash, flown])["min_clearance_m"] == -0.1


def test_a_start_on_a_paper_field_obstacle_names_the_field() -> None:
    opt = FlyOptions(seed=0, obstacles="mid")
    world = paper_world(opt)
    north, east = (float(v) for v in world.circles_ne_m[3])
    on_it = dataclasses.replace(opt, start_ne_m=(north, east))  # on a point obstacle: 0 m from it
    assert f"is 0.00 m from cylinder 3 of world {world.name}, within" in str(route_problem(on_it, world, 0.25))
