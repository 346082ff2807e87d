"""apf-sim fly's command line: its options, each checked at parsing (exit 2 naming the flag and its range), the
route check against the world before anything starts, one flight's summary, and the dispatch to one flight
(``sim.fly``) or a batch of them (``sim.flysweep``)."""

from __future__ import annotations

import argparse
import asyncio
import dataclasses
import math
import re
import sys
from pathlib import Path
from typing import TYPE_CHECKING, Any

from apf_companion.autopilot import Autopilot
from apf_companion.config import (
    HEARTBEAT_TIMEOUT_RANGE_S,
    MAX_FLIGHT_RANGE_S,
    RATE_RANGE_HZ,
    TAKEOFF_ALT_RANGE_M,
    GoalConfig,
)
from apf_companion.errors import ApfCompanionError, ConfigError
from apf_companion.links import load_signing_key
from apf_companion.planning import (
    ALL_PLANNER_NAMES,
    DEFAULT_PLANNER,
    FlyingArea,
    KeepOuts,
    area_text,
    zone_conflict,
)
from sim.argtypes import int_from, number_in, param_assignment
from sim.fly import (
    HEARTBEAT_FLOOR_S,
    PAPER_GOAL,
    PAPER_START,
    SPEEDUP_RANGE,
    FlyOptions,
    clearance_text,
    fly,
    output_files,
    paper_world,
)
from sim.flysweep import flight_densities, fly_trials
from sim.linkfaults import LinkFaults
from sim.vehicle.params import ParamSpec, ParamTable, param_specs
from sim.world import bundled_world_names
from sim.world.field import DENSITIES, MAX_OBSTACLES

if TYPE_CHECKING:
    from sim.world import World

__all__ = ["flight_summary", "register", "route_problem", "vehicle_params"]


def _speedup(text: str) -> float:
    """``--speedup``: a number in SPEEDUP_RANGE (argparse names the flag in its error)."""
    lo, hi = SPEEDUP_RANGE
    try:
        value = float(text)
    except ValueError:
        value = math.nan
    if not lo <= value <= hi:  # NaN too
        msg = (
            f"must be a number in [{lo:g}, {hi:g}], got {text!r} (the service's cycle.time_scale is the speed-up, "
            f"its link.heartbeat_timeout_s max({HEARTBEAT_FLOOR_S:g}, speed-up) s must stay within "
            f"{HEARTBEAT_TIMEOUT_RANGE_S[1]:g} s)"
        )
        raise argparse.ArgumentTypeError(msg)
    return value


def _pair(text: str) -> tuple[float, float]:
    """``--start`` / ``--goal``: two finite numbers N,E [m]."""
    parts = text.split(",")
    try:
        north, east = (float(part) for part in parts)
    except ValueError:
        north = east = math.nan
    if not (math.isfinite(north) and math.isfinite(east)):
        msg = f"expected N,E (two finite numbers in metres), got {text!r}"
        raise argparse.ArgumentTypeError(msg)
    return north, east


def _obstacles(text: str) -> str:
    """``--obstacles``: a count in [0, MAX_OBSTACLES] or a density name, or a comma list of them (the trials')."""
    items = [item.strip() for item in text.split(",")]
    for item in items:
        if item in DENSITIES or (item.isdigit() and int(item) <= MAX_OBSTACLES):
            continue
        msg = (
            f"must be an obstacle count in [0, {MAX_OBSTACLES}] or a density ({', '.join(DENSITIES)}), or a "
            f"comma list of them, got {text!r}"
        )
        raise argparse.ArgumentTypeError(msg)
    return ",".join(items)


def _noise_spec() -> ParamSpec:
    """The vehicle's actuation noise parameter (``--noise``), the same in both profiles."""
    return next(spec for spec in param_specs(Autopilot.ARDUPILOT) if spec.name == "SIM_POS_NOISE")


def vehicle_params(opt: FlyOptions) -> ParamTable:
    """The simulated autopilot's parameters for ``opt`` (``--vehicle-param`` and ``--noise``), checked as the
    vehicle would check them. Raises ConfigError naming an unknown parameter or a value outside its range."""
    overrides = {name: float(value) for name, _, value in (item.partition("=") for item in opt.vehicle_params)}
    if opt.noise_m > 0:
        overrides["SIM_POS_NOISE"] = opt.noise_m
    try:
        return ParamTable(Autopilot(opt.profile), overrides)
    except ConfigError as err:
        msg = f"--vehicle-param for the {opt.profile} profile: {err}"
        raise ConfigError(msg) from err


