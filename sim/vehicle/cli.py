"""``apf-sim vehicle`` (the simulated autopilot + vehicle + world + sensor) and ``apf-sim sensor`` (world and
sensor following an external autopilot)."""

from __future__ import annotations

import argparse
import asyncio
import contextlib
import logging
import math
import signal
import sys
from pathlib import Path

import numpy as np

from apf_companion.cli import add_log_level_option
from apf_companion.errors import ApfCompanionError, ConfigError
from apf_companion.links import load_signing_key
from apf_companion.planning import FlyingArea, KeepOuts
from sim.argtypes import int_from, number_in, param_assignment
from sim.vehicle.config import HomeConfig, SpawnConfig
from sim.vehicle.sensor import SENSOR_MESSAGES, RangeSensorConfig
from sim.vehicle.sensor_only import SENSOR_COMPID, SensorOnlyConfig, SensorSimulator
from sim.vehicle.simulator import SimConfig, Simulator, ZenohOutput
from sim.world import World, bundled_world_names, load_world, paper_field, parse_field_spec

log = logging.getLogger(__name__)

FIRST_REPORT_S = 2.0  # apf-sim sensor: say what it is waiting for after this long without scans [s, wall]
WAIT_REPORT_S = 5.0  # ... and again this often [s, wall]

__all__ = ["register"]


def register(subparsers: argparse._SubParsersAction) -> None:  # type: ignore[type-arg]
    """Add ``vehicle`` and ``sensor`` to ``apf-sim``."""
    _register_vehicle(subparsers)
    _register_sensor(subparsers)


def _startup_args(v: argparse.ArgumentParser) -> None:
    """How the ArduPilot profile boots (sim/vehicle/startup.py, telemetry.py)."""
    v.add_argument(
        "--fast-start",
        action="store_true",
        help="EKF origin at boot (ArduPilot otherwise has no position for SIM_EKF_ORIGIN_S = 20 s, as on SITL)",
    )
    v.add_argument(
        "--fence",
        action="store_true",
        help="serve the world file's flying area (area_ne_m) as the autopilot's fence, one inclusion polygon, "
        "and its keep-out zones as exclusion polygons",
    )
    v.add_argument(
        "--unasked-streams",
        action="store_true",
        help="stream telemetry without being asked (ArduPilot otherwise sends HEARTBEAT only until asked)",
    )


def _register_vehicle(subparsers: argparse._SubParsersAction) -> None:  # type: ignore[type-arg]
    v = subparsers.add_parser(
        "vehicle",
        help="simulated ArduCopter/PX4 vehicle with a world and a range sensor, over MAVLink",
        description="A pure-Python MAVLink vehicle simulator (sysid 1, compid 1). Connect a ground station or "
        "a companion to any --link. Writes --result-json on exit (also SIGINT/SIGTERM) and on a crash.",
    )
    v.add_argument("--profile", choices=("ardupilot", "px4"), default="ardupilot")
    v.add_argument(
        "--dynamics",
        choices=("auto", "simple", "arducopter"),
        default="auto",
        help="auto (default: arducopter for the ardupilot profile, simple for px4), simple, or arducopter: "
        "ArduCopter's jerk-limited position controller shape, lag, overshoot and spool-up (docs/simulator.md)",
    )
    _world_args(v)
    v.add_argument(
        "--link",
        action="append",
        metavar="ENDPOINT",
        help="MAVLink endpoint, repeatable (udpout:HOST:PORT, udpin:, tcpin:, tcp:); default udpout:127.0.0.1:14550",
    )
    v.add_argument("--speedup", type=float, default=1.0, help="simulated s per wall s (inf = max); default 1")
    v.add_argument("--seed", type=int, default=0, help="seed for noise (and for --paper-field unless --field-seed)")
    v.add_argument("--tlog", type=Path, help="record every frame in and out (.tlog)")
    v.add_argument("--result-json", type=Path, help="write the flight result here on exit and on a crash")
    v.add_argument("--duration", type=float, help="stop after this many simulated seconds (within one physics step)")
    v.add_argument("--exit-on-crash", action="store_true", help="stop when the vehicle crashes")
    v.add_argument(
        "--param", action="append", type=param_assignment, default=[], metavar="NAME=VALUE", help="parameter override"
    )
    v.add_argument(
        "--actuation-noise",
        type=float,
        metavar="SD",
        help="horizontal actuation noise SD per 0.1 s [m] (SIM_POS_NOISE; the paper's is 0.1)",
    )
    v.add_argument("--airborne", action="store_true", help="start flying (armed, hovering) instead of landed")
    v.add_argument("--alt", type=float, default=5.0, help="hover height for --airborne [m]")
    v.add_argument("--start", type=_pair, metavar="N,E", help="start north,east [m] (default: world start)")
    v.add_argument("--yaw", type=float, default=0.0, help="start heading [deg]")
    v.add_argument("--mode", help="start mode (GUIDED, LOITER, OFFBOARD, AUTO.LOITER, ...)")
    v.add_argument("--home", type=_triple, metavar="LAT,LON,ALT", help="home lat, lon [deg], alt AMSL [m]")
    v.add_argument("--physics-rate", type=float, default=100.0, help="physics steps per simulated s")
    v.add_argument(
        "--signing-key",
        type=Path,
        metavar="FILE",
        help="MAVLink 2 signing key (32 raw bytes or 64 hex digits, mode 600): sign every frame, drop frames not "
        "signed with it except RADIO_STATUS and a few others, as ArduPilot / PX4 do",
    )
    _startup_args(v)
    _sensor_args(v)
    v.set_defaults(func=run_vehicle)


