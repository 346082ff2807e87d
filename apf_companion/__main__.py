"""``python -m apf_companion``: the same as the ``apf-companion`` console script."""

from __future__ import annotations

import sys

from apf_companion.cli import main

sys.exit(main())
