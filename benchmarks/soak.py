"""Soak: one long-lived companion service flies accelerated simulated flights back to back for N minutes.

One ``apf-companion run`` process stays up the whole time (its memory and latency are what a soak measures).
For each flight a fresh ``apf-sim vehicle`` starts in a random paper field (preset ``reference``, density low/mid/
high at random, field seed = flight number) at a random start on one side of the field, and the soak sends a goal
on the far side over zenoh (``apf/cmd/goal``). The flight ends at ARRIVED or STUCK (from the service's zenoh
status), a crash (the vehicle exits), or ``--max-flight`` simulated seconds; the vehicle is then stopped, the
service sees LINK_LOST, and the next vehicle's heartbeat brings it back to IDLE for the next goal. With
``--link-faults SPEC`` each flight goes through the seeded proxy of ``sim.linkfaults``.

Sampled every ``--interval`` wall seconds:
- RSS of the service process (``VmRSS`` from /proc);
- the service's loop latency (pose read to setpoint sent, its ``loop_latency_ms.last`` in the status at
  ``status_rate_hz``): p50/p99 of the samples in the interval;
- the service's counters (status ``counters``): deltas per interval, totals at the end.
The summary gives RSS growth (first sample after the first flight to the last, and a least-squares slope), latency
drift (p50/p99 of the first vs the last interval, and the p99 slope), the flight outcomes, and the service's final
result counters (``--result-json`` at exit: navigator and link counters too).

Usage: python benchmarks/soak.py [--minutes 5] [--interval 30] [--speedup 5] [--link-faults SPEC] [--seed 0]
Target (issue 9): RSS growth < 5 MB over 30 minutes, no latency drift.
"""

from __future__ import annotations

import argparse
import asyncio
import contextlib
import dataclasses
import json
import math
import os
import platform
import signal
import socket
import sys
import tempfile
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from apf_companion.links.zenoh import ZenohConfig, ZenohLink, ZenohSubscription
from apf_companion.perception import GoalCommand, encode_goal_json
from sim.linkfaults import LinkFaults, LinkProxy

ALT_M = 5.0
EXPECTED_SPEED_M_S = 0.5  # as apf-sim fly: the default service's average speed through a paper field
DENSITIES = ("low", "mid", "high")
STATUS_KEY = "apf/status"
GOAL_KEY = "apf/cmd/goal"


def _free_port(kind: int) -> int:
    with socket.socket(socket.AF_INET, kind) as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def _rss_mb(pid: int) -> float | None:
    try:
        for line in Path(f"/proc/{pid}/status").read_text().splitlines():
            if line.startswith("VmRSS:"):
                return int(line.split()[1]) / 1024.0
    except OSError:
        return None
    return None


def _service_toml(port: int, zport: int, speedup: float, seed: int) -> str:
    age = max(0.5, 0.1 * speedup)
    return f"""# written by benchmarks/soak.py
exit_when_done = false

[link]
connect = "udpin:127.0.0.1:{port}"
heartbeat_timeout_s = {max(3.0, speedup)}

[autopilot]
profile = "ardupilot"
arm = true
takeoff_alt_m = {ALT_M}

[planner]
seed = {seed}
progress_timeout_s = 120.0

[cycle]
rate_hz = 10.0
time_scale = {speedup}
pose_max_age_s = {age}
ranges_max_age_s = {age}

[zenoh]
enabled = true
mode = "peer"
listen = ["tcp/127.0.0.1:{zport}"]
status_rate_hz = 10.0
"""


def _start_goal(rng: np.random.Generator) -> tuple[tuple[float, float], tuple[float, float]]:
    """A random diagonal across the reference field ([5, 20]^2 obstacles): start in one corner, goal in the
    opposite one, each jittered by up to 2 m."""
    corners = ((3.0, 3.0), (3.0, 22.0), (22.0, 22.0), (22.0, 3.0))
    k = int(rng.integers(4))
    start, goal = np.array(corners[k]), np.array(corners[(k + 2) % 4])
    start += rng.uniform(-2.0, 2.0, 2)
    goal += rng.uniform(-2.0, 2.0, 2)
    return (float(start[0]), float(start[1])), (float(goal[0]), float(goal[1]))


