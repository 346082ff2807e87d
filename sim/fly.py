"""apf-sim fly: one SITL-style flight of the companion service against the bundled simulator, in one command.

Two processes on loopback, as on a real vehicle: the simulated autopilot (``apf-sim vehicle``) and the companion
service (``apf-companion run``), which finds the simulator on a free UDP port. This command watches the flight
on a third MAVLink link (as a ground station would), shows progress, and when the flight ends prints the outcome,
path length, minimum clearance and flight time, and writes a trajectory plot, both .tlogs, the results and (with
foxglove-sdk, the ``viz`` extra) the service's ``.mcap`` recording to ``--out``. ``--json PATH`` writes the
outcome record::

    {"outcome": "arrived" | "collision" | "fence_breach" | "stuck" | "timeout" | "link_lost" | "error",
     "steps": int, "fence_breaches": int,
     "min_clearance_m": float | null, "path_length_m": float, "sim_time_s": float, "flight_time_s": float,
     "planner": str, "profile": str, "world": str, "seed": int, "wall_time_s": float, ...}

The paper's scenario by default: take off at (3, 3), fly to (22, 22) at 5 m through a random field of point
obstacles (``--preset reference`` draws them in [5, 20]^2, ``paper`` in [0, 30]^2; ``--obstacles N`` or a
density low/mid/high), or any world file with ``--world``.

Time: the simulator runs ``--speedup`` times faster than real time and the service gets the same
``cycle.time_scale``, so its 10 Hz cycle and 0.5 s staleness limits stay in simulated seconds (50 Hz and 100 ms of
wall time at the default speed-up of 5); the heartbeat timeout is ``max(3, speedup)`` simulated seconds. The
vehicle starts with ``--fast-start`` (EKF origin at boot, not 20 s later as on SITL: the flights keep their speed;
the startup wait is tested in tests/service/test_service_startup.py), and streams only what is asked for, as a
real ArduCopter: the service requests its streams, the ground-station watcher its LOCAL_POSITION_NED.

``--trials N`` flies seeds SEED..SEED+N-1 and, on paper fields, runs the study's engine ``--study-reps`` times on
each flown field (``study_same_worlds``), so the flight rate is compared with the study's on the same worlds.
``--obstacles low,mid,high`` cycles the densities over the trials.

``--link-faults SPEC`` (e.g. ``loss=0.3,jitter=0.1,dup=0.05,reorder=0.05,blackout=2@40%``) puts a seeded
fault-injection proxy (``sim.linkfaults``, seeded with the flight's seed) between the vehicle and the service.
Its times are simulated seconds; a relative blackout (``2@40%``) is placed in the expected flight, which starts
when the takeoff is done and lasts the start-goal distance at ``EXPECTED_SPEED_M_S``.
"""

from __future__ import annotations

import argparse
import asyncio
import contextlib
import dataclasses
import errno
import importlib.util
import json
import math
import os
import re
import signal
import socket
import sys
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import IO, TYPE_CHECKING, Any

import numpy as np
import numpy.typing as npt
from pymavlink.dialects.v20 import ardupilotmega as mavlink

from apf_companion.autopilot import Autopilot
from apf_companion.config import (
    HEARTBEAT_TIMEOUT_RANGE_S,
    MAX_AGE_RANGE_S,
    MAX_FLIGHT_RANGE_S,
    RATE_RANGE_HZ,
    TAKEOFF_ALT_RANGE_M,
    TIME_SCALE_RANGE,
    GoalConfig,
)
from apf_companion.errors import ApfCompanionError, ConfigError, LinkTimeout
from apf_companion.links import MavlinkLink, load_signing_key
from apf_companion.planning import FlyingArea, KeepOuts, area_text, in_keepout, inside_area
from sim.linkfaults import LinkFaults, LinkProxy
from sim.vehicle.params import ParamSpec, ParamTable, param_specs
from sim.world.field import DENSITIES, MAX_OBSTACLES

if TYPE_CHECKING:
    from sim.world import World

__all__ = ["FlyOptions", "flown_world", "fly", "paper_world", "register", "route_problem", "study_same_worlds"]

OUTCOMES = ("arrived", "collision", "fence_breach", "stuck", "timeout", "link_lost", "error")
PAPER_START = (3.0, 3.0)
PAPER_GOAL = (22.0, 22.0)
# Measured: the default service flies the paper's 26.9 m diagonal in ~53 simulated s after the takeoff.
EXPECTED_SPEED_M_S = 0.5
GCS_POSITION_INTERVAL_US = 200_000.0  # the ground-station watcher's LOCAL_POSITION_NED: 5 Hz
# The service's time limits at a speed-up (simulated s): the heartbeat timeout is the speed-up, never less than
# HEARTBEAT_FLOOR_S (one wall second of silence); the staleness limits MAX_AGE_PER_SPEEDUP_S per unit of speed-up
# (100 ms of wall time), never less than MAX_AGE_FLOOR_S.
HEARTBEAT_FLOOR_S = 3.0
MAX_AGE_FLOOR_S = 0.5
MAX_AGE_PER_SPEEDUP_S = 0.1


def heartbeat_timeout_s(speedup: float) -> float:
    """``link.heartbeat_timeout_s`` of the service at ``--speedup`` [simulated s]."""
    return max(HEARTBEAT_FLOOR_S, speedup)


def max_age_s(speedup: float) -> float:
    """``cycle.pose_max_age_s`` and ``cycle.ranges_max_age_s`` of the service at ``--speedup`` [simulated s]."""
    return max(MAX_AGE_FLOOR_S, MAX_AGE_PER_SPEEDUP_S * speedup)


def _speedup_range() -> tuple[float, float]:
    """The ``--speedup`` values whose settings the service's config accepts: ``cycle.time_scale`` is the speed-up,
    the heartbeat timeout grows with it up to its limit, and so do the staleness limits (the floors lie inside)."""
    hi = min(TIME_SCALE_RANGE[1], HEARTBEAT_TIMEOUT_RANGE_S[1], MAX_AGE_RANGE_S[1] / MAX_AGE_PER_SPEEDUP_S)
    return TIME_SCALE_RANGE[0], hi


#: [lo, hi] of ``--speedup`` (from the service config's limits: apf_companion/config.py).
SPEEDUP_RANGE = _speedup_range()


