"""``apf-sim study``: the paper's Monte Carlo study (Diab et al., IEEE Aerospace 2023, Table II).

Runs every (planner, density) cell as fixed seeded chunks of lockstep trials on all cores, prints a markdown
table beside the paper's values, and optionally writes JSON, per-trial CSV and figures.
"""

from __future__ import annotations

import argparse
import dataclasses
import sys
import time
from pathlib import Path
from typing import TYPE_CHECKING, TextIO

from apf_companion.errors import ConfigError
from apf_companion.planning import ALL_PLANNER_NAMES, AbapfRule
from sim.extras import require
from sim.study.config import (
    DEFAULT_DENSITIES,
    PRESET_NAMES,
    Density,
    ObstacleSampling,
    StudyConfig,
    check_planner_names,
    mu_sweep_grid,
)

if TYPE_CHECKING:
    from sim.study.engine import CellResult
    from sim.study.worldstudy import WorldCase, WorldCell

MU_SWEEP_PLANNERS = ("bapf", "cr-bapf*")


class ProgressBar:
    """A small progress bar on a text stream: redrawn in place on a terminal, every 10 % otherwise."""

    def __init__(self, stream: TextIO, label: str = "study", width: int = 30) -> None:
        self._stream = stream
        self._label = label
        self._width = width
        self._t0 = time.monotonic()
        self._tty = stream.isatty()
        self._last_decile = -1

    def __call__(self, done: int, total: int) -> None:
        frac = done / total if total else 1.0
        if not self._tty:
            decile = int(frac * 10)
            if decile == self._last_decile:
                return
            self._last_decile = decile
        filled = round(frac * self._width)
        elapsed = time.monotonic() - self._t0
        text = (
            f"{self._label} [{'#' * filled}{'.' * (self._width - filled)}] "
            f"{done}/{total} trials {100 * frac:5.1f}% {elapsed:6.1f} s{eta_text(done, total, elapsed)}"
        )
        if self._tty:
            self._stream.write("\r" + text + ("\n" if done >= total else ""))
        else:
            self._stream.write(text + "\n")
        self._stream.flush()


def eta_text(done: int, total: int, elapsed_s: float) -> str:
    """`` ETA 12 s`` from the rate so far (empty before the first result and once done)."""
    if done <= 0 or done >= total:
        return ""
    remaining_s = elapsed_s * (total - done) / done
    return f" ETA {remaining_s:.0f} s" if remaining_s < 120 else f" ETA {remaining_s / 60:.1f} min"


def _planners(text: str) -> tuple[str, ...]:
    return check_planner_names(tuple(p.strip() for p in text.split(",") if p.strip()))


def _densities(text: str) -> tuple[Density, ...]:
    return tuple(Density.parse(p) for p in text.split(",") if p.strip())


def register(subparsers: argparse._SubParsersAction) -> None:  # type: ignore[type-arg]
    """Add ``study`` to ``apf-sim``."""
    p = subparsers.add_parser("study", help="the paper's Monte Carlo study", description=__doc__)
    _add_field_options(p)
    _add_execution_options(p)
    _add_model_options(p)
    _add_output_options(p)
    _register_worlds(p)
    p.set_defaults(func=run)


def _add_field_options(p: argparse.ArgumentParser) -> None:
    """What the random-field study runs: preset, trials, densities, planners, seed."""
    p.add_argument(
        "--preset",
        choices=PRESET_NAMES,
        default="reference",
        help="reference = the authors' code (default), paper = the paper's text",
    )
    p.add_argument("--trials", type=int, default=4000, help="trials per planner and density (default 4000)")
    p.add_argument(
        "--densities",
        default=",".join(d.label for d in DEFAULT_DENSITIES),
        help="obstacle-count ranges N_l-N_u, comma separated (default 20-45,45-70,70-95)",
    )
    p.add_argument(
        "--planners",
        default=",".join(ALL_PLANNER_NAMES),
        help=f"comma-separated planners (default all: {','.join(ALL_PLANNER_NAMES)}; the last two are the product "
        "planner and the BendyRuler-style baseline, which the paper does not have)",
    )
    p.add_argument("--seed", type=int, default=0, help="root seed (default 0)")


