"""Sensor-to-setpoint latency and CPU share of the companion service at 10, 20 and 50 Hz.

Runs the real ``apf-companion run`` in a subprocess on loopback UDP and plays a scripted autopilot against it:
HEARTBEAT at 1 Hz, ATTITUDE + LOCAL_POSITION_NED at the cycle rate (the vehicle "flies" to each setpoint it
gets), OBSTACLE_DISTANCE (72 sectors, BODY_FRD) at 10 Hz from a field of obstacles. The goal lies 1 km away, so
the service navigates the whole time.

Measured:
- external latency: from sending a LOCAL_POSITION_NED to receiving the SET_POSITION_TARGET_LOCAL_NED it
  triggers (both processes' socket paths included);
- internal latency: the service's own pose-read-to-setpoint-sent time (its result JSON);
- CPU share of the service process: (utime + stime) / wall time over the measurement window, from /proc;
- the garbage collector over the whole run (its result JSON, ``apf_companion/heap.py``): collections, how many
  were full, and the longest pause;
- the scheduling policy the service process got (it asks for SCHED_FIFO itself, ``apf_companion/realtime.py``;
  ``--realtime-priority 0`` keeps it under the normal scheduler, ``--nice`` sets its niceness).

Usage: python benchmarks/bench_service_latency.py [--seconds 10] [--rates 10,20,50]
Targets (issue 4): p99 <= 2 ms and <= 5 % of one core at 20 Hz.
"""

from __future__ import annotations

import argparse
import asyncio
import json
import math
import os
import platform
import signal
import socket
import sys
import tempfile
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np

from apf_companion.config import CycleConfig, ServiceConfig
from apf_companion.links import MavlinkLink

UINT16_MAX = 65535
CLK_TCK = os.sysconf("SC_CLK_TCK")


def free_udp_port() -> int:
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def cpu_seconds(pid: int) -> float:
    fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    return (int(fields[11]) + int(fields[12])) / CLK_TCK  # utime, stime


def ranges_cm(pos: list[float], obstacles: np.ndarray) -> list[int]:
    """72 BODY_FRD sectors (yaw 0) of 5 deg: nearest obstacle per sector within 8 m, else free."""
    rel = obstacles - np.asarray(pos[:2])
    dist = np.hypot(rel[:, 0], rel[:, 1])
    bearing = np.degrees(np.arctan2(rel[:, 1], rel[:, 0])) % 360.0
    sector = np.round(bearing / 5.0).astype(int) % 72
    out = np.full(72, 801, dtype=np.int64)
    near = dist < 8.0
    np.minimum.at(out, sector[near], np.maximum(20, (dist[near] * 100).astype(np.int64)))
    return [int(v) for v in out]


def _niceness(nice: int) -> Callable[[], None] | None:
    """The service process's niceness increment (deploy/apf-companion.service: Nice=-5), or None for none."""
    if not nice:
        return None

    def apply() -> None:
        os.nice(nice)

    return apply


def policy_of(pid: int) -> str:
    """The scheduling policy a running process got (the service asks for SCHED_FIFO itself: ``realtime.py``)."""
    if os.sched_getscheduler(pid) == os.SCHED_FIFO:
        return f"SCHED_FIFO {os.sched_getparam(pid).sched_priority}"
    return "normal"