@dataclass(frozen=True, slots=True, kw_only=True)
class FlyOptions:
    """One flight (the CLI flags of ``apf-sim fly``)."""

    planner: str = "bapf-nav"
    profile: str = "ardupilot"
    dynamics: str = "auto"  # the simulator's vehicle response: auto (per profile) | simple | arducopter
    seed: int = 0
    preset: str = "reference"
    obstacles: str = "mid"
    world: str | None = None
    start_ne_m: tuple[float, float] = PAPER_START
    goal_ne_m: tuple[float, float] = PAPER_GOAL
    #: The world file's flying area (a rectangle or a polygon, local NED) [m]: bapf-nav's nav_area_ne_m.
    area_ne_m: FlyingArea | None = None
    #: The world file's keep-out zones (polygons, local NED) [m]: bapf-nav's nav_keepout_ne_m.
    keepouts_ne_m: KeepOuts = ()
    #: The vehicle serves ``area_ne_m`` and the keep-out zones as its fence, and the service reads them
    #: (``planner.fence_area``) instead of finding them in its config.
    fence: bool = False
    #: ``NAME=VALUE`` parameter overrides for the simulated autopilot (``apf-sim vehicle --param``), e.g. its
    #: fence's FENCE_MARGIN.
    vehicle_params: tuple[str, ...] = ()
    alt_m: float = 5.0
    speedup: float = 5.0
    rate_hz: float = 10.0
    max_flight_s: float = 300.0
    noise_m: float = 0.0
    out: Path = Path("fly-out")
    json_path: Path | None = None
    plot: bool = True
    progress: bool = True
    service_args: tuple[str, ...] = field(default_factory=tuple)
    link_faults: LinkFaults | None = None
    signing_key: Path | None = None  # both processes sign with this key file and require signed input


PORT_ATTEMPTS = 3
_EADDRINUSE = f"[Errno {errno.EADDRINUSE}]"  # how OSError words it in the service's error


def free_udp_port() -> int:
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def paper_world(opt: FlyOptions) -> World:
    """The random field the simulator flies for ``opt`` (``--paper-field PRESET:OBSTACLES --field-seed SEED``):
    the same two calls ``apf-sim vehicle`` makes, so the same seed gives the same obstacle coordinates."""
    from sim.world import paper_field, parse_field_spec

    preset, count = parse_field_spec(f"{opt.preset}:{opt.obstacles}")
    return paper_field(preset, count, np.random.default_rng(opt.seed))


def flown_world(opt: FlyOptions, sim_res: dict[str, Any] | None) -> npt.NDArray[np.float64]:
    """(N, 2) north/east obstacle points the simulator flew: from its result file when there is one (exactly
    the coordinates it checked collisions against), else regenerated with :func:`paper_world`."""
    if sim_res is not None:
        circles = sim_res.get("world", {}).get("circles_ne_m")
        if circles is not None:
            return np.asarray(circles, dtype=np.float64).reshape(-1, 2)
    return np.array(paper_world(opt).circles_ne_m, dtype=np.float64)


def study_same_worlds(
    fields_ne_m: Sequence[npt.NDArray[np.float64]],
    *,
    preset: str,
    planner: str,
    replications: int,
    seed: int,
    noise_std_m: float | None = None,
) -> npt.NDArray[np.int64]:
    """The study's success count per world: ``replications`` lockstep trials (``sim.study.engine.simulate``,
    ``StudyConfig.from_preset(preset)``: its noise, detection and planner parameters) on each given field.

    ``noise_std_m`` replaces the preset's actuation noise (0: only the random walk varies between replications).
    Returns (W,) successes out of ``replications`` per field. One motion generator seeded with ``seed``.
    """
    from sim.study.config import StudyConfig
    from sim.study.engine import simulate
    from sim.study.metrics import Outcome
    from sim.study.worlds import WorldBatch

    if replications < 1:
        msg = f"study replications must be >= 1, got {replications}"
        raise ConfigError(msg)
    n_worlds = len(fields_ne_m)
    if n_worlds == 0:
        return np.zeros(0, dtype=np.int64)
    config = StudyConfig.from_preset(preset)
    if noise_std_m is not None:
        config = dataclasses.replace(config, noise_std_m=noise_std_m)
    n_max = max(max(len(f) for f in fields_ne_m), 1)
    obstacles = np.zeros((n_worlds, n_max, 2))
    mask = np.zeros((n_worlds, n_max), dtype=bool)
    for w, f in enumerate(fields_ne_m):
        obstacles[w, : len(f)] = f
        mask[w, : len(f)] = True
    # Trial w * R + r is replication r of world w.
    batch = WorldBatch(
        obstacles_m=np.repeat(obstacles, replications, axis=0), mask=np.repeat(mask, replications, axis=0)
    )
    result = simulate(config, planner, batch, np.random.default_rng(seed))
    ok = (result.records.outcome == Outcome.SUCCESS).reshape(n_worlds, replications)
    successes: npt.NDArray[np.int64] = ok.sum(axis=1).astype(np.int64)
    return successes


def _service_toml(opt: FlyOptions, port: int, tlog: Path) -> str:
    north, east = opt.goal_ne_m
    return f"""# written by apf-sim fly
exit_when_done = true
max_flight_s = {opt.max_flight_s}

[link]
connect = "udpin:127.0.0.1:{port}"
tlog = "{tlog}"
# Simulated seconds: a simulator process that falls behind the wall clock for a moment (a loaded machine)
# freezes its vehicle too, so a longer heartbeat timeout here flies nothing blind.
heartbeat_timeout_s = {heartbeat_timeout_s(opt.speedup)}

{_signing_toml(opt)}
[autopilot]
profile = "{opt.profile}"
arm = true
takeoff_alt_m = {opt.alt_m}

[planner]
name = "{opt.planner}"
seed = {opt.seed}
# The study allows 900 iterations (~0.5 s each here); give the random walk comparable room.
progress_timeout_s = 120.0
{_area_toml(opt)}
[cycle]
rate_hz = {opt.rate_hz}
time_scale = {opt.speedup}
pose_max_age_s = {max_age_s(opt.speedup)}
ranges_max_age_s = {max_age_s(opt.speedup)}

[goal]
north_m = {north}
east_m = {east}
down_m = {-opt.alt_m}
""" + _visualisation_toml(opt)