def _add_execution_options(p: argparse.ArgumentParser) -> None:
    """Where the trials run: worker processes, Dask, chunk size."""
    p.add_argument(
        "--workers", type=int, default=None, help="worker processes (default: all cores; 1 = run in this process)"
    )
    p.add_argument(
        "--dask",
        metavar="local|ADDRESS",
        default=None,
        help="run the chunks on Dask: 'local' starts a cluster of --workers processes on 127.0.0.1, an address "
        "(tcp://HOST:8786) uses a running scheduler; same seed, same table (needs apf-companion[dask])",
    )
    p.add_argument(
        "--chunk-trials",
        type=int,
        default=None,
        help="trials per seeded chunk (default 500; part of the random-stream layout)",
    )


def _add_model_options(p: argparse.ArgumentParser) -> None:
    """Variants of the study's model: obstacle sampling, noise, the A-BAPF rule, the mu_o sweep."""
    p.add_argument(
        "--obstacles",
        choices=[s.value for s in ObstacleSampling],
        default=None,
        help="obstacle coordinates: continuous (default, both presets) or integer (the authors' README example "
        "randi([5 20], [N, 2]); repeated points count once)",
    )
    p.add_argument(
        "--noise-std",
        "--noise",
        dest="noise_std",
        type=float,
        default=None,
        metavar="M",
        help="actuation (position) noise N(0, M^2) per axis added on every move [m] (default 0.1, the paper's; "
        "0 = noise-free); --noise is the same option under another name, for random fields and --world alike",
    )
    p.add_argument(
        "--abapf-rule",
        choices=[r.value for r in AbapfRule],
        default=None,
        help="A-BAPF mu_o,k rule: exact (default: always mu_max, so A-BAPF equals BAPF at mu_o = mu_max) or "
        "paper (the float64-tie rule that reproduces the paper's mu_o,k figure)",
    )
    p.add_argument(
        "--mu-sweep",
        action="store_true",
        help="also run BAPF and CR-BAPF* over mu_o = 1000 k / 12, k = 0..12 (1 for k = 0)",
    )
    p.add_argument(
        "--mu-trials", type=int, default=1000, help="trials per planner, density and mu_o of the sweep (default 1000)"
    )


def _add_output_options(p: argparse.ArgumentParser) -> None:
    """What gets written: JSON summary, CSV records, figures, the progress bar."""
    p.add_argument("--json", type=Path, default=None, metavar="PATH", help="write the summary as JSON")
    p.add_argument("--csv", type=Path, default=None, metavar="PATH", help="write per-trial records as CSV")
    p.add_argument(
        "--plots",
        type=Path,
        default=None,
        metavar="DIR",
        help="write the figures (PNG) here (with --world: each world, its A* path and one run per planner)",
    )
    p.add_argument("--no-progress", action="store_true", help="no progress bar on stderr")


def _register_worlds(p: argparse.ArgumentParser) -> None:
    """The study over world files and the full-knowledge optimum (sim/study/worldstudy.py, optimal.py)."""
    p.add_argument(
        "--world",
        action="append",
        default=None,
        metavar="FILE|NAME",
        help="run the planners over this world file or bundled world instead of the random fields (repeatable; "
        "--trials per planner and world); walls and cylinders are seen as surface samples, collisions are "
        "judged on the true geometry",
    )
    p.add_argument(
        "--no-area",
        action="store_true",
        help="leave out the world files' flying areas (area_ne_m): bapf-nav's grid then moves with the agent",
    )
    p.add_argument(
        "--surface-spacing",
        type=float,
        default=None,
        metavar="M",
        help="spacing of the surface samples the planners see on world files [m] (default 0.2, the perception "
        "memory's merge radius)",
    )
    p.add_argument(
        "--optimum",
        action="store_true",
        help="random fields: also compute the full-knowledge grid optimum on a sample of fields and print each "
        "planner's mean path beside it (world files always get it)",
    )
    p.add_argument(
        "--optimum-fields", type=int, default=100, metavar="K", help="fields per density for --optimum (default 100)"
    )
    p.add_argument(
        "--optimum-clearance",
        type=float,
        default=None,
        metavar="M",
        help="clearance the optimum keeps from the true obstacles [m] (default 0.35 = collision radius 0.25 + 0.1)",
    )
    p.add_argument(
        "--optimum-resolution",
        type=float,
        default=None,
        metavar="M",
        help="optimum grid resolution [m] (default 0.1 on worlds, 0.2 on random fields)",
    )


def run(args: argparse.Namespace) -> int:
    """Run the study from parsed arguments; returns the exit code."""
    try:
        return _run(args)
    except ConfigError as err:
        print(f"apf-sim study: {err}", file=sys.stderr)
        return 2


