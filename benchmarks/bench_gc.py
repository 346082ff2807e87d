"""The collector's full-collection pause in the service process, before and after ``heap.freeze_startup_heap``.

Run: ``python benchmarks/bench_gc.py [--repeats 5]``. Builds the service as ``apf-companion run`` does (the
default configuration, the planner, the perception front end, the navigator; no links are opened), then times
``gc.collect()`` (a full, oldest-generation collection: what CPython runs now and then on its own, stopping the
process) with the startup heap tracked, and again after freezing it. Prints the tracked object counts and the
median and longest pause of each.
"""

from __future__ import annotations

import argparse
import gc
import os
import platform
import statistics
import time

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

from apf_companion.config import ServiceConfig
from apf_companion.heap import freeze_startup_heap
from apf_companion.service import CompanionService


def pauses_ms(repeats: int) -> list[float]:
    out = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        gc.collect()
        out.append((time.perf_counter() - t0) * 1000.0)
    return out


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0] if __doc__ else None)
    parser.add_argument("--repeats", type=int, default=5, help="full collections timed in each state (default 5)")
    args = parser.parse_args(argv)
    svc = CompanionService(ServiceConfig(), observers=[])
    print(f"python {platform.python_version()}, {platform.machine()}, {os.cpu_count()} cpus")
    print(f"load average {' '.join(f'{x:.2f}' for x in os.getloadavg())}\n")
    print("| heap | tracked objects | full collection, median (ms) | longest (ms) |")
    print("|---|---|---|---|")
    before = pauses_ms(args.repeats)
    tracked = len(gc.get_objects())
    print(f"| startup heap tracked | {tracked} | {statistics.median(before):.2f} | {max(before):.2f} |")
    frozen = freeze_startup_heap()
    after = pauses_ms(args.repeats)
    tracked = len(gc.get_objects())
    print(f"| frozen ({frozen} objects) | {tracked} | {statistics.median(after):.3f} | {max(after):.3f} |")
    del svc
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