def _area_toml(opt: FlyOptions) -> str:
    """bapf-nav plans over the world's flying area and keep-out zones when the world file gives them (the other
    planners have none); with ``--fence`` the service reads them from the vehicle instead."""
    if (opt.area_ne_m is None and not opt.keepouts_ne_m) or opt.planner != "bapf-nav" or opt.fence:
        return ""
    lines = ["", "[planner.params]"]
    if opt.area_ne_m is not None:
        lines += [
            "# the world file's flying area [m]: (north_min, east_min, north_max, east_max) or polygon vertices",
            f"nav_area_ne_m = {area_text(opt.area_ne_m)}",
        ]
    if opt.keepouts_ne_m:
        zones = ", ".join(area_text(zone) for zone in opt.keepouts_ne_m)
        lines += ["# the world file's keep-out zones [m]", f"nav_keepout_ne_m = [{zones}]"]
    return "\n".join(lines) + "\n"


def _visualisation_toml(opt: FlyOptions) -> str:
    """Record the flight to ``OUT/apf-*.mcap`` beside the tlogs when foxglove-sdk (the ``viz`` extra) is there."""
    if importlib.util.find_spec("foxglove") is None:
        return ""
    return f"""
[visualisation]
mcap_dir = "{opt.out.resolve()}"
"""


def _signing_toml(opt: FlyOptions) -> str:
    if opt.signing_key is None:
        return ""
    key = opt.signing_key.resolve()
    return (
        f'signing_key_file = "{key}"\nsigning_timestamp_file = "{(opt.out / "signing.timestamp").resolve()}"\n'
        "require_signed_telemetry = true\n"
    )


def _sim_argv(opt: FlyOptions, port: int, gcs_port: int) -> list[str]:
    argv = [
        sys.executable,
        "-m",
        "sim",
        "--log-level",
        "WARNING",
        "vehicle",
        "--profile",
        opt.profile,
        "--dynamics",
        opt.dynamics,
        "--link",
        f"udpout:127.0.0.1:{port}",
        "--link",
        f"udpout:127.0.0.1:{gcs_port}",
        "--speedup",
        str(opt.speedup),
        "--seed",
        str(opt.seed),
        "--tlog",
        str(opt.out / "vehicle.tlog"),
        "--result-json",
        str(opt.out / "sim_result.json"),
        # One word: "--start -12.0,0.0" would read as two options to the vehicle's argparse.
        f"--start={opt.start_ne_m[0]},{opt.start_ne_m[1]}",
        "--exit-on-crash",
        "--fast-start",  # the EKF origin at boot: fly keeps its speed (the startup is tested in tests/service)
        "--duration",
        str(opt.max_flight_s + 120.0),
    ]
    if opt.noise_m > 0:
        argv += ["--param", f"SIM_POS_NOISE={opt.noise_m}"]
    for item in opt.vehicle_params:
        argv += ["--param", item]
    if opt.signing_key is not None:
        argv += ["--signing-key", str(opt.signing_key.resolve())]
    if opt.world is not None:
        zones = opt.area_ne_m is not None or bool(opt.keepouts_ne_m)
        argv += ["--world", opt.world, *(["--fence"] if opt.fence and zones else [])]
    else:
        argv += ["--paper-field", f"{opt.preset}:{opt.obstacles}", "--field-seed", str(opt.seed)]
    return argv


class _Progress:
    def __init__(self, enabled: bool, goal: tuple[float, float]) -> None:
        self.enabled = enabled
        self.goal = goal
        self.tty = sys.stderr.isatty()
        self.last_print = 0.0
        self.pos: tuple[float, float, float] | None = None
        self.sim_t = 0.0
        self.texts: list[str] = []

    def show(self, force: bool = False) -> None:
        if not self.enabled or self.pos is None:
            return
        now = time.monotonic()
        if not force and now - self.last_print < (0.2 if self.tty else 2.0):
            return
        self.last_print = now
        n, e, d = self.pos
        dist = math.hypot(self.goal[0] - n, self.goal[1] - e)
        line = f"t={self.sim_t:6.1f} s  pos=({n:6.2f}, {e:6.2f}, alt {-d:4.1f})  to goal {dist:5.2f} m"
        if self.tty:
            sys.stderr.write("\r" + line.ljust(78))
        else:
            sys.stderr.write(line + "\n")
        sys.stderr.flush()

    def done(self) -> None:
        if self.enabled and self.tty:
            sys.stderr.write("\n")


async def _watch(
    gcs: MavlinkLink, progress: _Progress, airborne_m: float, on_airborne: Callable[[], None] | None = None
) -> None:
    """Follow the flight as a ground station: position for the progress line, STATUSTEXT for the log;
    ``on_airborne()`` once the vehicle is ``airborne_m`` above home. Like a ground station it asks for
    LOCAL_POSITION_NED (an ArduCopter streams nothing unasked), at each HEARTBEAT until the first one arrives."""
    have_position = False
    while True:
        try:
            msg = await gcs.recv(timeout=1.0)
        except LinkTimeout:
            continue
        kind = msg.get_type()
        if kind == "HEARTBEAT" and not have_position:
            gcs.send(
                gcs.mav.command_long_encode(
                    msg.get_srcSystem(),
                    msg.get_srcComponent(),
                    mavlink.MAV_CMD_SET_MESSAGE_INTERVAL,
                    0,
                    float(mavlink.MAVLINK_MSG_ID_LOCAL_POSITION_NED),
                    GCS_POSITION_INTERVAL_US,
                    0,
                    0,
                    0,
                    0,
                    0,
                )
            )
        if kind == "LOCAL_POSITION_NED":
            have_position = True
            progress.pos = (msg.x, msg.y, msg.z)
            progress.sim_t = msg.time_boot_ms / 1000.0
            progress.show()
            if on_airborne is not None and -msg.z >= airborne_m:
                on_airborne()
                on_airborne = None
        elif kind == "STATUSTEXT":
            text = msg.text if isinstance(msg.text, str) else bytes(msg.text).decode(errors="replace")
            progress.texts.append(text.rstrip("\x00"))


async def _stop(proc: asyncio.subprocess.Process, grace_s: float) -> None:
    if proc.returncode is not None:
        return
    with contextlib.suppress(ProcessLookupError):
        proc.send_signal(signal.SIGINT)
    try:
        await asyncio.wait_for(proc.wait(), grace_s)
    except TimeoutError:
        with contextlib.suppress(ProcessLookupError):
            proc.kill()
        await proc.wait()


def _read_json(path: Path) -> dict[str, Any] | None:
    try:
        data = json.loads(path.read_text())
    except (OSError, ValueError):
        return None
    return data if isinstance(data, dict) else None