async def measure(rate_hz: float, seconds: float, workdir: Path, nice: int, rt_priority: int) -> dict[str, Any]:
    port = free_udp_port()
    cfg = workdir / f"bench_{int(rate_hz)}.toml"
    cfg.write_text(
        f"""
[link]
connect = "udpin:127.0.0.1:{port}"
telemetry_rate_hz = {rate_hz}
[cycle]
rate_hz = {rate_hz}
realtime_priority = {rt_priority}
[status]
named_value_rate_hz = 2.0
[goal]
north_m = 1000.0
east_m = 0.0
down_m = -5.0
"""
    )
    result_path = workdir / f"result_{int(rate_hz)}.json"
    proc = await asyncio.create_subprocess_exec(
        sys.executable,
        "-m",
        "apf_companion",
        "--log-level",
        "WARNING",
        "run",
        "--config",
        str(cfg),
        "--result-json",
        str(result_path),
        env=os.environ | {"OPENBLAS_NUM_THREADS": "1"},
        preexec_fn=_niceness(nice),
    )
    await asyncio.sleep(1.5)  # interpreter + numpy import
    link = await MavlinkLink.open(f"udpout:127.0.0.1:{port}", source_system=1, source_component=1)
    mav = link.mav
    rng = np.random.default_rng(0)
    # Obstacles off the path (|east| >= 1 m) so the flight goes on; 1 per 2 m^2 band either side.
    n_obs = 400
    obstacles = np.stack([rng.uniform(0, 400, n_obs), rng.choice([-1, 1], n_obs) * rng.uniform(1, 6, n_obs)], 1)
    pos = [0.0, 0.0, -5.0]
    latencies: list[float] = []
    pending: list[float] = []
    t0 = time.monotonic()

    async def rx() -> None:
        async for msg in link.messages():
            kind = msg.get_type()
            if kind == "SET_POSITION_TARGET_LOCAL_NED":
                now = time.perf_counter()
                if pending:
                    latencies.append((now - pending.pop(0)) * 1000.0)
                    pending.clear()
                pos[0], pos[1], pos[2] = msg.x, msg.y, msg.z
            elif kind == "COMMAND_LONG" and msg.command == 176:
                mode[0] = int(msg.param2)

    mode = [5]
    period = 1.0 / rate_hz
    warmup_s = 3.0
    cpu0 = wall0 = None
    lat_start = 0
    async with asyncio.TaskGroup() as tg:
        rx_task = tg.create_task(rx())
        n = 0
        next_t = time.monotonic()
        next_hb = next_range = next_t
        while True:
            now = time.monotonic()
            if now >= next_hb:
                link.send(mav.heartbeat_encode(2, 3, 129, mode[0], 4))
                next_hb += 1.0
            ms = int((now - t0) * 1000)
            if now >= next_range:
                cm = ranges_cm(pos, obstacles)
                link.send(mav.obstacle_distance_encode(ms * 1000, 0, cm, 0, 20, 800, 5.0, 0.0, 12))
                next_range += 0.1
            link.send(mav.attitude_encode(ms, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0))
            pending.clear()
            pending.append(time.perf_counter())
            link.send(mav.local_position_ned_encode(ms, pos[0], pos[1], pos[2], 0.0, 0.0, 0.0))
            n += 1
            if cpu0 is None and now - t0 >= warmup_s:
                cpu0, wall0, lat_start = cpu_seconds(proc.pid), now, len(latencies)
            if wall0 is not None and now - wall0 >= seconds:
                cpu1, wall1 = cpu_seconds(proc.pid), now
                break
            next_t += period
            await asyncio.sleep(max(0.0, next_t - time.monotonic()))
        rx_task.cancel()
    await link.aclose()
    policy = policy_of(proc.pid)
    proc.send_signal(signal.SIGINT)
    await asyncio.wait_for(proc.wait(), 10.0)
    internal = json.loads(result_path.read_text())
    lat = np.asarray(latencies[lat_start:])
    assert cpu0 is not None and wall0 is not None
    return {
        "rate_hz": rate_hz,
        "cycles": int(lat.size),
        "ext_p50_ms": float(np.percentile(lat, 50)) if lat.size else math.nan,
        "ext_p99_ms": float(np.percentile(lat, 99)) if lat.size else math.nan,
        "int_p50_ms": internal["latency_ms_p50"],
        "int_p99_ms": internal["latency_ms_p99"],
        "cpu_pct": 100.0 * (cpu1 - cpu0) / (wall1 - wall0),
        "state": internal["state"],
        "obstacles_seen": internal["counters"].get("scans", 0),
        "gc": internal["gc"],  # the collector over the whole run (apf_companion/heap.py)
        "policy": policy,
    }


async def main_async(rates: list[float], seconds: float, nice: int, rt_priority: int) -> list[dict[str, Any]]:
    with tempfile.TemporaryDirectory() as tmp:
        return [await measure(r, seconds, Path(tmp), nice, rt_priority) for r in rates]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0] if __doc__ else None)
    parser.add_argument("--seconds", type=float, default=10.0, help="measurement window per rate [s]")
    parser.add_argument("--rates", default="10,20,50", help="cycle rates [Hz], comma separated")
    parser.add_argument(
        "--nice",
        type=int,
        default=0,
        help="niceness increment of the service process (deploy/apf-companion.service: -5; below 0 needs root)",
    )
    parser.add_argument(
        "--realtime-priority",
        type=int,
        default=CycleConfig().realtime_priority,
        help="the service's cycle.realtime_priority: SCHED_FIFO priority it asks for, 0 = the normal scheduler "
        "(default: the config's default; refused without RLIMIT_RTPRIO or root, see the policy column)",
    )
    args = parser.parse_args()
    rates = [float(r) for r in args.rates.split(",")]
    print(f"# machine: {platform.machine()} {platform.processor() or ''} cpus={os.cpu_count()}")
    print(f"# python {platform.python_version()}, numpy {np.__version__}, {platform.platform()}")
    planner = ServiceConfig().planner.name
    print(f"# window {args.seconds:.0f} s per rate after 3 s warm-up; planner {planner} (the default config's)")
    print(
        f"# service: niceness {args.nice:+d} (relative to this process), cycle.realtime_priority "
        f"{args.realtime_priority}; load average {os.getloadavg()[0]:.2f}"
    )
    rows = asyncio.run(main_async(rates, args.seconds, args.nice, args.realtime_priority))
    print()
    print(
        "| rate Hz | cycles | ext p50 ms | ext p99 ms | int p50 ms | int p99 ms | CPU % of one core | "
        "collections (full) | longest collection ms | scheduling |"
    )
    print("|---:|---:|---:|---:|---:|---:|---:|---:|---:|---|")
    for r in rows:
        gc = r["gc"]
        print(
            f"| {r['rate_hz']:.0f} | {r['cycles']} | {r['ext_p50_ms']:.2f} | {r['ext_p99_ms']:.2f} | "
            f"{r['int_p50_ms']:.2f} | {r['int_p99_ms']:.2f} | {r['cpu_pct']:.1f} | "
            f"{gc['collections']} ({gc['full']}) | {gc['max_pause_ms']:.2f} | {r['policy']} |"
        )


if __name__ == "__main__":
    main()
