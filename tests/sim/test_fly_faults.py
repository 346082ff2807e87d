"""apf-sim fly --link-faults: the proxy between the two real processes, and the sweep's fault summary."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path
from typing import Any

import pytest

from sim.cli import build_parser
from sim.fly import OUTCOMES, FlyOptions, _service_events, expected_flight_s
from sim.flysweep import _fault_summary, flight_densities
from sim.linkfaults import LinkFaults

pytestmark = pytest.mark.timeout(150)


def _apf_sim(*argv: str, timeout: float = 130.0) -> subprocess.CompletedProcess[str]:
    return subprocess.run(
        [sys.executable, "-m", "sim", *argv],
        capture_output=True,
        text=True,
        timeout=timeout,
        env=os.environ | {"OPENBLAS_NUM_THREADS": "1"},
        check=False,
    )


def test_cli_parses_the_spec_and_rejects_typos() -> None:
    args = build_parser().parse_args(["fly", "--link-faults", "loss=0.3,jitter=0.1,blackout=2@40%"])
    assert args.link_faults == LinkFaults.parse("loss=0.3,jitter=0.1,blackout=2@40%")
    proc = _apf_sim("fly", "--link-faults", "los=0.3", timeout=30.0)
    assert proc.returncode == 2
    assert "did you mean 'loss'" in proc.stderr


def test_densities_cycle_and_expected_flight() -> None:
    assert flight_densities(FlyOptions(obstacles="low,mid,high")) == ["low", "mid", "high"]
    assert flight_densities(FlyOptions(obstacles="37")) == ["37"]
    # The paper's diagonal, (3, 3) -> (22, 22): 26.9 m at 0.5 m/s.
    assert expected_flight_s(FlyOptions()) == pytest.approx(53.74, abs=0.01)


def test_service_events_from_the_json_log(tmp_path: Path) -> None:
    log = tmp_path / "service.log"
    lines: list[Any] = [
        {"event": "state.change", "new": "NAVIGATING", "reason": "new goal"},
        {"event": "state.change", "new": "HOLDING", "reason": "pose stale: holding position"},
        {"event": "state.change", "old": "HOLDING", "new": "HOLDING", "reason": "ranges stale: holding position"},
        "not json {",
        {"event": "takeover.failed", "error": "arming not confirmed within 5 s"},
        {"event": "state.change", "new": "LINK_LOST", "reason": "autopilot heartbeat lost: stopped sending"},
    ]
    log.write_text("\n".join(x if isinstance(x, str) else json.dumps(x) for x in lines) + "\n")
    ev = _service_events(log)
    assert ev == {
        "link_lost": 1,
        "holding": 1,
        "takeover_failed": ["arming not confirmed within 5 s"],
        "last_reason": "autopilot heartbeat lost: stopped sending",
    }
    assert _service_events(tmp_path / "missing.log")["link_lost"] == 0


def test_fault_summary_counts() -> None:
    records: list[dict[str, Any]] = [
        {"outcome": "arrived", "min_clearance_m": 0.4, "obstacles": "low", "service_events": {"link_lost": 0}},
        {
            "outcome": "link_lost",
            "min_clearance_m": 0.2,
            "dropped_goal": True,
            "obstacles": "mid",
            "service_events": {"link_lost": 1, "takeover_failed": ["x"]},
        },
        {"outcome": "collision", "min_clearance_m": 0.0, "obstacles": "mid", "service_events": {}},
        {"outcome": "error", "seed": 3},  # fly itself failed: no record fields
    ]
    s = _fault_summary(records)
    assert s["collisions"] == 1
    assert s["min_clearance_m"] == 0.0
    assert s["dropped_goals"] == 1
    assert s["link_lost_events"] == 1
    assert s["flights_with_link_lost"] == 1
    assert s["takeover_failures"] == 1
    assert s["by_obstacles"]["mid"]["collision"] == 1
    assert set(s["by_obstacles"]["low"]) == set(OUTCOMES)
    json.dumps(s)


def test_fly_through_a_faulty_link(tmp_path: Path) -> None:
    """One short flight through the proxy: the faults happen (counted per direction) and the flight ends with
    one of fly's outcomes. Which outcome is the service's business (issue 9), not this test's."""
    out = tmp_path / "out"
    result = tmp_path / "r.json"
    spec = "loss=0.2,jitter=0.05,dup=0.05,reorder=0.05,blackout=1@30%"
    proc = _apf_sim(
        "fly",
        "--obstacles",
        "10",
        "--seed",
        "3",
        "--no-plot",
        "--quiet",
        "--out",
        str(out),
        "--json",
        str(result),
        "--link-faults",
        spec,
    )
    rec = json.loads(result.read_text())
    assert rec["outcome"] in OUTCOMES, proc.stdout + proc.stderr
    assert rec["outcome"] != "error", proc.stdout + proc.stderr
    assert rec["link_faults"] == str(LinkFaults.parse(spec))
    for direction in ("to_companion", "to_vehicle"):
        stats = rec["link_stats"][direction]
        assert stats["received"] > 100
        assert 0.1 < stats["dropped"] / stats["received"] < 0.3
        assert stats["delivered"] > 0
    up = rec["link_stats"]["to_companion"]
    assert up["duplicated"] > 0
    assert up["reordered"] > 0
    assert up["max_delay_s"] <= 0.05 + 1e-6
    # The blackout was placed in the flight (after the takeoff) and dropped what came in it.
    if rec["outcome"] == "arrived":
        (t0, t1), *_ = rec["blackout_windows_s"]
        assert t1 - t0 == pytest.approx(1.0)
        assert up["blackout_dropped"] > 0
    assert isinstance(rec["service_events"]["link_lost"], int)
    assert isinstance(rec["dropped_goal"], bool)