def _outcome(sim: dict[str, Any] | None, svc: dict[str, Any] | None) -> str:
    if sim is None:
        return "error"
    if sim.get("collided") or sim.get("crashed"):
        return "collision"
    if sim.get("fence_breaches"):  # the autopilot enforced its fence (sim.vehicle.fencebreach)
        return "fence_breach"
    if svc is None:
        return "error"
    outcome = svc.get("outcome")
    if outcome in ("arrived", "stuck", "timeout", "link_lost"):
        return str(outcome)
    return "error"


def _service_events(log_path: Path) -> dict[str, Any]:
    """What the service's JSON log says about the flight: state changes, failed takeovers, the last reason."""
    events: dict[str, Any] = {"link_lost": 0, "holding": 0, "takeover_failed": [], "last_reason": None}
    try:
        lines = log_path.read_text(errors="replace").splitlines()
    except OSError:
        return events
    for line in lines:
        try:
            ev = json.loads(line)
        except ValueError:
            continue
        if not isinstance(ev, dict):
            continue
        if ev.get("event") == "state.change":
            events["last_reason"] = ev.get("reason")
            if ev.get("new") == "LINK_LOST":
                events["link_lost"] += 1
            elif ev.get("new") == "HOLDING" and ev.get("old") != "HOLDING":  # not a new reason while holding
                events["holding"] += 1
        elif ev.get("event") == "takeover.failed":
            events["takeover_failed"].append(ev.get("error"))
    return events


def expected_flight_s(opt: FlyOptions) -> float:
    """The flight a relative blackout is placed in: start-goal distance at EXPECTED_SPEED_M_S [simulated s]."""
    dist = math.hypot(opt.goal_ne_m[0] - opt.start_ne_m[0], opt.goal_ne_m[1] - opt.start_ne_m[1])
    return max(dist / EXPECTED_SPEED_M_S, 1.0)


async def fly(opt: FlyOptions) -> dict[str, Any]:
    """Fly once; returns the result record (also written to ``opt.out/result.json`` and ``opt.json_path``).

    The service's UDP port is picked free here and bound by the service a moment later, in another process; on a
    busy machine another program may take it in between. The service then exits before the flight starts
    ("Address already in use"), and the flight is set up again on a new port, at most ``PORT_ATTEMPTS`` times
    (``port_retries`` in the record)."""
    for attempt in range(PORT_ATTEMPTS):
        record, sim_res = await _fly_once(opt)
        if not _port_taken(record) or attempt == PORT_ATTEMPTS - 1:
            break
    record["port_retries"] = attempt
    _write_result(opt, record, sim_res)
    return record


def _port_taken(record: dict[str, Any]) -> bool:
    """The flight never started because the service could not bind the port picked for it."""
    return record["outcome"] == "error" and record["steps"] == 0 and _EADDRINUSE in str(record.get("error", ""))


async def _fly_once(opt: FlyOptions) -> tuple[dict[str, Any], dict[str, Any] | None]:
    """One attempt: the result record and the simulator's result (None if it wrote none)."""
    opt.out.mkdir(parents=True, exist_ok=True)
    for stale in (*FLIGHT_FILES, *(p.name for p in opt.out.glob("apf-*.mcap"))):
        (opt.out / stale).unlink(missing_ok=True)  # a previous flight's: only this flight's are listed after it
    port = free_udp_port()
    gcs = await MavlinkLink.open("udpin:127.0.0.1:0", source_system=255, source_component=190)
    assert gcs.local_address is not None
    gcs_port = gcs.local_address[1]
    proxy: LinkProxy | None = None
    if opt.link_faults is not None:
        proxy = await LinkProxy.open(opt.link_faults, companion_port=port, seed=opt.seed, time_scale=opt.speedup)
    cfg_path = opt.out / "service.toml"
    cfg_path.write_text(_service_toml(opt, port, (opt.out / "companion.tlog").resolve()))
    env = os.environ | {"OPENBLAS_NUM_THREADS": "1"}
    t0 = time.monotonic()
    svc_log = (opt.out / "service.log").open("wb")
    sim_log = (opt.out / "vehicle.log").open("wb")
    service = await _start_service(opt, cfg_path, svc_log, env)
    vehicle_port = port if proxy is None else proxy.vehicle_port  # the vehicle talks to the proxy
    vehicle = await asyncio.create_subprocess_exec(
        *_sim_argv(opt, vehicle_port, gcs_port), stdout=sim_log, stderr=sim_log, env=env
    )
    progress = _Progress(opt.progress, opt.goal_ne_m)
    wall_limit_s = opt.max_flight_s / opt.speedup + 60.0  # + start-up and takeoff
    airborne = None if proxy is None else (lambda: proxy.start_flight(expected_flight_s(opt)))
    watcher = asyncio.create_task(_watch(gcs, progress, 0.9 * opt.alt_m, airborne))
    try:
        done, _ = await asyncio.wait(
            [asyncio.create_task(service.wait()), asyncio.create_task(vehicle.wait())],
            timeout=wall_limit_s,
            return_when=asyncio.FIRST_COMPLETED,
        )
        timed_out = not done
    finally:
        progress.show(force=True)
        progress.done()
        await _stop(service, 10.0)
        await _stop(vehicle, 10.0)
        watcher.cancel()
        with contextlib.suppress(asyncio.CancelledError):
            await watcher
        await gcs.aclose()
        if proxy is not None:
            await proxy.aclose()
        svc_log.close()
        sim_log.close()
    wall_s = time.monotonic() - t0
    sim_res = _read_json(opt.out / "sim_result.json")
    svc_res = _read_json(opt.out / "service_result.json")
    outcome = "timeout" if timed_out and sim_res is not None else _outcome(sim_res, svc_res)
    record = _record(opt, outcome, sim_res, svc_res, wall_s, (service.returncode, vehicle.returncode), progress.texts)
    if proxy is not None:
        record["link_faults"] = str(opt.link_faults)
        record["link_stats"] = proxy.stats_dict()
        record["blackout_windows_s"] = proxy.blackout_windows()
    return record, sim_res


async def _start_service(
    opt: FlyOptions, cfg_path: Path, log: IO[bytes], env: dict[str, str]
) -> asyncio.subprocess.Process:
    """The companion service (``python -m apf_companion run``) as a child process, logging JSON to ``log``."""
    return await asyncio.create_subprocess_exec(
        sys.executable,
        "-m",
        "apf_companion",
        "--log-format",
        "json",
        "run",
        "--config",
        str(cfg_path),
        "--result-json",
        str(opt.out / "service_result.json"),
        *opt.service_args,
        stdout=log,
        stderr=log,
        env=env,
    )