def _register_sensor(subparsers: argparse._SubParsersAction) -> None:  # type: ignore[type-arg]
    s = subparsers.add_parser(
        "sensor",
        help="world + range sensor following an external autopilot's position",
        description="Follows an external autopilot (e.g. SITL) over MAVLink and publishes simulated ranges from "
        "a world to a companion over MAVLink (--output) and/or zenoh.",
    )
    s.add_argument("--autopilot", required=True, metavar="ENDPOINT", help="the autopilot (e.g. tcp:127.0.0.1:5760)")
    _world_args(s)
    s.add_argument("--output", action="append", default=[], metavar="ENDPOINT", help="MAVLink output, repeatable")
    s.add_argument("--to-autopilot", action="store_true", help="also send the sensor messages to the autopilot")
    s.add_argument("--sysid", type=int_from(1, 255), default=1, help="our MAVLink system id (default 1: the vehicle's)")
    s.add_argument(
        "--compid",
        type=int_from(1, 255),
        default=SENSOR_COMPID,
        help=f"our MAVLink component id (default {SENSOR_COMPID}, MAV_COMP_ID_PERIPHERAL; never 1: ArduPilot drops "
        'packets with its own ids). The service must list it: [sensors] mavlink_sources = ["1/158"]',
    )
    s.add_argument("--rate", type=number_in(0.1, 100.0, what="Hz"), default=10.0, help="sensor rate [Hz], [0.1, 100]")
    s.add_argument("--range", type=number_in(0.0, math.inf, lo_open=True, what="m"), default=8.0, help="max range [m]")
    s.add_argument("--min-range", type=number_in(0.0, math.inf, what="m"), default=0.2, help="min range [m], < --range")
    s.add_argument("--noise", type=number_in(0.0, math.inf, what="m"), default=0.0, help="range noise SD [m], >= 0")
    s.add_argument("--dropout", type=number_in(0.0, 1.0), default=0.0, help="probability a reading is lost, [0, 1]")
    s.add_argument("--seed", type=int, default=0)
    s.add_argument("--tlog", type=Path, help="record the autopilot link (.tlog)")
    s.add_argument("--result-json", type=Path, help="write clearance/collision result on exit")
    s.add_argument("--duration", type=float, help="stop after this many wall seconds")
    _sensor_args(s)
    s.set_defaults(func=run_sensor)


def _world_args(p: argparse.ArgumentParser) -> None:
    g = p.add_mutually_exclusive_group()
    g.add_argument("--world", help=f"world TOML file, or a bundled example: {', '.join(bundled_world_names())}")
    g.add_argument("--paper-field", metavar="PRESET:N", help="the paper's random field, e.g. reference:40, paper:mid")
    p.add_argument("--field-seed", type=int, help="seed of --paper-field (default: --seed)")
    p.add_argument("--field-radius", type=float, default=0.0, help="obstacle radius of --paper-field [m]")


def _sensor_args(p: argparse.ArgumentParser) -> None:
    p.add_argument(
        "--sensor-msg",
        default="obstacle_distance",
        help=f"comma list of {','.join(sorted(SENSOR_MESSAGES))} (default obstacle_distance); 'none' = off",
    )
    p.add_argument("--sectors", type=int, default=72, help="OBSTACLE_DISTANCE sectors used (<= 72)")
    p.add_argument("--increment", type=float, default=5.0, help="sector width [deg]")
    p.add_argument("--angle-offset", type=float, default=0.0, help="body bearing of sector 0 [deg]")
    p.add_argument("--zenoh-connect", action="append", default=[], metavar="tcp/HOST:PORT")
    p.add_argument("--zenoh-listen", action="append", default=[], metavar="tcp/HOST:PORT")
    p.add_argument("--zenoh-mode", default="peer", choices=("peer", "client", "router"))
    p.add_argument("--zenoh-key", default="apf/sensors/range0/ranges")
    p.add_argument("--zenoh-encoding", default="json", choices=("json", "cdr"))


