"""The documented log workflow: pymavlink's ``mavgraph.py`` graphs a .tlog headless into a PNG.

matplotlib 3.11 removed ``Axes.plot_date``, which mavgraph.py (pymavlink 2.4.50) and MAVExplorer's grapher
(MAVProxy 1.8.75) call; pyproject pins matplotlib < 3.11 for that. This test fails again if the pin goes while
the tools still call it.
"""

from __future__ import annotations

import struct
import subprocess
import sys
from pathlib import Path

import pytest
from pymavlink.dialects.v20 import common as mavlink2

MAVGRAPH = Path(sys.executable).parent / "mavgraph.py"


def _write_tlog(path: Path, n: int = 40) -> None:
    """A .tlog as the project writes it: 8-byte big-endian UNIX time in µs, then the MAVLink 2 frame."""
    mav = mavlink2.MAVLink(None, srcSystem=1, srcComponent=1)
    t0_us = 1_795_000_000_000_000
    with path.open("wb") as fh:
        for k in range(n):
            msg = mav.local_position_ned_encode(100 * k, 0.1 * k, 0.05 * k, -5.0, 1.0, 0.5, 0.0)
            fh.write(struct.pack(">Q", t0_us + 100_000 * k) + msg.pack(mav))


@pytest.mark.skipif(not MAVGRAPH.is_file(), reason="mavgraph.py not beside this interpreter (pymavlink's script)")
def test_mavgraph_writes_a_png_from_a_tlog(tmp_path: Path) -> None:
    tlog = tmp_path / "vehicle.tlog"
    _write_tlog(tlog)
    png = tmp_path / "graph.png"
    result = subprocess.run(
        [
            sys.executable,
            str(MAVGRAPH),
            "--output",
            str(png),
            str(tlog),
            "LOCAL_POSITION_NED.x",
            "LOCAL_POSITION_NED.y",
        ],
        capture_output=True,
        text=True,
        timeout=120,
        cwd=tmp_path,
        env={"MPLBACKEND": "Agg", "PATH": "/usr/bin:/bin", "HOME": str(tmp_path)},
    )
    assert result.returncode == 0, result.stderr
    assert "Traceback" not in result.stderr
    assert png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    assert png.stat().st_size > 5000  # a drawn graph, not an empty canvas