def _record(
    opt: FlyOptions,
    outcome: str,
    sim_res: dict[str, Any] | None,
    svc_res: dict[str, Any] | None,
    wall_s: float,
    exit_codes: tuple[int | None, int | None],
    statustexts: list[str],
) -> dict[str, Any]:
    """The flight's result record from the vehicle's and the service's result files."""
    return (
        {
            "outcome": outcome,
            "steps": int(svc_res["steps"]) if svc_res else 0,
            "min_clearance_m": sim_res.get("min_clearance_m") if sim_res else None,
            "fence_breaches": int(sim_res.get("fence_breaches", 0)) if sim_res else 0,
            "path_length_m": float(sim_res["path_length_m"]) if sim_res else 0.0,
            "sim_time_s": float(sim_res["sim_time_s"]) if sim_res else 0.0,
            "flight_time_s": float(svc_res["flight_time_s"]) if svc_res else 0.0,
            "planner": opt.planner,
            "profile": opt.profile,
            "dynamics": (sim_res or {}).get("dynamics", opt.dynamics),  # the vehicle's own (auto resolved)
            "world": (sim_res or {}).get("world", {}).get("name", opt.world),
            "seed": opt.seed,
            "speedup": opt.speedup,
            "wall_time_s": round(wall_s, 3),
            "service_state": svc_res.get("state") if svc_res else None,
            "latency_ms_p99": svc_res.get("latency_ms_p99") if svc_res else None,
            "service_exit_code": exit_codes[0],
            "vehicle_exit_code": exit_codes[1],
            "statustexts": statustexts[-20:],
            "service_outcome": svc_res.get("outcome") if svc_res else None,
            # The goal was lost without arriving: LINK_LOST, or IDLE after a failed takeover / mode loss.
            "dropped_goal": bool(svc_res and svc_res.get("state") in ("IDLE", "LINK_LOST")),
            "service_events": _service_events(opt.out / "service.log"),
            "mcap": next((str(p) for p in sorted(opt.out.glob("apf-*.mcap"))), None),
            "crash": (sim_res or {}).get("crashed_at"),  # the simulator's: reason, t_s, pos_ned_m, obstacle_id
            "airborne": airborne(sim_res),
        }
        | ({"error": error_reason(opt.out, svc_res, sim_res, exit_codes)} if outcome == "error" else {})
    )


AIRBORNE_M = 0.1  # a flight took off once the vehicle was this high above home [m]


def airborne(sim_res: dict[str, Any] | None) -> bool:
    """Whether the vehicle ever left the ground (its recorded trajectory rose ``AIRBORNE_M`` above home): a flight
    that never took off has no clearance worth printing, only the one of where it stood."""
    traj = (sim_res or {}).get("trajectory_ned_m") or []
    return any(isinstance(p, list) and len(p) == 3 and -float(p[2]) >= AIRBORNE_M for p in traj)


def clearance_flown(rec: dict[str, Any]) -> float | None:
    """A record's min clearance when it means something: the vehicle took off (or collided), else None."""
    clearance = rec.get("min_clearance_m")
    flew = rec.get("airborne", True) or rec.get("outcome") == "collision"
    return float(clearance) if isinstance(clearance, int | float) and flew else None


def _clearance_text(rec: dict[str, Any]) -> str:
    """The summary's min clearance: n/a when there is none or the vehicle never took off."""
    clearance = clearance_flown(rec)
    if clearance is None:
        return "n/a" if rec.get("airborne", True) else "n/a (the vehicle never took off)"
    return f"{clearance:.3f} m"


def error_reason(
    out: Path, svc_res: dict[str, Any] | None, sim_res: dict[str, Any] | None, exit_codes: tuple[int | None, int | None]
) -> str:
    """Why a flight ended in ``error``, for the user: the service's own error, else the last error line either
    process logged (a config error is printed before any JSON log), else the exit codes."""
    if svc_res and svc_res.get("error"):
        return f"service: {svc_res['error']}"
    for name, who in (("service.log", "service"), ("vehicle.log", "vehicle")):
        line = _last_error_line(out / name)
        if line:
            return f"{who}: {line}"
    if svc_res and svc_res.get("outcome") not in (None, "arrived"):
        return f"service ended {svc_res['outcome']} in state {svc_res.get('state')}"
    if sim_res is None:
        return f"no vehicle result (exit codes: service {exit_codes[0]}, vehicle {exit_codes[1]})"
    return f"exit codes: service {exit_codes[0]}, vehicle {exit_codes[1]}"


ERROR_DETAIL_LINES = 5  # at most this many "  - ..." lines under an error line (the service's config errors)


def _last_error_line(path: Path) -> str | None:
    """The last ERROR/CRITICAL JSON log event (with its error field) or plain ``prog: ...`` line of a log, with the
    first ``ERROR_DETAIL_LINES`` of the ``  - ...`` lines under it (``config error: 4 config errors:`` lists them)."""
    try:
        lines = path.read_text(errors="replace").splitlines()
    except OSError:
        return None
    for i in range(len(lines) - 1, -1, -1):
        text = lines[i].strip()
        if text.startswith("{"):
            with contextlib.suppress(ValueError):
                ev = json.loads(text)
                if isinstance(ev, dict) and ev.get("level") in ("ERROR", "CRITICAL"):
                    return f"{ev.get('event')}: {ev.get('error', '')}".rstrip(": ")
            continue
        if text.startswith(("apf-companion:", "apf-sim")) or "Error" in text:
            return text + _detail_lines(lines[i + 1 :], path.name)
    return None


def _detail_lines(lines: list[str], log_name: str) -> str:
    """The ``  - ...`` lines that follow an error line, the first ``ERROR_DETAIL_LINES`` of them, one per line."""
    details: list[str] = []
    for line in lines:
        if not line.lstrip().startswith("- "):
            break
        details.append(line.strip())
    shown = [f"\n  {d}" for d in details[:ERROR_DETAIL_LINES]]
    more = len(details) - ERROR_DETAIL_LINES
    return "".join(shown) + (f"\n  ... and {more} more in {log_name}" if more > 0 else "")


# What ``apf-sim fly`` lists on its ``output:`` line, then the rest it writes to --out (and apf-*.mcap). Each flight
# removes a previous flight's before it starts, so what is there afterwards is its own; anything else in --out
# (signing.timestamp, the user's files) is left alone.
LISTED_FILES = ("trajectory.png", "vehicle.tlog", "companion.tlog", "result.json", "service.log", "vehicle.log")
FLIGHT_FILES = (*LISTED_FILES, "sim_result.json", "service_result.json", "service.toml")