def _pair(text: str) -> tuple[float, float]:
    """N,E: two finite numbers (a NaN start would fly nowhere and report a NaN path)."""
    try:
        a, b = (float(x) for x in text.split(","))
    except ValueError:
        a = b = math.nan
    if not (math.isfinite(a) and math.isfinite(b)):
        msg = f"expected N,E (two finite numbers in metres), got {text!r}"
        raise argparse.ArgumentTypeError(msg)
    return a, b


def _triple(text: str) -> tuple[float, float, float]:
    a, b, c = (float(x) for x in text.split(","))
    return a, b, c


def _world(args: argparse.Namespace) -> World:
    if args.world:
        return load_world(args.world)
    if args.paper_field:
        preset, count = parse_field_spec(args.paper_field)
        seed = args.field_seed if args.field_seed is not None else args.seed
        return paper_field(preset, count, np.random.default_rng(seed), radius_m=args.field_radius)
    return World.empty()


def _fence(args: argparse.Namespace, world: World) -> tuple[FlyingArea | None, KeepOuts]:
    """--fence: the world's flying area and keep-out zones (an error when it has neither: a fence was asked for)."""
    if not args.fence:
        return None, ()
    if world.area_ne_m is None and not world.keepouts_ne_m:
        msg = "--fence: the world has no flying area (area_ne_m) and no keep-out zone to serve as the fence"
        raise ConfigError(msg)
    return world.area_ne_m, world.keepouts_ne_m


def _sensor_cfg(args: argparse.Namespace, links: tuple[int, ...] | None = None) -> RangeSensorConfig:
    kinds = frozenset() if args.sensor_msg == "none" else frozenset(k.strip() for k in args.sensor_msg.split(","))
    return RangeSensorConfig(
        sectors=args.sectors,
        increment_deg=args.increment,
        angle_offset_deg=args.angle_offset,
        messages=kinds,
        links=links,
    )


def _zenoh(args: argparse.Namespace) -> ZenohOutput | None:
    if not args.zenoh_connect and not args.zenoh_listen:
        return None
    return ZenohOutput(
        connect=tuple(args.zenoh_connect),
        listen=tuple(args.zenoh_listen),
        mode=args.zenoh_mode,
        key=args.zenoh_key,
        encoding=args.zenoh_encoding,
    )


def _params(items: list[str]) -> dict[str, float]:
    """``--param`` overrides, each already checked by ``param_assignment``."""
    return {name: float(value) for name, _, value in (item.partition("=") for item in items)}


def _install_signals(stop: asyncio.Event) -> None:
    loop = asyncio.get_running_loop()
    for sig in (signal.SIGINT, signal.SIGTERM):
        with contextlib.suppress(NotImplementedError, RuntimeError):
            loop.add_signal_handler(sig, stop.set)


async def _vehicle_main(args: argparse.Namespace) -> int:
    home = HomeConfig()
    if args.home is not None:
        home = HomeConfig(lat_deg=args.home[0], lon_deg=args.home[1], alt_amsl_m=args.home[2])
    world = _world(args)
    fence, fence_keepouts = _fence(args, world)
    cfg = SimConfig(
        links=args.link or ["udpout:127.0.0.1:14550"],
        profile=args.profile,
        dynamics=args.dynamics,
        world=world,
        speedup=math.inf if math.isinf(args.speedup) else args.speedup,
        seed=args.seed,
        spawn=SpawnConfig(
            pos_ne_m=args.start, yaw_deg=args.yaw, airborne=args.airborne, alt_m=args.alt, mode=args.mode
        ),
        params=_params(args.param) | ({} if args.actuation_noise is None else {"SIM_POS_NOISE": args.actuation_noise}),
        sensor=_sensor_cfg(args),
        home=home,
        physics_rate_hz=args.physics_rate,
        tlog_path=args.tlog,
        zenoh=_zenoh(args),
        result_json=args.result_json,
        fast_start=args.fast_start,
        unasked_streams=True if args.unasked_streams else None,
        signing_key=None if args.signing_key is None else load_signing_key(args.signing_key),
        fence=fence,
        fence_keepouts=fence_keepouts,
        duration_s=args.duration,
    )
    stop = asyncio.Event()
    _install_signals(stop)
    sim = await Simulator.start(cfg)
    print(
        f"apf-sim vehicle ready: profile={args.profile} world={cfg.world.name} links={list(cfg.links)}"
        f"{' signed' if cfg.signing_key is not None else ''}",
        flush=True,
    )
    try:
        while not stop.is_set():
            with contextlib.suppress(TimeoutError):
                async with asyncio.timeout(0.05):
                    await stop.wait()
            if sim.finished.is_set():  # --duration: the simulator stopped its physics there
                break
            if args.exit_on_crash and sim.vehicle.crashed:
                break
            if sim.error is not None:
                log.error("simulator failed: %s", sim.error)
                return 1
    finally:
        await sim.aclose()
    res = sim.result()
    print(
        f"apf-sim vehicle done: sim_time_s={res['sim_time_s']:.1f} collided={res['collided']} "
        f"path_length_m={res['path_length_m']:.2f} min_clearance_m={res['min_clearance_m']}",
        flush=True,
    )
    return 0