def _config(args: argparse.Namespace) -> StudyConfig:
    """The preset's StudyConfig with the command line's overrides."""
    config = StudyConfig.from_preset(args.preset)
    if args.chunk_trials is not None:
        config = dataclasses.replace(config, chunk_trials=args.chunk_trials)
    if args.obstacles is not None:
        config = dataclasses.replace(config, obstacle_sampling=ObstacleSampling(args.obstacles))
    if args.noise_std is not None:
        if not args.noise_std >= 0:
            raise ConfigError(f"--noise-std/--noise: need >= 0, got {args.noise_std}")
        config = dataclasses.replace(config, noise_std_m=args.noise_std)
    if args.abapf_rule is not None:
        params = dataclasses.replace(config.planner_params, abapf_rule=AbapfRule(args.abapf_rule))
        config = dataclasses.replace(config, planner_params=params)
    return config


def _run(args: argparse.Namespace) -> int:
    from sim.study.engine import collect_cells, make_tasks, run_tasks
    from sim.study.executors import study_executor

    config = _config(args)
    planners = _planners(args.planners)
    if args.plots is not None:
        require("--plots", "matplotlib")  # before the study, not after it
    if args.world:
        return _run_worlds(args, config, planners)
    densities = _densities(args.densities)
    if args.trials < 1 or args.mu_trials < 1:
        raise ConfigError(f"--trials/--mu-trials: need >= 1, got {args.trials}/{args.mu_trials}")
    if args.workers is not None and args.workers < 1:
        raise ConfigError(f"--workers: need >= 1, got {args.workers}")

    tasks = make_tasks(config, planners, densities, args.trials, args.seed)
    sweep_spans: list[tuple[float, int, int]] = []
    all_tasks = list(tasks)
    if args.mu_sweep:
        for mu in mu_sweep_grid():
            sweep = make_tasks(config.with_mu_o(mu), MU_SWEEP_PLANNERS, densities, args.mu_trials, args.seed)
            sweep_spans.append((mu, len(all_tasks), len(all_tasks) + len(sweep)))
            all_tasks.extend(sweep)

    with study_executor(args.dask, args.workers) as (executor, ran_on):
        progress = None if args.no_progress else ProgressBar(sys.stderr)
        t0 = time.perf_counter()
        results = run_tasks(all_tasks, executor, progress=progress)
        wall_s = time.perf_counter() - t0
    workers = ran_on.workers

    cells = collect_cells(results[: len(tasks)])
    sweep_cells = [(mu, collect_cells(results[a:b])) for mu, a, b in sweep_spans]
    n_trials = sum(t.n_trials for t in all_tasks)
    _print_fields(args, config, cells, sweep_cells, n_trials, wall_s, ran_on.describe())
    if args.optimum:
        _print_field_optimum(args, config, cells, densities, workers)
    _write_fields(args, config, cells, sweep_cells, densities, wall_s, workers)
    return 0


def _print_fields(
    args: argparse.Namespace,
    config: StudyConfig,
    cells: list[CellResult],
    sweep_cells: list[tuple[float, list[CellResult]]],
    n_trials: int,
    wall_s: float,
    ran_on: str,
) -> None:
    """The random-field study's Markdown tables and its one-line run summary."""
    from sim.study.report import markdown_table

    variant = "" if config.obstacle_sampling is ObstacleSampling.CONTINUOUS else ", integer obstacle coordinates"
    if args.noise_std is not None:
        variant += f", noise std {config.noise_std_m:g} m"
    print(f"## apf-sim study: preset {config.preset}{variant}, seed {args.seed}, {args.trials} trials per cell\n")
    print(markdown_table(cells))
    if sweep_cells:
        print(f"\n### R_s versus mu_o ({args.mu_trials} trials per point)\n")
        print(_sweep_table(sweep_cells))
    print(
        f"\n{n_trials} trials in {wall_s:.1f} s wall clock with {ran_on} "
        f"({n_trials / wall_s:.0f} trials/s). M_s and S over successful trials; T_a = chunk wall time / "
        "chunk trials (amortised, lockstep)."
    )


def _write_fields(
    args: argparse.Namespace,
    config: StudyConfig,
    cells: list[CellResult],
    sweep_cells: list[tuple[float, list[CellResult]]],
    densities: tuple[Density, ...],
    wall_s: float,
    workers: int,
) -> None:
    """The random-field study's --json, --csv and --plots files."""
    from sim.study.report import study_json, write_csv, write_json

    if args.json is not None:
        doc = study_json(
            config,
            cells,
            seed=args.seed,
            trials=args.trials,
            wall_s=wall_s,
            workers=workers,
            mu_sweep=sweep_cells,
        )
        write_json(args.json, doc)
    if args.csv is not None:
        write_csv(args.csv, cells)
    if args.plots is not None:
        _write_plots(args.plots, config, cells, sweep_cells, densities, args.seed)


