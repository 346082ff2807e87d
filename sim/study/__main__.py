"""``python -m sim.study [options]``: the same as ``apf-sim study [options]``, without the other subcommands."""

from __future__ import annotations

import argparse
import logging
import sys
from collections.abc import Callable, Sequence
from typing import cast

from sim.study.cli import register


def main(argv: Sequence[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m sim.study", add_help=False)
    sub = parser.add_subparsers(dest="command", required=True)
    register(sub)
    sub.choices["study"].prog = "python -m sim.study"
    args = parser.parse_args(["study", *(sys.argv[1:] if argv is None else argv)])
    logging.basicConfig(level=logging.WARNING, format="%(asctime)s %(levelname)s %(name)s: %(message)s")
    func = cast(Callable[[argparse.Namespace], int], args.func)
    try:
        return func(args)
    except KeyboardInterrupt:
        return 130


if __name__ == "__main__":
    sys.exit(main())
