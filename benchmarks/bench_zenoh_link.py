"""ZenohLink one-way latency on loopback: publish on one peer -> asyncio consumer on the other.

Two peer sessions in one process (tcp/127.0.0.1, free port). Each sample carries a 72-range
``apf.range_scan/1`` JSON scan; we report the time from ``publish`` to the zenoh callback (``sample.t_s``)
and to the moment the asyncio consumer has the sample, plus the time to decode it into a RangeScan.
Run: ``OPENBLAS_NUM_THREADS=1 python benchmarks/bench_zenoh_link.py [--count N] [--period-ms P]``.
"""

from __future__ import annotations

import argparse
import asyncio
import math
import os
import platform
import socket
import time

import numpy as np

from apf_companion.links.zenoh import DEFAULT_SENSOR_KEY, Overflow, ZenohConfig, ZenohLink
from apf_companion.perception import RangeScan, ScanFrame, decode_scan_payload, encode_scan_json


def _free_port() -> int:
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


async def run(count: int, period_s: float) -> None:
    port = _free_port()
    rx = await ZenohLink.open(ZenohConfig(mode="peer", listen=(f"tcp/127.0.0.1:{port}",)))
    tx = await ZenohLink.open(ZenohConfig(mode="peer", connect=(f"tcp/127.0.0.1:{port}",)))
    scan = RangeScan(
        t_s=0.0,
        frame=ScanFrame.BODY_FRD,
        bearings_rad=np.linspace(-math.pi, math.pi, 72, endpoint=False),
        ranges_m=np.random.default_rng(0).uniform(0.5, 11.0, 72),
        range_min_m=0.2,
        range_max_m=12.0,
    )
    payload = encode_scan_json(scan)
    try:
        sub = await rx.subscribe(DEFAULT_SENSOR_KEY, overflow=Overflow.FIFO, capacity=4)
        for _ in range(500):  # wait for the peers to connect
            tx.publish(DEFAULT_SENSOR_KEY, payload)
            try:
                await sub.recv(timeout=0.02)
                break
            except TimeoutError:
                continue
        while sub.try_recv() is not None:
            pass
        to_callback = np.empty(count)
        to_loop = np.empty(count)
        decode = np.empty(count)
        for i in range(count):
            t0 = time.monotonic()
            tx.publish(DEFAULT_SENSOR_KEY, payload, encoding="application/json")
            sample = await sub.recv(timeout=2.0)
            t1 = time.monotonic()
            decode_scan_payload(sample.payload, sample.encoding, t_s=sample.t_s)
            t2 = time.monotonic()
            to_callback[i], to_loop[i], decode[i] = sample.t_s - t0, t1 - t0, t2 - t1
            await asyncio.sleep(period_s)
        print(f"machine: {platform.machine()} cpus={os.cpu_count()} python {platform.python_version()}")
        print(f"samples={count} period={period_s * 1e3:.1f} ms payload={len(payload)} B (72-range JSON scan)")
        print(f"{'stage':<34} {'p50 us':>8} {'p99 us':>8} {'max us':>8}")
        for name, arr in (
            ("publish -> zenoh callback", to_callback),
            ("publish -> asyncio consumer", to_loop),
            ("decode_scan_payload (JSON, 72)", decode),
        ):
            us = arr * 1e6
            print(f"{name:<34} {np.median(us):8.0f} {np.percentile(us, 99):8.0f} {us.max():8.0f}")
        print(f"subscription stats: {sub.stats}")
    finally:
        await tx.aclose()
        await rx.aclose()


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--count", type=int, default=2000)
    parser.add_argument("--period-ms", type=float, default=2.0)
    args = parser.parse_args()
    asyncio.run(run(args.count, args.period_ms / 1000.0))


if __name__ == "__main__":
    main()