def output_files(out: Path) -> list[str]:
    """The files a flight actually wrote (what ``apf-sim fly`` lists: never a file it did not write)."""
    return [n for n in LISTED_FILES if (out / n).is_file() and (out / n).stat().st_size > 0]


def _write_result(opt: FlyOptions, record: dict[str, Any], sim_res: dict[str, Any] | None) -> None:
    """``result.json``, the --json copy and, with --plot, ``trajectory.png``."""
    (opt.out / "result.json").write_text(json.dumps(record, indent=2) + "\n")
    if opt.json_path is not None:
        opt.json_path.parent.mkdir(parents=True, exist_ok=True)
        opt.json_path.write_text(json.dumps(record, indent=2) + "\n")
    if opt.plot and sim_res is not None:
        try:
            plot_trajectory(sim_res, record, opt.out / "trajectory.png", goal_ne_m=opt.goal_ne_m)
        except Exception as err:  # a missing matplotlib must not lose the flight result
            print(f"apf-sim fly: no plot ({err})", file=sys.stderr)


def plot_trajectory(
    sim_res: dict[str, Any], record: dict[str, Any], path: Path, *, goal_ne_m: tuple[float, float]
) -> None:
    """The flown path over the world (east right, north up), with the start, goal and obstacles."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.patches import Circle

    world = sim_res.get("world", {})
    traj = sim_res.get("trajectory_ned_m") or []
    fig, ax = plt.subplots(figsize=(6.5, 6.5), dpi=110)
    for (n, e), r in zip(world.get("circles_ne_m", []), world.get("circle_radii_m", []), strict=False):
        ax.add_patch(Circle((e, n), max(r, 0.08), color="k"))
        ax.add_patch(Circle((e, n), max(r, 0.0) + 0.25, fill=False, ls=":", lw=0.6, color="r"))
    for (a, b), t in zip(world.get("walls_ne_m", []), world.get("wall_thickness_m", []), strict=False):
        ax.plot([a[1], b[1]], [a[0], b[0]], "k-", lw=max(2.0, 20 * t))
    if traj:
        ax.plot([p[1] for p in traj], [p[0] for p in traj], "-", color="tab:blue", lw=1.5, label="flown path")
        ax.plot(traj[0][1], traj[0][0], "go", label="start")
    ax.plot(goal_ne_m[1], goal_ne_m[0], "r*", ms=14, label="goal")
    ax.add_patch(Circle((goal_ne_m[1], goal_ne_m[0]), 0.7, fill=False, color="r", lw=0.8))
    crash = sim_res.get("crashed_at")
    if isinstance(crash, dict) and "pos_ned_m" in crash:
        ax.plot(crash["pos_ned_m"][1], crash["pos_ned_m"][0], "rx", ms=12, mew=2, label="collision")
    clearance = clearance_flown(record)
    ax.set_title(
        f"{record['planner']} ({record['profile']}), {record['world']}: {record['outcome']}\n"
        f"path {record['path_length_m']:.1f} m, min clearance "
        f"{'n/a' if clearance is None else f'{clearance:.2f} m'}, {record['steps']} steps"
    )
    ax.set_xlabel("east [m]")
    ax.set_ylabel("north [m]")
    ax.set_aspect("equal")
    ax.grid(True, alpha=0.3)
    ax.legend(loc="lower right", fontsize=8)
    fig.tight_layout()
    fig.savefig(path)
    plt.close(fig)


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


def _number_in(lo: float, hi: float, *, lo_open: bool = False, what: str) -> Callable[[str], float]:
    """An argparse type: a number in [lo, hi] (``(lo, hi]`` with ``lo_open``); ``what`` is its unit and meaning."""

    def parse(text: str) -> float:
        try:
            value = float(text)
        except ValueError:
            value = math.nan
        if not ((value > lo if lo_open else value >= lo) and value <= hi):  # NaN too
            msg = f"must be a number in {'(' if lo_open else '['}{lo:g}, {hi:g}] {what}, got {text!r}"
            raise argparse.ArgumentTypeError(msg)
        return value

    return parse


def _int_from(lo: int) -> Callable[[str], int]:
    """An argparse type: an integer >= lo."""

    def parse(text: str) -> int:
        try:
            value = int(text)
        except ValueError:
            value = lo - 1
        if value < lo:
            msg = f"must be an integer >= {lo}, got {text!r}"
            raise argparse.ArgumentTypeError(msg)
        return value

    return parse


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


def _vehicle_param(text: str) -> str:
    """``--vehicle-param NAME=VALUE`` with a finite number (the name and its range are checked per profile by
    :func:`vehicle_params`)."""
    name, sep, value = text.partition("=")
    try:
        number = float(value)
    except ValueError:
        number = math.nan
    if not sep or not name.strip() or not math.isfinite(number):
        msg = f"must be NAME=VALUE with a finite number VALUE, got {text!r}"
        raise argparse.ArgumentTypeError(msg)
    return f"{name.strip().upper()}={value.strip()}"


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
        "--planner", default="bapf-nav", help="bapf-nav (default), bendyruler, capf, bapf, a-bapf, cr-bapf, cr-bapf*"
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
        "--seed", type=_int_from(0), default=0, help="seed of the random field and the planner, >= 0 (default 0)"
    )
    p.add_argument("--preset", choices=("reference", "paper"), default="reference", help="random-field preset")
    p.add_argument(
        "--obstacles",
        type=_obstacles,
        default="mid",
        help=f"obstacle count N in [0, {MAX_OBSTACLES}], or density {'|'.join(DENSITIES)} (default mid); a list "
        "(low,mid,high) cycles over --trials",
    )
    p.add_argument("--world", help=f"world TOML file or bundled example ({', '.join(_bundled_worlds())})")
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
        type=_vehicle_param,
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
    # The service takes off to --alt (autopilot.takeoff_alt_m) and refuses a goal higher than goal.max_altitude_m.
    alt_hi = min(TAKEOFF_ALT_RANGE_M[1], GoalConfig().max_altitude_m)
    p.add_argument(
        "--alt",
        type=_number_in(0.0, alt_hi, lo_open=True, what="m (the service's takeoff height and goal.max_altitude_m)"),
        default=5.0,
        help=f"flight height above home, in (0, {alt_hi:g}] m (default 5)",
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
        type=_number_in(rate_lo, rate_hi, what="Hz (the service's cycle.rate_hz)"),
        default=10.0,
        help=f"service cycle rate in simulated Hz, in [{rate_lo:g}, {rate_hi:g}] (default 10)",
    )
    flight_hi = MAX_FLIGHT_RANGE_S[1]
    p.add_argument(
        "--max-flight",
        type=_number_in(0.0, flight_hi, lo_open=True, what="simulated s (the service's max_flight_s)"),
        default=300.0,
        help=f"give up after this many simulated s, in (0, {flight_hi:g}] (default 300)",
    )
    noise = _noise_spec()
    p.add_argument(
        "--noise",
        type=_number_in(noise.lo, noise.hi, what=f"m (the vehicle's {noise.name})"),
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
        type=_int_from(1),
        default=1,
        help="fly this many worlds (seeds SEED, SEED+1, ...) one after another and print the success rate (>= 1)",
    )
    p.add_argument(
        "--study-reps",
        type=_int_from(0),
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


def _bundled_worlds() -> list[str]:
    from sim.world import EXAMPLES_DIR

    return sorted(p.stem for p in EXAMPLES_DIR.glob("*.toml"))


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
    for flag, (north, east) in (("--start", opt.start_ne_m), ("--goal", opt.goal_ne_m)):
        point = f"{flag} (north {north:g} m, east {east:g} m)"
        if opt.area_ne_m is not None and not inside_area(opt.area_ne_m, north, east):
            return (
                f"{point} lies outside the flying area of {where}, area_ne_m = {area_text(opt.area_ne_m)}: "
                "pick a point inside it, or fly without the area (--no-area)"
            )
        if in_keepout(opt.keepouts_ne_m, north, east):
            return f"{point} lies in a keep-out zone of {where}: pick a point outside it, or --no-area"
    if world is not None:
        i, clearance = world.nearest_obstacle(opt.start_ne_m)
        if clearance < radius_m:
            kind = "cylinder" if i < world.n_circles else "wall"
            north, east = opt.start_ne_m
            gap = f"lies inside {kind} {i}" if clearance < 0 else f"is {clearance:.2f} m from {kind} {i}"
            return (
                f"--start (north {north:g} m, east {east:g} m) {gap} of world {world.name}, within the vehicle's "
                "collision "
                f"radius SIM_VEH_RADIUS = {radius_m:g} m: the flight would end in a collision at once"
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
        opt = dataclasses.replace(opt, obstacles=_densities(opt)[0])
    # A world file's obstacles, or the one paper field a single flight flies (the trials' are random draws).
    world = route.world if opt.world is not None else (paper_world(opt) if args.trials <= 1 else None)
    problem = route_problem(opt, world, radius_m)
    if problem is not None:
        print(f"apf-sim fly: {problem}", file=sys.stderr)
        return 2
    if args.trials > 1:
        return _sweep(opt, args.trials, study_reps=args.study_reps)
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
        f"min clearance: {_clearance_text(rec)}\n"
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


def wilson_interval(successes: int, n: int, z: float = 1.96) -> tuple[float, float]:
    """95 % Wilson score interval of a binomial proportion."""
    if n == 0:
        return (0.0, 1.0)
    p = successes / n
    denom = 1.0 + z * z / n
    centre = (p + z * z / (2 * n)) / denom
    half = z * math.sqrt(p * (1 - p) / n + z * z / (4 * n * n)) / denom
    return (max(0.0, centre - half), min(1.0, centre + half))


def _sweep_loop(
    base: FlyOptions, trials: int, records: list[dict[str, Any]], fields: list[npt.NDArray[np.float64]]
) -> None:
    from sim.study.cli import eta_text

    densities = _densities(base)
    started = time.monotonic()
    for k in range(trials):
        seed = base.seed + k
        opt = dataclasses.replace(
            base,
            seed=seed,
            obstacles=densities[k % len(densities)],
            out=base.out / f"seed-{seed}",
            json_path=None,
            progress=False,
            plot=base.plot,
        )
        try:
            rec = asyncio.run(fly(opt))
        except ApfCompanionError as err:
            rec = {"outcome": "error", "seed": seed, "error": str(err)}
        if base.world is None:
            fields.append(flown_world(opt, _read_json(opt.out / "sim_result.json")))
            rec["obstacles"] = opt.obstacles
        records.append(rec)
        ok = sum(r["outcome"] == "arrived" for r in records)
        clearance = clearance_flown(rec)
        clearance_txt = "-" if clearance is None else f"{clearance:.3f} m"
        print(
            f"[{k + 1}/{trials}] seed {seed}: {rec['outcome']:9s} world {rec.get('world')} "
            f"clearance {clearance_txt} steps {rec.get('steps')}  (success so far {ok}/{k + 1})"
            f"{eta_text(k + 1, trials, time.monotonic() - started)}",
            flush=True,
        )


def _densities(opt: FlyOptions) -> list[str]:
    """``--obstacles low,mid,high``: the densities the trials cycle through (one entry: all the same)."""
    return [d.strip() for d in opt.obstacles.split(",") if d.strip()] or ["mid"]


def _fault_summary(records: list[dict[str, Any]]) -> dict[str, Any]:
    """Collisions, lowest clearance, dropped goals and LINK_LOST events over the trials (for --link-faults)."""
    clearances = [c for c in map(clearance_flown, records) if c is not None]
    events = [r.get("service_events") or {} for r in records]
    return {
        "collisions": sum(r["outcome"] == "collision" for r in records),
        "min_clearance_m": min(clearances) if clearances else None,
        "dropped_goals": sum(bool(r.get("dropped_goal")) for r in records),
        "link_lost_events": sum(int(e.get("link_lost", 0)) for e in events),
        "flights_with_link_lost": sum(int(e.get("link_lost", 0)) > 0 for e in events),
        "takeover_failures": sum(len(e.get("takeover_failed") or []) for e in events),
        "by_obstacles": {
            d: {o: sum(r["outcome"] == o and r.get("obstacles") == d for r in records) for o in OUTCOMES}
            for d in sorted({str(r.get("obstacles")) for r in records})
        },
    }


def _mean_ci(values: npt.NDArray[np.float64], z: float = 1.96) -> tuple[float, float, float]:
    """Mean and its normal-approximation 95 % interval (worlds as the sampling unit)."""
    mean = float(values.mean())
    if values.size < 2:
        return mean, -math.inf, math.inf
    half = z * float(values.std(ddof=1)) / math.sqrt(values.size)
    return mean, mean - half, mean + half


def _study_summary(
    base: FlyOptions, records: list[dict[str, Any]], fields: list[npt.NDArray[np.float64]], replications: int
) -> dict[str, Any]:
    """The study's rate on the flown fields, per world into ``records``, overall as the returned dict."""
    successes = study_same_worlds(
        fields, preset=base.preset, planner=base.planner, replications=replications, seed=base.seed
    )
    for rec, n_ok in zip(records, successes, strict=True):
        rec["study_successes"] = int(n_ok)
        rec["study_rate"] = float(n_ok) / replications
    total = int(successes.sum())
    n = replications * len(records)
    quiet = study_same_worlds(
        fields, preset=base.preset, planner=base.planner, replications=replications, seed=base.seed, noise_std_m=0.0
    )
    for rec, n_ok in zip(records, quiet, strict=True):
        rec["study_rate_no_noise"] = float(n_ok) / replications
    fly_ok = np.array([r["outcome"] == "arrived" for r in records], dtype=np.float64)
    study_rate = successes.astype(np.float64) / replications
    mean, lo, hi = _mean_ci(study_rate)
    diff, dlo, dhi = _mean_ci(fly_ok - study_rate)
    return {
        "rate": total / n,
        # Every trial as independent (as the study reports its rates) ...
        "ci95": list(wilson_interval(total, n)),
        # ... and with the world as the unit (these worlds are a sample of the density's fields).
        "ci95_worlds": [max(0.0, lo), min(1.0, hi)],
        "replications": replications,
        "trials": n,
        "preset": base.preset,
        "planner": base.planner,
        "noise_std_m": _study_noise(base.preset),
        "fly_minus_study": diff,
        "fly_minus_study_ci95": [dlo, dhi],
        "study_mean_of_world_rates": mean,
        # The same trials without actuation noise: how much of the gap the noise explains.
        "no_noise": {"rate": int(quiet.sum()) / n, "ci95": list(wilson_interval(int(quiet.sum()), n))},
    }


