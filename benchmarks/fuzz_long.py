"""Long fuzz run (issue 9, not in CI): N hostile frames over loopback UDP into one real service.

The harness is tests/service/fuzzing.py (the CI version, a few thousand frames, is
tests/service/test_service_fuzz.py): one socket plays the autopilot, a genuine 20 Hz stream with hostile frames
from ``GENERATORS`` interleaved (chosen uniformly, seeded); every setpoint the service sends is checked against the
genuine position. Prints frames/s, the frames per generator, the service's counters and rejected totals, escaped
exceptions (``handler_errors`` and their kinds, send errors) and setpoints that were not finite or not plausible.

Usage: nice -n 10 python benchmarks/fuzz_long.py --frames 1000000 [--seed 0] [--json out.json]
Exit status 1 if the service died, an exception escaped a handler or a bad setpoint was sent.
"""

from __future__ import annotations

import argparse
import asyncio
import dataclasses
import json
import random
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

from tests.service.fuzzing import FuzzReport, choose_kinds, run_fuzz


def _progress(r: FuzzReport) -> None:
    print(f"{r.frames:>9} frames  {r.frames_per_s:7.0f} frames/s", flush=True)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--frames", type=int, default=100_000)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--rate", type=float, default=None, help="hostile frames per second (default: as fast as read)")
    ap.add_argument("--json", type=Path, default=None, help="write the report here")
    args = ap.parse_args(argv)
    rng = random.Random(args.seed)
    kinds = choose_kinds(rng, args.frames)
    report = asyncio.run(run_fuzz(kinds, rng, progress=_progress, rate_hz=args.rate))
    print(f"frames {report.frames} in {report.wall_s:.1f} s: {report.frames_per_s:.0f} frames/s")
    print("per generator:", json.dumps(report.by_generator, sort_keys=True))
    print(f"service alive: {report.alive}; goals given by the harness: {report.goals_given}")
    print(f"escaped exceptions (handler_errors): {report.handler_errors} {report.fault_kinds}")
    print(f"send errors: {report.send_errors}")
    nav = report.counters
    print(
        f"cycles {nav.get('nav_cycles', 0)}: planner steps {nav.get('nav_planner_steps', 0)}, unconfirmed pose "
        f"{nav.get('nav_unconfirmed_pose_cycles', 0)}, stale pose {nav.get('nav_stale_pose_cycles', 0)}"
    )
    print(f"setpoints: {report.setpoints} (brakes {report.brakes}); bad setpoints: {len(report.bad_setpoints)}")
    for line in report.bad_setpoints[:20]:
        print("  ", line)
    print("rejected (status / NAMED_VALUE_INT):", report.rejected, "received:", report.named_int)
    print("counters:", json.dumps({k: v for k, v in report.counters.items() if v}, sort_keys=True))
    if args.json is not None:
        args.json.write_text(json.dumps(dataclasses.asdict(report), indent=1) + "\n")
    ok = report.alive and report.handler_errors == 0 and report.send_errors == 0 and not report.bad_setpoints
    return 0 if ok else 1


if __name__ == "__main__":
    raise SystemExit(main())
