"""``apf-sim sweep``: R_s and path length over a grid of planner parameters and obstacle densities or worlds.

    apf-sim sweep --planners cr-bapf* --param mu_o=100,500,1000 --param rho_l=0.2,0.4 --trials 200 --out sweep-out
    apf-sim sweep --param step=0.2:0.6:5 --densities 20-45,70-95 --dask local --workers 2
    apf-sim sweep --param rho_l=0.2,0.4 --worlds u-trap,forest-dense,my-world.toml            # worlds only
    apf-sim sweep --param rho_l=0.2,0.4 --worlds u-trap --densities 20-45                   # both
    apf-sim sweep --list-params

Writes sweep.csv, sweep.json and heatmap_<planner>.png (R_s and mean path length) into --out and prints the table.
Every grid point sees the same seeded fields and noise (see sim/sweep.py); runs here, or on Dask with --dask.
Worlds (bundled names or TOML files) run as in ``apf-sim study --world``.
"""

from __future__ import annotations

import argparse
import dataclasses
import sys
import time
from pathlib import Path
from typing import TYPE_CHECKING

from apf_companion.errors import ConfigError
from sim.extras import require
from sim.study.config import DEFAULT_DENSITIES, PRESET_NAMES, Density, StudyConfig, check_planner_names
from sim.sweep_grid import format_value, parse_params, sweepable_fields

if TYPE_CHECKING:
    from sim.sweep import Scenario