def _study_noise(preset: str) -> float:
    from sim.study.config import StudyConfig

    return float(StudyConfig.from_preset(preset).noise_std_m)


def _sweep(base: FlyOptions, trials: int, study_reps: int = 0) -> int:
    """Fly seeds base.seed .. base.seed + trials - 1; per-trial output in OUT/seed-<k>/, summary in OUT/.

    With ``study_reps`` > 0 (paper fields only) the study's engine then runs ``study_reps`` noisy trials on each
    flown field, so the flight rate can be compared with the study's on exactly the same worlds.
    """
    records: list[dict[str, Any]] = []
    fields: list[npt.NDArray[np.float64]] = []
    try:
        _sweep_loop(base, trials, records, fields)
    except KeyboardInterrupt:
        print(f"interrupted after {len(records)} flights", file=sys.stderr)
    trials = len(records)
    if trials == 0:
        return 130
    summary = _sweep_summary(base, records)
    study: dict[str, Any] | None = None
    if study_reps > 0 and base.world is None and len(fields) == trials:
        study = _study_summary(base, records, fields, study_reps)
        summary["study_same_worlds"] = study
    summary["records"] = records
    base.out.mkdir(parents=True, exist_ok=True)
    (base.out / "sweep.json").write_text(json.dumps(summary, indent=2) + "\n")
    if base.json_path is not None:
        base.json_path.write_text(json.dumps(summary, indent=2) + "\n")
    _print_sweep(base, summary, study, study_reps)
    return 0