@dataclass(slots=True)
class StatusFeed:
    """The service's zenoh status, collected in the background."""

    latest: dict[str, Any] | None = None
    latencies_ms: list[float] = field(default_factory=list)
    received: int = 0

    async def follow(self, sub: ZenohSubscription) -> None:
        async for sample in sub:
            try:
                status = json.loads(sample.payload)
            except ValueError:
                continue
            self.latest = status
            self.received += 1
            lat = status.get("loop_latency_ms") or {}
            if isinstance(lat.get("last"), int | float):
                self.latencies_ms.append(float(lat["last"]))

    def state(self) -> str | None:
        return None if self.latest is None else self.latest.get("state")

    def link_alive(self) -> bool:
        return bool(self.latest and (self.latest.get("autopilot") or {}).get("link_alive"))


@dataclass(frozen=True, slots=True)
class Flight:
    index: int
    density: str
    start_ne_m: tuple[float, float]
    goal_ne_m: tuple[float, float]
    outcome: str
    min_clearance_m: float | None
    sim_time_s: float
    wall_s: float


class Soak:
    def __init__(self, args: argparse.Namespace, workdir: Path) -> None:
        self.args = args
        self.workdir = workdir
        self.rng = np.random.default_rng(args.seed)
        self.faults = LinkFaults.parse(args.link_faults) if args.link_faults else None
        self.port = _free_port(socket.SOCK_DGRAM)
        self.zport = _free_port(socket.SOCK_STREAM)
        self.feed = StatusFeed()
        self.flights: list[Flight] = []
        self.service: asyncio.subprocess.Process | None = None
        self.stop = asyncio.Event()  # SIGINT / SIGTERM: finish the current flight, then summarise

    # ---- one flight ------------------------------------------------------------------------------------------
    async def _wait(self, cond: Any, timeout_s: float) -> bool:
        deadline = time.monotonic() + timeout_s
        while not cond():
            if time.monotonic() > deadline:
                return False
            await asyncio.sleep(0.05)
        return True

    async def fly(self, k: int, zl: ZenohLink) -> Flight:
        args = self.args
        density = DENSITIES[int(self.rng.integers(len(DENSITIES)))]
        start, goal = _start_goal(self.rng)
        out = self.workdir / f"flight-{k}"
        out.mkdir()
        proxy = None
        target_port = self.port
        if self.faults is not None:
            proxy = await LinkProxy.open(
                self.faults, companion_port=self.port, seed=args.seed + k, time_scale=args.speedup
            )
            target_port = proxy.vehicle_port
        argv = [
            sys.executable, "-m", "sim", "--log-level", "WARNING", "vehicle",
            "--link", f"udpout:127.0.0.1:{target_port}",
            "--speedup", str(args.speedup),
            "--seed", str(args.seed + k),
            "--paper-field", f"reference:{density}", "--field-seed", str(args.seed + k),
            "--start", f"{start[0]},{start[1]}",
            "--result-json", str(out / "sim_result.json"),
            "--exit-on-crash",
            "--duration", str(args.max_flight + 60.0),
        ]  # fmt: skip
        if args.tlogs:
            argv += ["--tlog", str(out / "vehicle.tlog")]
        t0 = time.monotonic()
        with (out / "vehicle.log").open("wb") as log:
            vehicle = await asyncio.create_subprocess_exec(*argv, stdout=log, stderr=log)
        try:
            outcome = await self._run_flight(vehicle, zl, start, goal, proxy)
        finally:
            if vehicle.returncode is None:
                with contextlib.suppress(ProcessLookupError):
                    vehicle.send_signal(signal.SIGINT)
                try:
                    await asyncio.wait_for(vehicle.wait(), 10.0)
                except TimeoutError:
                    vehicle.kill()
                    await vehicle.wait()
            if proxy is not None:
                await proxy.aclose()
        try:
            sim = json.loads((out / "sim_result.json").read_text())
        except (OSError, ValueError):
            sim = {}
        if sim.get("collided") or sim.get("crashed"):
            outcome = "collision"
        # The vehicle is gone: wait until the service has noticed (LINK_LOST), so the next vehicle starts clean.
        await self._wait(lambda: not self.feed.link_alive(), 30.0)
        return Flight(
            index=k,
            density=density,
            start_ne_m=start,
            goal_ne_m=goal,
            outcome=outcome,
            min_clearance_m=sim.get("min_clearance_m"),
            sim_time_s=float(sim.get("sim_time_s", 0.0)),
            wall_s=time.monotonic() - t0,
        )

    async def _run_flight(
        self,
        vehicle: asyncio.subprocess.Process,
        zl: ZenohLink,
        start: tuple[float, float],
        goal: tuple[float, float],
        proxy: LinkProxy | None,
    ) -> str:
        args = self.args
        if not await self._wait(lambda: self.feed.link_alive() and self.feed.state() == "IDLE", 60.0):
            return "no_link"
        payload = encode_goal_json(GoalCommand(pos_ned_m=np.array([goal[0], goal[1], -ALT_M])))

        for _ in range(10):  # once, then again only if the service has not taken it within 3 s (a lost sample)
            zl.publish(GOAL_KEY, payload)
            if await self._wait(lambda: self.feed.state() == "NAVIGATING", 3.0):
                break
        else:
            return "goal_refused"
        if proxy is not None:  # relative blackouts: in a flight of the start-goal distance at 0.5 m/s
            proxy.start_flight(math.dist(start, goal) / EXPECTED_SPEED_M_S)
        limit_s = args.max_flight / args.speedup + 30.0
        ends = {"ARRIVED": "arrived", "STUCK": "stuck", "LINK_LOST": "link_lost", "IDLE": "dropped"}
        deadline = time.monotonic() + limit_s
        while time.monotonic() < deadline:
            if vehicle.returncode is not None:
                return "vehicle_exit"
            state = self.feed.state()
            if state in ends:
                return ends[state]
            await asyncio.sleep(0.05)
        return "timeout"

    # ---- sampling --------------------------------------------------------------------------------------------
    def sample(self, t_wall: float, last_counters: dict[str, int], dt_s: float) -> dict[str, Any]:
        assert self.service is not None
        lat = np.asarray(self.feed.latencies_ms, dtype=np.float64)
        self.feed.latencies_ms = []
        counters = dict((self.feed.latest or {}).get("counters") or {})
        row: dict[str, Any] = {
            "t_s": round(t_wall, 1),
            "dt_s": round(dt_s, 1),
            "flights": len(self.flights),
            "rss_mb": _rss_mb(self.service.pid),
            "lat_n": int(lat.size),
            "lat_p50_ms": float(np.percentile(lat, 50)) if lat.size else None,
            "lat_p99_ms": float(np.percentile(lat, 99)) if lat.size else None,
            "counters": counters,
            "delta": {k: v - last_counters.get(k, 0) for k, v in counters.items()},
        }
        return row

    async def run(self) -> dict[str, Any]:
        args = self.args
        cfg = self.workdir / "service.toml"
        toml = _service_toml(self.port, self.zport, args.speedup, args.seed)
        if args.tlogs:  # every frame the service sent and received, for the whole soak
            toml = toml.replace("[link]\n", f'[link]\ntlog = "{self.workdir / "companion.tlog"}"\n')
        cfg.write_text(toml)
        env = os.environ | {"OPENBLAS_NUM_THREADS": "1"}
        svc_log = (self.workdir / "service.log").open("wb")
        self.service = await asyncio.create_subprocess_exec(
            sys.executable, "-m", "apf_companion", "--log-format", "json", "run", "--config", str(cfg),
            "--result-json", str(self.workdir / "service_result.json"),
            stdout=svc_log, stderr=svc_log, env=env,
        )  # fmt: skip
        rows: list[dict[str, Any]] = []
        t_start = time.monotonic()
        loop = asyncio.get_running_loop()
        for sig in (signal.SIGINT, signal.SIGTERM):  # also when started in the background (SIGINT ignored)
            loop.add_signal_handler(sig, self.stop.set)
        try:
            zl = None
            for _ in range(100):  # the service opens its zenoh listener a moment after it starts
                with contextlib.suppress(Exception):
                    zl = await ZenohLink.open(ZenohConfig(mode="peer", connect=(f"tcp/127.0.0.1:{self.zport}",)))
                    break
                await asyncio.sleep(0.1)
            if zl is None:
                msg = "cannot reach the service's zenoh listener"
                raise RuntimeError(msg)
            async with zl:
                sub = await zl.subscribe(STATUS_KEY)
                follower = asyncio.create_task(self.feed.follow(sub))
                sampler = asyncio.create_task(self._sampler(rows, t_start))
                try:
                    k = 0
                    while time.monotonic() - t_start < args.minutes * 60.0 and not self.stop.is_set():
                        flight = await self.fly(k, zl)
                        self.flights.append(flight)
                        clearance = "n/a" if flight.min_clearance_m is None else f"{flight.min_clearance_m:.2f} m"
                        print(
                            f"  flight {k:3d} ({flight.density:4s}): {flight.outcome:12s} clearance {clearance:>7s} "
                            f"sim {flight.sim_time_s:5.1f} s wall {flight.wall_s:5.1f} s",
                            flush=True,
                        )
                        k += 1
                finally:
                    sampler.cancel()
                    with contextlib.suppress(asyncio.CancelledError):
                        await sampler
                    rows.append(self._row(rows, t_start))
                    follower.cancel()
                    with contextlib.suppress(asyncio.CancelledError):
                        await follower
        finally:
            if self.service.returncode is None:
                self.service.send_signal(signal.SIGINT)
                try:
                    await asyncio.wait_for(self.service.wait(), 15.0)
                except TimeoutError:
                    self.service.kill()
                    await self.service.wait()
            svc_log.close()
        return self.summary(rows, time.monotonic() - t_start)

    def _row(self, rows: list[dict[str, Any]], t_start: float) -> dict[str, Any]:
        last = rows[-1]["counters"] if rows else {}
        t = time.monotonic() - t_start
        row = self.sample(t, last, t - (rows[-1]["t_s"] if rows else 0.0))
        _print_row(row, header=not rows)
        return row

    async def _sampler(self, rows: list[dict[str, Any]], t_start: float) -> None:
        while True:
            await asyncio.sleep(self.args.interval)
            rows.append(self._row(rows, t_start))

    # ---- summary ---------------------------------------------------------------------------------------------
    def summary(self, rows: list[dict[str, Any]], wall_s: float) -> dict[str, Any]:
        try:
            result = json.loads((self.workdir / "service_result.json").read_text())
        except (OSError, ValueError):
            result = {}
        outcomes: dict[str, int] = {}
        for f in self.flights:
            outcomes[f.outcome] = outcomes.get(f.outcome, 0) + 1
        clear = [f.min_clearance_m for f in self.flights if f.min_clearance_m is not None]
        # RSS growth from the first sample after the first flight (imports, planner and zenoh warmed up).
        warm = [r for r in rows if r["flights"] >= 1 and r["rss_mb"] is not None] or [
            r for r in rows if r["rss_mb"] is not None
        ]
        # Latency drift over whole intervals only (the last row is whatever was left when the flights ended).
        lat_rows = [r for r in rows if r["lat_p99_ms"] is not None and r["dt_s"] >= 0.5 * self.args.interval]
        return {
            "machine": f"{platform.machine()}, {os.cpu_count()} CPUs, Python {platform.python_version()}",
            "wall_s": wall_s,
            "speedup": self.args.speedup,
            "link_faults": None if self.faults is None else str(self.faults),
            "flights": len(self.flights),
            "outcomes": outcomes,
            "lowest_clearance_m": min(clear) if clear else None,
            "rss_mb_first": warm[0]["rss_mb"] if warm else None,
            "rss_mb_last": warm[-1]["rss_mb"] if warm else None,
            "rss_mb_max": max(r["rss_mb"] for r in warm) if warm else None,
            "rss_slope_mb_per_h": _slope([r["t_s"] for r in warm], [r["rss_mb"] for r in warm], 3600.0),
            "lat_first": None if not lat_rows else [lat_rows[0]["lat_p50_ms"], lat_rows[0]["lat_p99_ms"]],
            "lat_last": None if not lat_rows else [lat_rows[-1]["lat_p50_ms"], lat_rows[-1]["lat_p99_ms"]],
            "lat_p99_slope_ms_per_h": _slope([r["t_s"] for r in lat_rows], [r["lat_p99_ms"] for r in lat_rows], 3600.0),
            "service_result": result,
            "intervals": rows,
            "flight_records": [dataclasses.asdict(f) for f in self.flights],
        }


