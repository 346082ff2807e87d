"""``python -m sim.study [options]``: the same as ``apf-sim study [options]``."""

from __future__ import annotations

import sys
from collections.abc import Sequence

from sim.cli import main as apf_sim_main


def main(argv: Sequence[str] | None = None) -> int:
    return apf_sim_main(["study", *(sys.argv[1:] if argv is None else argv)])


if __name__ == "__main__":
    sys.exit(main())