def _sweep_summary(base: FlyOptions, records: list[dict[str, Any]]) -> dict[str, Any]:
    """The sweep's summary: outcome counts, success rate with its Wilson interval, means, fault counts."""
    trials = len(records)
    counts = {o: sum(r["outcome"] == o for r in records) for o in OUTCOMES}
    ok = counts["arrived"]
    lo, hi = wilson_interval(ok, trials)
    wins = [r for r in records if r["outcome"] == "arrived"]
    return {
        "planner": base.planner,
        "profile": base.profile,
        "preset": base.preset if base.world is None else None,
        "obstacles": base.obstacles if base.world is None else None,
        "world": base.world,
        "noise_m": base.noise_m,
        "trials": trials,
        "first_seed": base.seed,
        "success_rate": ok / trials,
        "success_rate_95ci": [lo, hi],
        "counts": counts,
        "mean_steps_success": (sum(r["steps"] for r in wins) / len(wins)) if wins else None,
        "mean_path_length_m_success": (sum(r["path_length_m"] for r in wins) / len(wins)) if wins else None,
        "link_faults": None if base.link_faults is None else str(base.link_faults),
        **_fault_summary(records),
    }


def _print_sweep(base: FlyOptions, summary: dict[str, Any], study: dict[str, Any] | None, study_reps: int) -> None:
    """The sweep's summary lines on stdout."""
    trials = summary["trials"]
    counts = summary["counts"]
    ok = counts["arrived"]
    lo, hi = summary["success_rate_95ci"]
    print(
        f"success {ok}/{trials} = {ok / trials:.3f} (95 % CI {lo:.3f}-{hi:.3f}); "
        + ", ".join(f"{o} {n}" for o, n in counts.items())
    )
    clearance = summary["min_clearance_m"]
    print(
        f"collisions {summary['collisions']}, lowest clearance "
        f"{'n/a' if clearance is None else f'{clearance:.3f} m'}, dropped goals {summary['dropped_goals']}, "
        f"LINK_LOST {summary['link_lost_events']} (in {summary['flights_with_link_lost']} flights), "
        f"failed takeovers {summary['takeover_failures']}"
        + ("" if base.link_faults is None else f"; link faults {base.link_faults}")
    )
    if study is not None:
        slo, shi = study["ci95"]
        wlo, whi = study["ci95_worlds"]
        dlo, dhi = study["fly_minus_study_ci95"]
        print(
            f"study on the same {trials} worlds ({study['preset']}, noise {study['noise_std_m']} m, "
            f"{study_reps} replications each): {study['rate']:.3f} (95 % CI {slo:.3f}-{shi:.3f} over trials, "
            f"{wlo:.3f}-{whi:.3f} over worlds); without its noise {study['no_noise']['rate']:.3f}\n"
            f"flight {ok / trials:.3f} vs study {study['rate']:.3f}: paired difference "
            f"{study['fly_minus_study']:+.3f} (95 % CI {dlo:+.3f} to {dhi:+.3f})"
        )