def _slope(t: list[float], y: list[float], per: float) -> float | None:
    """Least-squares slope of y over t, per ``per`` seconds (None with fewer than 3 points)."""
    if len(t) < 3:
        return None
    tt, yy = np.asarray(t, dtype=np.float64), np.asarray(y, dtype=np.float64)
    if np.ptp(tt) <= 0.0:
        return None
    return float(np.polyfit(tt, yy, 1)[0] * per)


def _fmt(v: float | None, spec: str) -> str:
    return "n/a" if v is None else format(v, spec)


def _print_row(row: dict[str, Any], *, header: bool) -> None:
    if header:
        print(
            f"{'t [s]':>7s} {'flights':>7s} {'RSS [MB]':>8s} {'lat n':>6s} {'p50 [ms]':>8s} {'p99 [ms]':>8s} "
            f"{'setpts':>7s} {'poses':>6s} {'scans':>6s} {'goals':>5s} {'stale':>5s} {'bad':>4s}"
        )
    d = row["delta"]
    bad = sum(v for k, v in d.items() if k.startswith("bad_") or k == "foreign_messages")
    print(
        f"{row['t_s']:7.1f} {row['flights']:7d} {_fmt(row['rss_mb'], '8.2f')} {row['lat_n']:6d} "
        f"{_fmt(row['lat_p50_ms'], '8.3f')} {_fmt(row['lat_p99_ms'], '8.3f')} "
        f"{d.get('setpoints_sent', 0):7d} {d.get('poses', 0):6d} {d.get('scans', 0):6d} {d.get('goals', 0):5d} "
        f"{d.get('stale_poses', 0):5d} {bad:4d}",
        flush=True,
    )


