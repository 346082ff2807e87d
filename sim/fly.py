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

import asyncio
import contextlib
import dataclasses
import errno
import importlib.util
import json
import math
import os
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

from apf_companion.config import (
    HEARTBEAT_TIMEOUT_RANGE_S,
    MAX_AGE_RANGE_S,
    TIME_SCALE_RANGE,
)
from apf_companion.errors import ConfigError, LinkTimeout
from apf_companion.links import MavlinkLink
from apf_companion.planning import FlyingArea, KeepOuts, area_text
from sim.linkfaults import LinkFaults, LinkProxy

if TYPE_CHECKING:
    from sim.world import World

__all__ = ["FlyOptions", "flown_world", "fly", "paper_world", "study_same_worlds"]

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


def read_json(path: Path) -> dict[str, Any] | None:
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
    sim_res = read_json(opt.out / "sim_result.json")
    svc_res = read_json(opt.out / "service_result.json")
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


def clearance_text(rec: dict[str, Any]) -> str:
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
        except ImportError as err:  # a missing matplotlib must not lose the flight result
            print(f"apf-sim fly: no plot ({err}; pip install 'apf-companion[sim]', or --no-plot)", file=sys.stderr)
        except Exception as err:  # nor a plot that fails for any other reason
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