async def _sensor_main(args: argparse.Namespace) -> int:
    if not (args.output or args.zenoh_connect or args.zenoh_listen or args.to_autopilot):
        # Said here with the flags, before SensorOnlyConfig says it with its field names.
        msg = (
            "needs an output: --output ENDPOINT (MAVLink, repeatable), --zenoh-connect/--zenoh-listen, "
            "or --to-autopilot"
        )
        raise ConfigError(msg)
    if not args.min_range < args.range:
        msg = f"--min-range ({args.min_range:g} m) must be less than --range ({args.range:g} m)"
        raise ConfigError(msg)
    cfg = SensorOnlyConfig(
        autopilot=args.autopilot,
        outputs=tuple(args.output),
        also_to_autopilot=args.to_autopilot,
        world=_world(args),
        sensor=_sensor_cfg(args),
        source_system=args.sysid,
        source_component=args.compid,
        rate_hz=args.rate,
        min_range_m=args.min_range,
        max_range_m=args.range,
        noise_sd_m=args.noise,
        dropout_prob=args.dropout,
        seed=args.seed,
        zenoh=_zenoh(args),
        tlog_path=args.tlog,
        result_json=args.result_json,
    )
    stop = asyncio.Event()
    _install_signals(stop)
    loop = asyncio.get_running_loop()
    t0 = loop.time()
    sim = await SensorSimulator.start(cfg)
    ids = f"{cfg.source_system}/{cfg.source_component}"
    print(f"apf-sim sensor started as {ids}: autopilot={args.autopilot} world={cfg.world.name}", flush=True)
    status = SensorStatusPrinter(sim, t0)
    try:
        while not stop.is_set():
            with contextlib.suppress(TimeoutError):
                async with asyncio.timeout(0.1):
                    await stop.wait()
            status.update(loop.time())
            if args.duration is not None and loop.time() - t0 >= args.duration:
                break
            if sim.error is not None:
                return 1
    finally:
        await sim.aclose()
    print(f"apf-sim sensor done: scans={sim.scans} min_clearance_m={sim.result()['min_clearance_m']}", flush=True)
    return 0


class SensorStatusPrinter:
    """Says "ready" once scans flow, and what is missing (after ``FIRST_REPORT_S``, then every ``WAIT_REPORT_S``)
    while they do not."""

    def __init__(self, sim: SensorSimulator, t0: float) -> None:
        self.sim = sim
        self.ready = False
        self.next_report = t0 + FIRST_REPORT_S

    def update(self, now: float) -> None:
        reason = self.sim.waiting_for(now)
        if reason is None and not self.ready:
            self.ready = True
            print(f"apf-sim sensor ready: scans flowing (autopilot system {self.sim.sysid})", flush=True)
        elif reason is not None and now >= self.next_report:
            self.ready = False
            self.next_report = now + WAIT_REPORT_S
            print(f"apf-sim sensor waiting: {reason}", flush=True)


def run_vehicle(args: argparse.Namespace) -> int:
    try:
        return asyncio.run(_vehicle_main(args))
    except ApfCompanionError as err:
        print(f"apf-sim vehicle: {err}", file=sys.stderr)
        return 2


def run_sensor(args: argparse.Namespace) -> int:
    try:
        return asyncio.run(_sensor_main(args))
    except ApfCompanionError as err:
        print(f"apf-sim sensor: {err}", file=sys.stderr)
        return 2


def main(argv: list[str] | None = None) -> int:
    """Standalone entry (``python -m sim.vehicle.cli vehicle ...``), the same as ``apf-sim vehicle|sensor``."""
    parser = argparse.ArgumentParser(prog="python -m sim.vehicle.cli")
    add_log_level_option(parser, default="WARNING")
    register(parser.add_subparsers(dest="command", required=True))
    args = parser.parse_args(argv)
    logging.basicConfig(level=args.log_level, format="%(asctime)s %(levelname)s %(name)s: %(message)s")
    return int(args.func(args))


if __name__ == "__main__":
    sys.exit(main())