def _print_summary(s: dict[str, Any]) -> None:
    print(f"\nsoak: {s['wall_s'] / 60.0:.1f} min wall, speed-up {s['speedup']}, link faults {s['link_faults']}")
    print(f"machine: {s['machine']}")
    print(
        f"flights: {s['flights']}  outcomes: {s['outcomes']}  "
        f"lowest clearance: {_fmt(s['lowest_clearance_m'], '.3f')} m"
    )
    print(
        f"RSS: {_fmt(s['rss_mb_first'], '.2f')} MB after the first flight -> "
        f"{_fmt(s['rss_mb_last'], '.2f')} MB at the end "
        f"(growth {_fmt(None if s['rss_mb_first'] is None else s['rss_mb_last'] - s['rss_mb_first'], '+.2f')} MB, "
        f"max {_fmt(s['rss_mb_max'], '.2f')} MB, slope {_fmt(s['rss_slope_mb_per_h'], '+.2f')} MB/h)"
    )
    if s["lat_first"] is not None:
        (a50, a99), (b50, b99) = s["lat_first"], s["lat_last"]
        print(
            f"loop latency: first interval p50 {a50:.3f} / p99 {a99:.3f} ms, last interval p50 {b50:.3f} / "
            f"p99 {b99:.3f} ms (p99 slope {_fmt(s['lat_p99_slope_ms_per_h'], '+.3f')} ms/h)"
        )
    res = s["service_result"]
    if res:
        print(
            f"service result: outcome {res.get('outcome')}, latency p50 {res.get('latency_ms_p50')} ms, "
            f"p99 {res.get('latency_ms_p99')} ms over the run"
        )
        print("counters: " + ", ".join(f"{k}={v}" for k, v in sorted((res.get("counters") or {}).items())))


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--minutes", type=float, default=5.0, help="wall minutes of flights (default 5)")
    p.add_argument("--interval", type=float, default=30.0, help="sampling interval [wall s] (default 30)")
    p.add_argument("--speedup", type=float, default=5.0, help="simulated s per wall s (default 5)")
    p.add_argument("--max-flight", type=float, default=240.0, help="give a flight up after this [simulated s]")
    p.add_argument("--link-faults", help="sim.linkfaults spec, e.g. loss=0.1,jitter=0.05 (default none)")
    p.add_argument("--seed", type=int, default=0, help="seed of worlds, starts, goals and faults")
    p.add_argument("--out", type=Path, help="keep logs and the summary JSON here (default: a temp dir)")
    p.add_argument("--tlogs", action="store_true", help="record vehicle.tlog per flight and the service's tlog")
    args = p.parse_args(argv)
    if args.link_faults:
        LinkFaults.parse(args.link_faults)  # a typo fails here, not after the service started
    with tempfile.TemporaryDirectory(prefix="apf-soak-") as tmp:
        workdir = args.out or Path(tmp)
        if workdir.exists() and any(workdir.iterdir()):
            p.error(f"--out {workdir} is not empty")
        workdir.mkdir(parents=True, exist_ok=True)
        summary = asyncio.run(Soak(args, workdir).run())
        (workdir / "soak.json").write_text(json.dumps(summary, indent=2, default=str) + "\n")
        _print_summary(summary)
    return 0


if __name__ == "__main__":
    sys.exit(main())
