"""apf-sim fly end to end: two real processes on loopback, result files, plot and tlogs."""

from __future__ import annotations

import asyncio
import json
import os
import socket
import subprocess
import sys
from pathlib import Path

import pytest
from pymavlink import mavutil

from apf_companion.viz import Topic
from sim import fly as fly_module
from sim.cli import main as sim_main
from sim.fly import FlyOptions, _outcome
from sim.mcap_plot import read_recording

pytestmark = pytest.mark.timeout(120)


def _types_in_tlog(path: Path) -> set[str]:
    conn = mavutil.mavlink_connection(str(path))
    seen: set[str] = set()
    while True:
        msg = conn.recv_match()
        if msg is None:
            return seen
        seen.add(msg.get_type())


@pytest.mark.slow
def test_fly_paper_scenario_one_command(tmp_path: Path) -> None:
    out = tmp_path / "out"
    result = tmp_path / "r.json"
    proc = subprocess.run(
        [
            sys.executable,
            "-m",
            "sim",
            "fly",
            "--obstacles",
            "20",
            "--seed",
            "1",
            "--out",
            str(out),
            "--json",
            str(result),
            "--quiet",
        ],
        capture_output=True,
        text=True,
        timeout=110,
        env=os.environ | {"OPENBLAS_NUM_THREADS": "1"},
        check=False,
    )
    assert proc.returncode == 0, proc.stdout + proc.stderr
    rec = json.loads(result.read_text())
    assert rec["outcome"] == "arrived"
    assert {"outcome", "steps", "min_clearance_m", "path_length_m", "sim_time_s"} <= set(rec)
    # 26.9 m diagonal in 0.4 m steps, plus the 5 m climb in the path length.
    assert rec["steps"] >= 60
    assert rec["path_length_m"] >= 26.8
    assert rec["min_clearance_m"] > 0.25
    assert "outcome: arrived" in proc.stdout and "path length:" in proc.stdout
    assert (out / "trajectory.png").stat().st_size > 10_000
    companion = _types_in_tlog(out / "companion.tlog")
    assert {"SET_POSITION_TARGET_LOCAL_NED", "HEARTBEAT", "OBSTACLE_DISTANCE", "LOCAL_POSITION_NED"} <= companion
    assert "SET_POSITION_TARGET_LOCAL_NED" in _types_in_tlog(out / "vehicle.tlog")
    # The service's MCAP beside the tlogs (the `viz` extra is in `test`), read back and drawn by mcap-plot.
    mcap = Path(rec["mcap"])
    assert mcap.parent == out and mcap.name.startswith("apf-") and mcap.suffix == ".mcap"
    recording = read_recording(mcap)
    assert set(recording.topics) == {str(t) for t in Topic}
    planned = [c for _, c in recording.topics[Topic.CYCLE] if c["decision"] not in (None, "TRACKING")]
    assert len(planned) >= rec["steps"] - 1
    png = tmp_path / "flight.png"
    assert sim_main(["mcap-plot", str(mcap), "-o", str(png)]) == 0
    assert png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n" and png.stat().st_size > 20_000


def test_outcome_rules() -> None:
    assert _outcome(None, {"outcome": "arrived"}) == "error"
    assert _outcome({"collided": True}, {"outcome": "arrived"}) == "collision"
    assert _outcome({"collided": False, "crashed": False}, {"outcome": "arrived"}) == "arrived"
    assert _outcome({"collided": False}, {"outcome": "stuck"}) == "stuck"
    # The autopilot enforced its fence: whatever the service then said (its goal dropped: IDLE)
    assert _outcome({"collided": False, "fence_breaches": 1}, {"outcome": "error"}) == "fence_breach"
    assert _outcome({"collided": True, "fence_breaches": 1}, {"outcome": "error"}) == "collision"
    assert _outcome({"collided": False}, {"outcome": "timeout"}) == "timeout"
    # LINK_LOST is an outcome of its own (issue 9's sweeps count it); anything else the service reports is an error.
    assert _outcome({"collided": False}, {"outcome": "link_lost"}) == "link_lost"
    assert _outcome({"collided": False}, {"outcome": "error"}) == "error"
    assert _outcome({"collided": False}, {"outcome": "stopped"}) == "error"
    assert _outcome({"collided": False}, None) == "error"


def test_a_planner_typo_is_refused_before_anything_starts(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    out = tmp_path / "out"
    with pytest.raises(SystemExit) as exc:
        sim_main(["fly", "--planner", "cr-bapff", "--out", str(out)])
    assert exc.value.code == 2
    assert "argument --planner: invalid choice: 'cr-bapff'" in capsys.readouterr().err
    assert not out.exists()


def test_a_port_taken_before_the_service_binds_it_is_picked_again(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """The service's port is picked free and bound a moment later by another process; another program took it in
    between (seen in a batch beside another: "Address already in use"). The flight is set up again on a new port."""
    taken = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    taken.bind(("127.0.0.1", 0))
    picks = [int(taken.getsockname()[1])]
    real = fly_module.free_udp_port
    monkeypatch.setattr(fly_module, "free_udp_port", lambda: picks.pop() if picks else real())
    opt = FlyOptions(obstacles="0", goal_ne_m=(6.0, 6.0), out=tmp_path / "out", plot=False, progress=False)
    try:
        rec = asyncio.run(fly_module.fly(opt))
    finally:
        taken.close()
    assert rec["port_retries"] == 1 and rec["outcome"] == "arrived", rec
    assert json.loads((tmp_path / "out" / "result.json").read_text())["port_retries"] == 1
