"""apf-sim: the bundled simulator's command line.

Subcommands live beside what they run; each module exposes ``register(subparsers)`` that adds its parser and
sets ``func`` (a callable taking the parsed namespace and returning an exit code):
- ``study``   the paper's Monte Carlo study (sim/study/cli.py)
- ``vehicle`` the simulated autopilot + vehicle + world + range sensor (sim/vehicle/cli.py)
- ``sensor``  world and range sensor only, following an external autopilot (sim/vehicle/cli.py)
- ``fly``     the simulator and the companion service together, one SITL-style flight (sim/flycli.py, sim/fly.py)
- ``sweep``   R_s and path length over a grid of planner parameters and densities (sim/sweep_cli.py)
- ``mcap-plot`` a recorded flight (.mcap) drawn to PNG (sim/mcap_plot.py)
"""

from __future__ import annotations

import argparse
import importlib
import importlib.metadata
import logging
import sys
from collections.abc import Callable, Sequence
from typing import cast

from apf_companion.cli import add_log_level_option

_SUBCOMMAND_MODULES = ("sim.flycli", "sim.vehicle.cli", "sim.study.cli", "sim.sweep_cli", "sim.mcap_plot")


def package_version() -> str:
    """The installed distribution's version (the wheel's metadata, not a copy in the source)."""
    try:
        return importlib.metadata.version("apf-companion")
    except importlib.metadata.PackageNotFoundError:
        return "unknown (not installed: pip install -e .)"


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="apf-sim", description=__doc__.splitlines()[0])
    parser.add_argument("--version", action="version", version=f"%(prog)s {package_version()}")
    add_log_level_option(parser, default="WARNING")
    sub = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")
    for name in _SUBCOMMAND_MODULES:
        importlib.import_module(name).register(sub)
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    logging.basicConfig(level=args.log_level, format="%(asctime)s %(levelname)s %(name)s: %(message)s")
    func = cast(Callable[[argparse.Namespace], int], args.func)
    try:
        return func(args)
    except KeyboardInterrupt:
        return 130


if __name__ == "__main__":
    sys.exit(main())