def register(subparsers: argparse._SubParsersAction) -> None:  # type: ignore[type-arg]
    """Add ``apf-sim fly``."""
    p = subparsers.add_parser(
        "fly",
        help="fly the companion service against the simulator (the paper's scenario by default)",
        description=__doc__,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    _add_scenario_options(p)
    _add_flight_options(p)
    _add_sweep_options(p)
    p.set_defaults(func=_cmd_fly)


def _add_scenario_options(p: argparse.ArgumentParser) -> None:
    """What flies where: planner, autopilot profile, dynamics, the world and its start and goal."""
    p.add_argument(
        "--planner",
        default=DEFAULT_PLANNER,
        choices=ALL_PLANNER_NAMES,
        metavar="PLANNER",
        help=f"default {DEFAULT_PLANNER}; one of {', '.join(ALL_PLANNER_NAMES)}",
    )
    p.add_argument("--profile", choices=("ardupilot", "px4"), default="ardupilot")
    p.add_argument(
        "--dynamics",
        choices=("auto", "simple", "arducopter"),
        default="auto",
        help="the simulated vehicle's response: auto (default: arducopter, ArduCopter's controller shape, for the "
        "ardupilot profile; simple for px4), simple, or arducopter",
    )
    p.add_argument(
        "--seed", type=int_from(0), default=0, help="seed of the random field and the planner, >= 0 (default 0)"
    )
    p.add_argument("--preset", choices=("reference", "paper"), default="reference", help="random-field preset")
    p.add_argument(
        "--obstacles",
        type=_obstacles,
        default="mid",
        help=f"obstacle count N in [0, {MAX_OBSTACLES}], or density {'|'.join(DENSITIES)} (default mid); a list "
        "(low,mid,high) cycles over --trials",
    )
    p.add_argument("--world", help=f"world TOML file or bundled example ({', '.join(bundled_world_names())})")
    p.add_argument("--start", type=_pair, metavar="N,E", help="start (default: the world file's, else the paper's 3,3)")
    p.add_argument("--goal", type=_pair, metavar="N,E", help="goal (default: the world file's, else 22,22)")
    p.add_argument(
        "--no-area",
        action="store_true",
        help="fly without the world file's flying area (area_ne_m): bapf-nav's grid then moves with the vehicle",
    )
    p.add_argument(
        "--fence",
        action="store_true",
        help="the vehicle serves the world file's flying area as its fence, and the service reads it from there "
        "(planner.fence_area) instead of from its config, with ArduCopter's fence parameters (FENCE_MARGIN 2 m: "
        "see --vehicle-param)",
    )
    p.add_argument(
        "--vehicle-param",
        action="append",
        type=param_assignment,
        default=[],
        metavar="NAME=VALUE",
        help="a parameter of the simulated autopilot (apf-sim vehicle --param), e.g. FENCE_MARGIN=0.5 (ArduPilot's "
        "default is 2 m, which closes a gap within 2 m of a fence drawn on the walls); repeatable",
    )
    # "--start -12.0,0.0": argparse takes a word starting with "-" for an option unless it looks like a negative
    # number, and its pattern (argparse._ActionsContainer) has no comma; widen it to N,E pairs for this parser.
    p._negative_number_matcher = re.compile(r"^-\d+$|^-\d*\.\d+$|^-\d*\.?\d*,-?\d*\.?\d*$")


def _add_flight_options(p: argparse.ArgumentParser) -> None:
    """How one flight runs and what it writes: height, speed-up, rates, limits, noise, output."""
    # The service takes off to --alt (autopilot.takeoff_alt_m) and refuses a goal higher than goal.max_altitude_m
    # or lower than goal.min_altitude_m.
    goal = GoalConfig()
    alt_lo, alt_hi = max(TAKEOFF_ALT_RANGE_M[0], goal.min_altitude_m), min(TAKEOFF_ALT_RANGE_M[1], goal.max_altitude_m)
    p.add_argument(
        "--alt",
        type=number_in(alt_lo, alt_hi, what="m (the service's takeoff height, goal.min_altitude_m / max_altitude_m)"),
        default=5.0,
        help=f"flight height above home, in [{alt_lo:g}, {alt_hi:g}] m (default 5)",
    )
    lo, hi = SPEEDUP_RANGE
    p.add_argument(
        "--speedup",
        type=_speedup,
        default=5.0,
        help=f"simulated s per wall s, in [{lo:g}, {hi:g}] (the service's cycle.time_scale and "
        "link.heartbeat_timeout_s follow it and have limits; default 5)",
    )
    rate_lo, rate_hi = RATE_RANGE_HZ
    p.add_argument(
        "--rate",
        type=number_in(rate_lo, rate_hi, what="Hz (the service's cycle.rate_hz)"),
        default=10.0,
        help=f"service cycle rate in simulated Hz, in [{rate_lo:g}, {rate_hi:g}] (default 10)",
    )
    flight_hi = MAX_FLIGHT_RANGE_S[1]
    p.add_argument(
        "--max-flight",
        type=number_in(0.0, flight_hi, lo_open=True, what="simulated s (the service's max_flight_s)"),
        default=300.0,
        help=f"give up after this many simulated s, in (0, {flight_hi:g}] (default 300)",
    )
    noise = _noise_spec()
    p.add_argument(
        "--noise",
        type=number_in(noise.lo, noise.hi, what=f"m (the vehicle's {noise.name})"),
        default=0.0,
        help=f"actuation noise SD [m], in [{noise.lo:g}, {noise.hi:g}] (the paper's is 0.1; {noise.name})",
    )
    p.add_argument("--out", type=Path, default=Path("fly-out"), help="output directory (default ./fly-out)")
    p.add_argument("--json", type=Path, help="write the result record here too")
    p.add_argument("--no-plot", action="store_true", help="skip the trajectory PNG")
    p.add_argument("--quiet", action="store_true", help="no progress line")
    p.add_argument(
        "--signing-key",
        type=Path,
        metavar="FILE",
        help="MAVLink 2 signing key file (mode 600): the simulator and the service sign every frame and drop "
        "unsigned ones (docs/hardening.md#mavlink-2-signing)",
    )


def _add_sweep_options(p: argparse.ArgumentParser) -> None:
    """Several flights: --trials, the study on the same worlds, seeded link faults."""
    p.add_argument(
        "--trials",
        type=int_from(1),
        default=1,
        help="fly this many worlds (seeds SEED, SEED+1, ...) one after another and print the success rate (>= 1)",
    )
    p.add_argument(
        "--study-reps",
        type=int_from(0),
        default=100,
        metavar="R",
        help="with --trials on a paper field: also run the study's engine R times on each flown field "
        "(its noise and rules) and print its success rate on the same worlds (default 100; 0 = off)",
    )
    p.add_argument(
        "--link-faults",
        type=_link_faults,
        metavar="SPEC",
        help="seeded faults between vehicle and service, e.g. loss=0.3,jitter=0.1,dup=0.05,reorder=0.05,"
        "blackout=2@40%%  (times in simulated s; see sim/linkfaults.py)",
    )


def _link_faults(text: str) -> LinkFaults:
    try:
        return LinkFaults.parse(text)
    except ConfigError as err:
        raise argparse.ArgumentTypeError(str(err)) from err


@dataclasses.dataclass(frozen=True, slots=True)
class _Route:
    """Where ``apf-sim fly`` flies: start, goal, and the world file's zones."""

    start_ne_m: tuple[float, float]
    goal_ne_m: tuple[float, float]
    area_ne_m: FlyingArea | None
    keepouts_ne_m: KeepOuts
    world: World | None = None  # the world file's obstacles (None: a paper field)


def _route(args: argparse.Namespace) -> _Route:
    """--start/--goal, else the world file's suggested start/goal, else the paper's (3, 3) -> (22, 22); and the
    world file's flying area and keep-out zones unless --no-area (the file read once)."""
    start, goal = PAPER_START, PAPER_GOAL
    area: FlyingArea | None = None
    keepouts: KeepOuts = ()
    world: World | None = None
    if args.world is not None:
        from sim.world import load_world

        world = load_world(args.world)
        start = world.start_ne_m or start
        goal = world.goal_ne_m or goal
        if not args.no_area:
            area, keepouts = world.area_ne_m, world.keepouts_ne_m
    return _Route(args.start or start, args.goal or goal, area, keepouts, world)


def route_problem(opt: FlyOptions, world: World | None, radius_m: float) -> str | None:
    """Why ``apf-sim fly`` refuses ``opt``'s start or goal before it starts anything, or None.

    A start or goal outside the world's flying area or in one of its keep-out zones (the service refuses such a
    goal, bapf-nav gives up at once; ``--no-area`` flies without them), or a start whose clearance to an obstacle
    of ``world`` (``World.nearest_obstacle``, the distance the simulator judges collisions by) is less than the
    vehicle's collision radius ``radius_m`` (SIM_VEH_RADIUS): the simulator would end the flight in a collision at
    once."""
    where = f"world {opt.world}" if opt.world is not None else "the world"
    points = (("--start", opt.start_ne_m), ("--goal", opt.goal_ne_m))
    conflict = zone_conflict(opt.area_ne_m, opt.keepouts_ne_m, *zip(*(ne for _, ne in points), strict=True))
    if conflict is not None:
        flag, (n, e) = points[conflict.index]
        point = f"{flag} (north {n:g} m, east {e:g} m)"
        if conflict.keepout is None:
            assert opt.area_ne_m is not None  # only an area leaves a point outside
            return (
                f"{point} lies outside the flying area of {where}, area_ne_m = {area_text(opt.area_ne_m)}: "
                "pick a point inside it, or fly without the area (--no-area)"
            )
        return f"{point} lies in a keep-out zone of {where}: pick a point outside it, or --no-area"
    if world is not None:
        i, clearance = world.nearest_obstacle(opt.start_ne_m)
        if clearance < radius_m:
            kind = "cylinder" if i < world.n_circles else "wall"
            north, east = opt.start_ne_m
            gap = f"lies inside {kind} {i}" if clearance < 0 else f"is {clearance:.2f} m from {kind} {i}"
            return (
                f"--start (north {north:g} m, east {east:g} m) {gap} of world {world.name}, within the vehicle's "
                f"collision radius SIM_VEH_RADIUS = {radius_m:g} m: the flight would end in a collision at once"
            )
    return None


def _cmd_fly(args: argparse.Namespace) -> int:
    try:
        route = _route(args)
        if args.signing_key is not None:
            load_signing_key(args.signing_key)  # a key file others can read: refused before anything starts
    except ApfCompanionError as err:
        print(f"apf-sim fly: {err}", file=sys.stderr)
        return 2
    opt = FlyOptions(
        planner=args.planner,
        profile=args.profile,
        dynamics=args.dynamics,
        seed=args.seed,
        preset=args.preset,
        obstacles=args.obstacles,
        world=args.world,
        start_ne_m=route.start_ne_m,
        goal_ne_m=route.goal_ne_m,
        area_ne_m=route.area_ne_m,
        keepouts_ne_m=route.keepouts_ne_m,
        fence=args.fence,
        vehicle_params=tuple(args.vehicle_param),
        alt_m=args.alt,
        speedup=args.speedup,
        rate_hz=args.rate,
        max_flight_s=args.max_flight,
        noise_m=args.noise,
        out=args.out,
        json_path=args.json,
        plot=not args.no_plot,
        progress=not args.quiet,
        link_faults=args.link_faults,
        signing_key=args.signing_key,
    )
    try:
        radius_m = vehicle_params(opt)["SIM_VEH_RADIUS"]
    except ConfigError as err:
        print(f"apf-sim fly: {err}", file=sys.stderr)
        return 2
    if args.trials <= 1:
        opt = dataclasses.replace(opt, obstacles=flight_densities(opt)[0])
    # A world file's obstacles, or the one paper field a single flight flies (the trials' are random draws).
    world = route.world if opt.world is not None else (paper_world(opt) if args.trials <= 1 else None)
    problem = route_problem(opt, world, radius_m)
    if problem is not None:
        print(f"apf-sim fly: {problem}", file=sys.stderr)
        return 2
    if args.trials > 1:
        return fly_trials(opt, args.trials, study_reps=args.study_reps)
    try:
        rec = asyncio.run(fly(opt))
    except ApfCompanionError as err:
        print(f"apf-sim fly: {err}", file=sys.stderr)
        return 1
    if rec["outcome"] == "error":
        print(f"apf-sim fly: error: {rec.get('error', 'unknown')}", file=sys.stderr)
    print(flight_summary(rec, opt.out))
    return 0 if rec["outcome"] == "arrived" else 3


def flight_summary(rec: dict[str, Any], out: Path) -> str:
    """What ``apf-sim fly`` prints after one flight: outcome (and the simulator's crash message after a
    collision), path, clearance, times and the files the flight wrote to ``out``."""
    crash = rec.get("crash")
    mcap = rec.get("mcap")
    return (
        f"outcome: {rec['outcome']}\n"
        + (f"crash: {_crash_text(crash)}\n" if rec["outcome"] == "collision" and isinstance(crash, dict) else "")
        + f"planner: {rec['planner']} ({rec['profile']}), world: {rec['world']}, seed {rec['seed']}\n"
        f"path length: {rec['path_length_m']:.2f} m\n"
        f"min clearance: {clearance_text(rec)}\n"
        f"flight time: {rec['flight_time_s']:.1f} s simulated ({rec['sim_time_s']:.1f} s since boot), "
        f"{rec['steps']} planner steps, {rec['wall_time_s']:.1f} s wall\n"
        f"output: {out}/ ({', '.join(output_files(out)) or 'nothing written'})"
        + (f"; {Path(mcap).name}: apf-sim mcap-plot, or open it in Foxglove" if mcap else "")
    )


def _crash_text(crash: dict[str, Any]) -> str:
    """The simulator's crash record (its ``crashed_at``) for the summary: reason, time and place."""
    text = str(crash.get("reason", "crashed"))
    t_s, pos = crash.get("t_s"), crash.get("pos_ned_m")
    if isinstance(t_s, int | float):
        text += f" at t={t_s:.1f} s"
    if isinstance(pos, list) and len(pos) >= 2:
        text += f", north {pos[0]:.2f} m, east {pos[1]:.2f} m"
    return text
