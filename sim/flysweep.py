"""apf-sim fly --trials N: flights of seeds SEED..SEED+N-1, their outcome rates with Wilson intervals, the
link-fault summary, and (on paper fields) the study's engine on the same fields for comparison."""

from __future__ import annotations

import asyncio
import dataclasses
import json
import math
import sys
import time
from typing import Any

import numpy as np
import numpy.typing as npt

from apf_companion.errors import ApfCompanionError
from sim.fly import OUTCOMES, FlyOptions, clearance_flown, flown_world, fly, read_json, study_same_worlds
from sim.study.metrics import wilson_interval

__all__ = ["flight_densities", "fly_trials"]


def _sweep_loop(
    base: FlyOptions, trials: int, records: list[dict[str, Any]], fields: list[npt.NDArray[np.float64]]
) -> None:
    from sim.study.cli import eta_text

    densities = flight_densities(base)
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
            fields.append(flown_world(opt, read_json(opt.out / "sim_result.json")))
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


def flight_densities(opt: FlyOptions) -> list[str]:
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


def fly_trials(base: FlyOptions, trials: int, study_reps: int = 0) -> int:
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