def _optimum_kwargs(args: argparse.Namespace, *, fields: bool = False) -> dict[str, float]:
    from sim.study.optimal import DEFAULT_CLEARANCE_M, DEFAULT_RESOLUTION_M, FIELD_RESOLUTION_M

    clearance = DEFAULT_CLEARANCE_M if args.optimum_clearance is None else args.optimum_clearance
    default_resolution = FIELD_RESOLUTION_M if fields else DEFAULT_RESOLUTION_M
    resolution = default_resolution if args.optimum_resolution is None else args.optimum_resolution
    if not (clearance >= 0 and resolution > 0):
        raise ConfigError(f"--optimum-clearance/--optimum-resolution: need >= 0 and > 0, got {clearance}, {resolution}")
    return {"clearance_m": clearance, "resolution_m": resolution}


def _print_field_optimum(
    args: argparse.Namespace, config: StudyConfig, cells: list[CellResult], densities: tuple[Density, ...], workers: int
) -> None:
    from sim.study.engine import map_tasks
    from sim.study.fieldoptimum import collect_optima, field_optimum_table, field_optimum_tasks, run_field_optimum

    if args.optimum_fields < 1:
        raise ConfigError(f"--optimum-fields: need >= 1, got {args.optimum_fields}")
    kw = _optimum_kwargs(args, fields=True)
    tasks = field_optimum_tasks(
        config,
        densities,
        args.optimum_fields,
        args.trials,
        args.seed,
        clearance_m=kw["clearance_m"],
        resolution_m=kw["resolution_m"],
    )
    t0 = time.perf_counter()
    results = map_tasks(run_field_optimum, tasks, workers=workers)
    wall_s = time.perf_counter() - t0
    optima = collect_optima(tasks, results)
    n = min(args.optimum_fields, args.trials)
    print(
        f"\n### Full-knowledge grid optimum (clearance {kw['clearance_m']} m, grid {kw['resolution_m']} m, first {n} "
        f"fields per density, {wall_s:.1f} s)\n"
    )
    print(field_optimum_table(cells, optima, config.goal_radius_m))


def _world_spacing(args: argparse.Namespace, config: StudyConfig) -> float:
    """Check the --world run's options; the surface-sample spacing [m]."""
    from sim.world.geometry import SURFACE_SPACING_M

    if args.mu_sweep or args.csv is not None:
        raise ConfigError("--world: --mu-sweep and --csv are for the random fields; use --json")
    if config.dim != 2:
        raise ConfigError("--world: world files are 2D")
    if args.trials < 1:
        raise ConfigError(f"--trials: need >= 1, got {args.trials}")
    if args.workers is not None and args.workers < 1:
        raise ConfigError(f"--workers: need >= 1, got {args.workers}")
    spacing = SURFACE_SPACING_M if args.surface_spacing is None else args.surface_spacing
    if not spacing > 0:
        raise ConfigError(f"--surface-spacing: need > 0, got {spacing}")
    return spacing


def _run_worlds(args: argparse.Namespace, config: StudyConfig, planners: tuple[str, ...]) -> int:
    from sim.study.executors import study_executor
    from sim.study.worldstudy import load_case, run_world_study, without_area, world_table

    spacing = _world_spacing(args, config)
    kw = _optimum_kwargs(args)
    cases = [
        load_case(w, spacing_m=spacing, optimum_clearance_m=kw["clearance_m"], optimum_resolution_m=kw["resolution_m"])
        for w in args.world
    ]
    if args.no_area:
        cases = [without_area(c) for c in cases]
    labels = [c.label for c in cases]
    if len(set(labels)) != len(labels):
        raise ConfigError(f"--world: each world needs its own name (file stem), got {labels}")
    progress = None if args.no_progress else ProgressBar(sys.stderr)
    t0 = time.perf_counter()
    with study_executor(args.dask, args.workers) as (executor, ran_on):
        cells = run_world_study(config, planners, cases, args.trials, args.seed, executor, progress=progress)
    wall_s = time.perf_counter() - t0
    workers = ran_on.workers
    print(
        f"## apf-sim study over worlds: preset {config.preset}, noise {config.noise_std_m} m, seed {args.seed}, "
        f"{args.trials} trials per planner and world\n"
    )
    print(world_table(cells, config.goal_radius_m))
    n_trials = len(planners) * len(cases) * args.trials
    print(
        f"\n{n_trials} trials in {wall_s:.1f} s wall clock with {workers} worker(s). Planners see wall and trunk "
        f"surfaces as points every {spacing} m; collision (< {config.collision_radius_m} m) and clearance on the "
        f"true geometry. A* = full-knowledge grid optimum (clearance {kw['clearance_m']} m, grid "
        f"{kw['resolution_m']} m) to the goal circle (radius {config.goal_radius_m} m); mean path over successes."
    )
    fenced = [c.label for c in cases if c.world.area_ne_m is not None]
    if fenced and "bapf-nav" in planners:
        print(f"bapf-nav plans over the flying area (area_ne_m) of: {', '.join(fenced)}; --no-area leaves it out.")
    _write_worlds(args, config, planners, cases, cells, spacing, kw)
    return 0


