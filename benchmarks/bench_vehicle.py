"""Simulator speed: simulated seconds per wall second for a 60 s flight with the range sensor at 10 Hz.

The vehicle flies a zig-zag through the paper's random field (reference preset, 40 point obstacles) for 60
simulated seconds, steered by position+velocity setpoints injected at 10 Hz (as a companion would send them).
Physics at 100 Hz; all default telemetry plus OBSTACLE_DISTANCE go out over a real UDP socket to a local sink.
Printed: the pure engine (no sockets), the full simulator with one link, and with every sensor message on.
Target: >= 20x real time.

    python benchmarks/bench_vehicle.py
"""

from __future__ import annotations

import asyncio
import math
import os
import socket
import threading
import time
from typing import Any

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import numpy as np
from pymavlink.dialects.v20 import ardupilotmega as m

from apf_companion.autopilot import MASK_POS_VEL
from sim.vehicle import EngineConfig, RangeSensorConfig, SimConfig, Simulator, SpawnConfig, VehicleEngine
from sim.world import World, paper_field

FLIGHT_S = 60.0
WAYPOINTS = np.array([[22.0, 4.0], [22.0, 10.0], [4.0, 10.0], [4.0, 16.0], [22.0, 16.0], [22.0, 22.0], [3.0, 3.0]])
GCS = m.MAVLink(None, srcSystem=42, srcComponent=191)


def world() -> World:
    """The reference field, minus obstacles within 1 m of the zig-zag (the pilot flies blind, straight lines)."""
    field = paper_field("reference", 60, np.random.default_rng(7), radius_m=0.0)
    a, b = WAYPOINTS[:-1], WAYPOINTS[1:]
    p = field.circles_ne_m
    ab = b - a
    t = np.clip(np.einsum("skd,sd->sk", p[None, :, :] - a[:, None, :], ab) / np.sum(ab**2, axis=1)[:, None], 0, 1)
    foot = a[:, None, :] + t[..., None] * ab[:, None, :]
    keep = np.hypot(*(foot - p[None]).transpose(2, 0, 1)).min(axis=0) > 1.0
    return World.from_obstacles(p[keep][:40], 0.0, name="bench-field")


class Pilot:
    """A 10 Hz companion stand-in: one position+velocity setpoint per sensor scan, along the waypoints."""

    def __init__(self, engine: VehicleEngine) -> None:
        self.engine = engine
        self.leg = 0

    def __call__(self, scan: Any) -> None:
        pos = self.engine.state.pos_ned_m
        goal = WAYPOINTS[self.leg % len(WAYPOINTS)]
        if float(np.hypot(*(goal - pos[:2]))) < 0.5:
            self.leg += 1
            goal = WAYPOINTS[self.leg % len(WAYPOINTS)]
        d = goal - pos[:2]
        dist = float(np.hypot(*d))
        step = d / dist * min(0.4, dist) if dist > 0 else d
        vel = d / dist * 2.0 if dist > 0.5 else np.zeros(2)
        msg = GCS.set_position_target_local_ned_encode(
            0, 1, 1, 1, MASK_POS_VEL, pos[0] + step[0], pos[1] + step[1], -5.0, vel[0], vel[1], 0.0, 0, 0, 0, 0, 0
        )
        self.engine.handle(GCS.decode(bytearray(msg.pack(GCS))), 0)


def bench_engine() -> float:
    engine = VehicleEngine(
        EngineConfig(world=world(), spawn=SpawnConfig(airborne=True, alt_m=5.0)), n_links=1, emit=lambda lk, msg: None
    )
    engine.scan_listeners.append(Pilot(engine))
    t0 = time.perf_counter()
    while engine.t_s < FLIGHT_S:
        engine.step()
    return FLIGHT_S / (time.perf_counter() - t0)


class _Sink:
    """A UDP receiver on its own thread (so it never competes with the simulator's event loop for reads)."""

    def __init__(self) -> None:
        self.sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self.sock.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 1 << 22)
        self.sock.bind(("127.0.0.1", 0))
        self.sock.settimeout(0.2)
        self.port = int(self.sock.getsockname()[1])
        self.packets = 0
        self.bytes = 0
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, daemon=True)
        self._thread.start()

    def _run(self) -> None:
        while not self._stop.is_set():
            try:
                data = self.sock.recv(65536)
            except TimeoutError:
                continue
            self.packets += 1
            self.bytes += len(data)

    def close(self) -> None:
        self._stop.set()
        self._thread.join()
        self.sock.close()


async def bench_simulator(messages: frozenset[str]) -> tuple[float, int, int, float, bool]:
    sink = _Sink()
    port = sink.port
    try:
        sim = await Simulator.start(
            SimConfig(
                links=[f"udpout:127.0.0.1:{port}"],
                world=world(),
                speedup=math.inf,
                spawn=SpawnConfig(airborne=True, alt_m=5.0),
                sensor=RangeSensorConfig(messages=messages),
                unasked_streams=True,  # the full telemetry load, as measured before streams waited to be asked
            )
        )
        sim.engine.scan_listeners.append(Pilot(sim.engine))
        t0 = time.perf_counter()
        while sim.t_s < FLIGHT_S:
            await asyncio.sleep(0.01)
        wall = time.perf_counter() - t0
        sim_s = sim.t_s
        res = sim.result()
        await sim.aclose()
        await asyncio.sleep(0.3)
        return sim_s / wall, sink.packets, sink.bytes, float(res["path_length_m"]), bool(res["crashed"])
    finally:
        sink.close()


def main() -> None:
    print(f"bench_vehicle: {FLIGHT_S:.0f} s simulated flight, physics 100 Hz, range sensor 10 Hz, 40 obstacles")
    print(f"  pure engine (no sockets):            {bench_engine():7.1f} x real time")
    for label, kinds in (
        ("simulator, UDP link, OBSTACLE_DISTANCE", frozenset({"obstacle_distance"})),
        (
            "simulator, UDP link, all 3 sensor msgs",
            frozenset({"obstacle_distance", "distance_sensor", "obstacle_distance_3d"}),
        ),
    ):
        ratio, packets, nbytes, path, crashed = asyncio.run(bench_simulator(kinds))
        print(
            f"  {label}: {ratio:7.1f} x real time  ({packets / FLIGHT_S:.0f} msgs and "
            f"{nbytes / FLIGHT_S / 1000:.1f} kB received per simulated s; flew {path:.0f} m"
            f"{', CRASHED' if crashed else ''})"
        )
    print("  target: >= 20 x real time")


if __name__ == "__main__":
    main()