def register(subparsers: argparse._SubParsersAction) -> None:  # type: ignore[type-arg]
    """Add ``sweep`` to ``apf-sim``."""
    p = subparsers.add_parser(
        "sweep",
        help="R_s and path length over a grid of planner parameters and densities or worlds",
        description=__doc__,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    p.add_argument(
        "--param",
        action="append",
        default=[],
        metavar="NAME=VALUES",
        help="a swept planner parameter: NAME=V1,V2,... or NAME=LOW:HIGH:N; repeat for a grid. NAME is a "
        "PlannerParams field, without its unit suffix if you like (mu_o, rho_l, rho_u, step) or N_b "
        "(see --list-params)",
    )
    p.add_argument("--list-params", action="store_true", help="print the sweepable parameters and exit")
    p.add_argument("--planners", default="cr-bapf*", help="comma-separated planners (default cr-bapf*)")
    p.add_argument(
        "--densities",
        default=None,
        help="obstacle-count ranges N_l-N_u, comma separated (default 20-45,45-70,70-95 without --worlds, none "
        "with it)",
    )
    p.add_argument(
        "--worlds",
        default=None,
        metavar="NAME|FILE,...",
        help="world files or bundled worlds (u-trap, forest-dense, ...), comma separated, run as in apf-sim study "
        "--world: a sweep axis beside or instead of the densities",
    )
    p.add_argument(
        "--surface-spacing",
        type=float,
        default=None,
        metavar="M",
        help="spacing of the surface samples the planners see on worlds [m] (default 0.2, as apf-sim study)",
    )
    p.add_argument(
        "--no-area",
        action="store_true",
        help="leave out the worlds' flying areas (area_ne_m), as apf-sim study --no-area: needed to sweep nav_grid_m "
        "on wall-gap or rooms, whose area grid replaces it",
    )
    p.add_argument("--preset", choices=PRESET_NAMES, default="reference", help="study rules (default reference)")
    p.add_argument("--trials", type=int, default=200, help="trials per cell (default 200)")
    p.add_argument("--chunk-trials", type=int, default=None, help="trials per seeded chunk (default 500)")
    p.add_argument("--seed", type=int, default=0, help="root seed (default 0)")
    p.add_argument("--workers", type=int, default=None, help="worker processes (default: all cores)")
    p.add_argument(
        "--dask", metavar="local|ADDRESS", default=None, help="run on Dask: 'local' or tcp://HOST:8786 (as study)"
    )
    p.add_argument("--out", type=Path, default=Path("sweep-out"), help="output directory (default sweep-out)")
    p.add_argument("--no-plots", action="store_true", help="write no heatmaps")
    p.add_argument("--no-progress", action="store_true", help="no progress bar on stderr")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    try:
        return _run(args)
    except ConfigError as err:
        print(f"apf-sim sweep: {err}", file=sys.stderr)
        return 2


def _list_params(config: StudyConfig) -> int:
    params = config.planner_params
    print(f"sweepable fields of {type(params).__name__} (preset {config.preset} values):")
    for name, kind in sweepable_fields(params).items():
        print(f"  {name:<16} {kind.__name__:<15} {format_value(getattr(params, name))}")
    return 0


def _scenarios(args: argparse.Namespace) -> tuple[Scenario, ...]:
    """The densities, then the worlds (each loaded, sampled and given its optimum as ``apf-sim study --world``
    does); every world that cannot be loaded is reported in one ``ConfigError``."""
    from sim.study.worldstudy import load_case, without_area
    from sim.world.geometry import SURFACE_SPACING_M

    density_text = args.densities
    if density_text is None:
        density_text = "" if args.worlds else ",".join(d.label for d in DEFAULT_DENSITIES)
    densities = [Density.parse(d) for d in density_text.split(",") if d.strip()]
    spacing = SURFACE_SPACING_M if args.surface_spacing is None else args.surface_spacing
    if not spacing > 0:
        raise ConfigError(f"--surface-spacing: need > 0, got {spacing}")
    worlds: list[Scenario] = []
    errors: list[str] = []
    for name in (w.strip() for w in (args.worlds or "").split(",")):
        if not name:
            continue
        try:
            case = load_case(name, spacing_m=spacing)
            if args.no_area:
                case = without_area(case)
            worlds.append(case)
        except ConfigError as err:
            errors.append(str(err))
    if errors:
        raise ConfigError("--worlds: " + "; ".join(errors))
    return (*densities, *worlds)


def _run(args: argparse.Namespace) -> int:
    from sim.study.cli import ProgressBar
    from sim.study.executors import study_executor
    from sim.sweep import plan_sweep, run_sweep
    from sim.sweep_report import markdown_table, plot_heatmaps, sweep_json, write_csv, write_json

    config = StudyConfig.from_preset(args.preset)
    if args.list_params:
        return _list_params(config)
    if args.chunk_trials is not None:
        config = dataclasses.replace(config, chunk_trials=args.chunk_trials)
    if not args.param:
        raise ConfigError("give at least one --param NAME=VALUES (apf-sim sweep --list-params shows the names)")
    if args.trials < 1:
        raise ConfigError(f"--trials: need >= 1, got {args.trials}")
    if args.workers is not None and args.workers < 1:
        raise ConfigError(f"--workers: need >= 1, got {args.workers}")
    if not args.no_plots:
        require("the heatmaps (--no-plots skips them)", "matplotlib")  # before the sweep, not after it
    swept = parse_params(args.param, config.planner_params)
    planners = check_planner_names(tuple(p.strip() for p in args.planners.split(",") if p.strip()))
    plan = plan_sweep(config, planners, swept, _scenarios(args), args.trials, args.seed)

    with study_executor(args.dask, args.workers) as (executor, ran_on):
        progress = None if args.no_progress else ProgressBar(sys.stderr, label="sweep")
        t0 = time.perf_counter()
        cells = run_sweep(plan, executor, progress=progress)
        wall_s = time.perf_counter() - t0

    n_trials = sum(t.n_trials for t in plan.tasks)
    print(f"## apf-sim sweep: preset {config.preset}, seed {args.seed}, {args.trials} trials per cell\n")
    print(markdown_table(cells))
    print(f"\n{len(cells)} cells, {n_trials} trials in {wall_s:.1f} s wall clock with {ran_on.describe()}.")
    out: Path = args.out
    write_csv(out / "sweep.csv", cells, swept)
    executor_doc = {"kind": ran_on.kind, "workers": ran_on.workers, "address": ran_on.address}
    doc = sweep_json(config, cells, swept, seed=args.seed, trials=args.trials, wall_s=wall_s, executor=executor_doc)
    write_json(out / "sweep.json", doc)
    written = ["sweep.csv", "sweep.json"]
    if not args.no_plots:
        written += [p.name for p in plot_heatmaps(out, cells)]
    print(f"wrote {', '.join(written)} in {out}")
    return 0