def _write_worlds(
    args: argparse.Namespace,
    config: StudyConfig,
    planners: tuple[str, ...],
    cases: list[WorldCase],
    cells: list[WorldCell],
    spacing: float,
    kw: dict[str, float],
) -> None:
    """The --world run's --json and --plots files."""
    from sim.study.report import write_json
    from sim.study.worldstudy import cell_summary

    if args.json is not None:
        doc: dict[str, object] = {
            "schema": 1,
            "kind": "worlds",
            "preset": config.preset,
            "seed": args.seed,
            "trials_per_cell": args.trials,
            "noise_std_m": config.noise_std_m,
            "surface_spacing_m": spacing,
            "optimum": kw,
            "results": [cell_summary(c, config.goal_radius_m) for c in cells],
        }
        write_json(args.json, doc)
    if args.plots is not None:
        from sim.study.worldplots import plot_world

        args.plots.mkdir(parents=True, exist_ok=True)
        for case in cases:
            plot_world(args.plots / f"world_{case.label}.png", case, config, planners, args.seed, **kw)
        print(f"\nfigures in {args.plots}: " + ", ".join(f"world_{c.label}.png" for c in cases))


def _sweep_table(sweep_cells: list[tuple[float, list[CellResult]]]) -> str:
    from sim.study.metrics import summarize

    keys: list[tuple[str, str]] = []
    for _, cells in sweep_cells:
        for c in cells:
            key = (c.planner_name, c.density.label)
            if key not in keys:
                keys.append(key)
    head = "| mu_o | " + " | ".join(f"{n} N {d}" for n, d in keys) + " |"
    lines = [head, "|" + "---|" * (len(keys) + 1)]
    for mu, cells in sweep_cells:
        by_key = {(c.planner_name, c.density.label): summarize(c.records).R_s for c in cells}
        lines.append(f"| {mu:.2f} | " + " | ".join(f"{by_key.get(k, float('nan')):.3f}" for k in keys) + " |")
    return "\n".join(lines)


def _write_plots(
    out_dir: Path,
    config: StudyConfig,
    cells: list[CellResult],
    sweep_cells: list[tuple[float, list[CellResult]]],
    densities: tuple[Density, ...],
    seed: int,
) -> None:
    from sim.study import plots

    out_dir.mkdir(parents=True, exist_ok=True)
    density = densities[len(densities) // 2]
    written: list[str] = []
    runs = plots.example_runs(config, "cr-bapf*", density, seed)
    if plots.plot_trajectories(out_dir / "trajectories.png", runs):
        written.append("trajectories.png")
    else:
        print(
            "plots: no pair of successful/unsuccessful CR-BAPF* runs found; trajectories.png skipped", file=sys.stderr
        )
    abapf = plots.example_runs(plots.abapf_paper_rule_config(config), "a-bapf", density, seed)
    if plots.plot_abapf_mu(out_dir / "abapf_mu.png", abapf):
        written.append("abapf_mu.png")
    else:
        print("plots: no successful A-BAPF run found; abapf_mu.png skipped", file=sys.stderr)
    if cells:
        plots.plot_rs_per_planner(out_dir / "rs_per_planner.png", cells)
        written.append("rs_per_planner.png")
    if sweep_cells:
        plots.plot_mu_sweep(out_dir / "rs_vs_mu.png", sweep_cells)
        written.append("rs_vs_mu.png")
    else:
        print("plots: rs_vs_mu.png needs --mu-sweep; skipped", file=sys.stderr)
    print(f"\nfigures in {out_dir}: {', '.join(written)}")
