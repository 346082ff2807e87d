"""A link that does not come back: with ``exit_when_done`` the run ends after ``max_link_lost_s`` without an autopilot
HEARTBEAT (outcome link_lost, exit code 3) although the goal is kept for the heartbeat's return; without it the
service waits for ever. Either way the log says every ``LINK_LOST_REPEAT_S`` how long the link has been lost.

The rule is driven socket-free (records straight to the handlers, the service clock injected); one loopback test
runs ``apf-companion run`` against an ``apf-sim vehicle`` process and stops the vehicle.
"""

from __future__ import annotations

import json
import logging
import os
import signal
import socket
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

import pytest
from pymavlink.dialects.v20 import ardupilotmega as m

from apf_companion.cli import EXIT_STUCK, _exit_code
from apf_companion.config import config_from_mapping
from apf_companion.goal import Route
from apf_companion.links.messages import Attitude, Heartbeat, LocalPositionNed, ObstacleDistance, Source
from apf_companion.navigator import State
from apf_companion.service import LINK_LOST_REPEAT_S, CompanionService, LinkLostLog
from tests.conftest import ManualClock, free_port

AP = Source(1, 1)
GUIDED = 4


def _service(**extra: Any) -> tuple[CompanionService, ManualClock]:
    clock = ManualClock()
    cfg = config_from_mapping({"link": {"connect": "udpin:127.0.0.1:0"}, **extra})
    return CompanionService(cfg, route=Route.point(30.0, 0.0, -5.0, source="cli"), clock=clock), clock


def _heartbeat(svc: CompanionService, clock: ManualClock) -> None:
    hb = Heartbeat(src=AP, type=m.MAV_TYPE_QUADROTOR, autopilot=3, base_mode=1, custom_mode=GUIDED, system_status=4)
    svc.handlers.handle(hb, clock.t)


def _inputs(svc: CompanionService, clock: ManualClock) -> None:
    """A pose and a free range scan at ``clock.t`` (the autopilot's boot time follows the service clock)."""
    ms = int(clock.t * 1000)
    svc.handlers.handle(Attitude(src=AP, time_boot_ms=ms, roll=0.0, pitch=0.0, yaw=0.0), clock.t)
    pose = LocalPositionNed(src=AP, time_boot_ms=ms, x=0.0, y=0.0, z=-5.0, vx=0.0, vy=0.0, vz=0.0)
    svc.handlers.handle(pose, clock.t)
    scan = ObstacleDistance(
        src=AP, time_usec=ms * 1000, distances=(801,) * 72, increment=0, min_distance=20, max_distance=800,
        increment_f=5.0, angle_offset=0.0, frame=12,
    )  # fmt: skip
    svc.handlers.handle(scan, clock.t)


def _flying(**extra: Any) -> tuple[CompanionService, ManualClock, float]:
    """A service navigating to its goal; the time of the autopilot's last HEARTBEAT."""
    svc, clock = _service(exit_when_done=True, **extra)
    _heartbeat(svc, clock)
    _inputs(svc, clock)
    out = svc.run_cycle(clock.t)
    assert svc.navigator.route is not None and out.state is State.NAVIGATING, out
    return svc, clock, clock.t


def _cycle_at(svc: CompanionService, clock: ManualClock, t_s: float) -> State:
    clock.t = t_s
    return svc.run_cycle(t_s).state


def test_exit_when_done_ends_the_run_when_the_link_stays_lost_past_max_link_lost_s() -> None:
    """The bug: the goal is kept at LINK_LOST (resume_after_link_lost), so the run waited for ever; exit code 3
    "link lost" of ``run --help`` could not happen with the default configuration."""
    svc, clock, last_hb = _flying(max_link_lost_s=20.0)
    assert _cycle_at(svc, clock, last_hb + 4.0) is State.LINK_LOST  # heartbeat_timeout_s = 3
    assert svc.navigator.route is not None  # the goal is kept for the heartbeat's return
    assert _cycle_at(svc, clock, last_hb + 19.9) is State.LINK_LOST
    assert not svc._stop.is_set() and svc.flight.outcome is None
    _cycle_at(svc, clock, last_hb + 20.1)
    assert svc._stop.is_set()
    result = svc.result()
    assert result.outcome == "link_lost" and result.state == "LINK_LOST"
    assert _exit_code(result.outcome) == EXIT_STUCK == 3


def test_the_default_bound_is_60_s_and_0_waits_for_ever() -> None:
    svc, clock, last_hb = _flying()
    assert svc.config.max_link_lost_s == 60.0
    _cycle_at(svc, clock, last_hb + 59.0)
    assert not svc._stop.is_set()
    _cycle_at(svc, clock, last_hb + 61.0)
    assert svc._stop.is_set() and svc.result().outcome == "link_lost"
    svc, clock, last_hb = _flying(max_link_lost_s=0.0)
    _cycle_at(svc, clock, last_hb + 4.0)
    _cycle_at(svc, clock, last_hb + 86_400.0)
    assert not svc._stop.is_set() and svc.result().outcome == "stopped"


def test_a_heartbeat_back_in_time_restarts_the_count() -> None:
    svc, clock, last_hb = _flying(max_link_lost_s=20.0)
    _cycle_at(svc, clock, last_hb + 15.0)
    clock.t = last_hb + 16.0
    _heartbeat(svc, clock)  # back, still GUIDED: HOLDING, the goal resumes
    assert _cycle_at(svc, clock, last_hb + 16.0) is State.HOLDING
    back = clock.t
    assert _cycle_at(svc, clock, back + 4.0) is State.LINK_LOST  # lost again
    _cycle_at(svc, clock, last_hb + 30.0)  # 30 s after the first loss, 14 s after the last HEARTBEAT
    assert not svc._stop.is_set()
    _cycle_at(svc, clock, back + 20.5)
    assert svc._stop.is_set() and svc.result().outcome == "link_lost"


def test_max_flight_s_running_out_while_the_link_is_lost_ends_it_as_link_lost() -> None:
    """Out of time with the autopilot unheard: the outcome names the lost link, not a slow flight."""
    svc, clock, last_hb = _flying(max_flight_s=10.0)
    _cycle_at(svc, clock, last_hb + 4.0)
    assert not svc._stop.is_set()
    _cycle_at(svc, clock, last_hb + 10.5)
    assert svc._stop.is_set() and svc.result().outcome == "link_lost"
    svc, clock, last_hb = _flying(max_flight_s=10.0)  # heard throughout: a timeout
    for k in range(1, 11):
        clock.t = last_hb + k * 1.05
        _heartbeat(svc, clock)
        svc.run_cycle(clock.t)
    assert svc._stop.is_set() and svc.result().outcome == "timeout"


def test_without_exit_when_done_the_service_waits_and_says_so_every_repeat_period(
    caplog: pytest.LogCaptureFixture,
) -> None:
    svc, clock = _service()
    _heartbeat(svc, clock)
    _inputs(svc, clock)
    svc.run_cycle(clock.t)
    last_hb = clock.t
    lost_log = LinkLostLog(svc)
    caplog.set_level(logging.INFO, logger="apf_companion.service")
    assert lost_log.due(clock.t) == clock.t + 1.0  # heard: nothing to say
    _cycle_at(svc, clock, last_hb + 4.0)
    entered = clock.t
    t = entered
    while t < entered + 4 * LINK_LOST_REPEAT_S:
        _cycle_at(svc, clock, t)
        lost_log.due(t)
        t += 0.5
    lines = [r for r in caplog.records if r.getMessage() == "link.lost"]
    assert not svc._stop.is_set()  # a service waits for its autopilot
    assert len(lines) == 3  # at 15, 30 and 45 s after LINK_LOST was seen
    lost = [r.__dict__["lost_s"] for r in lines]
    assert lost == pytest.approx([4.0 + k * LINK_LOST_REPEAT_S for k in (1, 2, 3)], abs=0.6)
    assert all(r.levelno == logging.WARNING and r.__dict__["goal"] == "kept" for r in lines)
    assert not any(hasattr(r, "max_link_lost_s") for r in lines)  # nothing ends this run
    clock.t = t
    _heartbeat(svc, clock)
    _cycle_at(svc, clock, t)
    caplog.clear()
    for k in range(40):
        lost_log.due(t + k)
    assert not [r for r in caplog.records if r.getMessage() == "link.lost"]  # back: quiet again


def test_the_end_of_a_run_by_the_lost_link_is_logged(caplog: pytest.LogCaptureFixture) -> None:
    svc, clock, last_hb = _flying(max_link_lost_s=20.0)
    caplog.set_level(logging.INFO, logger="apf_companion.service")
    _cycle_at(svc, clock, last_hb + 4.0)
    _cycle_at(svc, clock, last_hb + 21.0)
    (line,) = [r for r in caplog.records if r.getMessage() == "link.lost"]
    assert line.__dict__["ends_run"] is True and line.__dict__["lost_s"] == 21.0
    assert line.__dict__["max_link_lost_s"] == 20.0


@pytest.mark.timeout(120)
def test_a_stopped_vehicle_ends_an_exit_when_done_run_with_exit_code_3(tmp_path: Path) -> None:
    """``apf-companion run`` against an ``apf-sim vehicle`` process on loopback UDP: the vehicle process is
    stopped mid-flight, and the run ends with exit code 3 and outcome link_lost after ``max_link_lost_s`` (before,
    it waited for ever after LINK_LOST with the goal kept, and the log was quiet). A goal from the command line is
    flown although the vehicle hovers in GUIDED already (``goal.fly_after_restart`` is about the config's goal)."""
    port = free_port(socket.SOCK_DGRAM)
    config = tmp_path / "run.toml"
    config.write_text(
        "exit_when_done = true\n"
        "max_link_lost_s = 3.0\n"
        f'[link]\nconnect = "udpin:127.0.0.1:{port}"\nheartbeat_timeout_s = 1.0\n'
        '[planner]\nname = "cr-bapf*"\n',
        encoding="utf-8",
    )
    result = tmp_path / "result.json"
    env = os.environ | {"OPENBLAS_NUM_THREADS": "1", "PYTHONUNBUFFERED": "1"}
    vehicle = subprocess.Popen(
        [sys.executable, "-m", "sim", "vehicle", "--link", f"udpout:127.0.0.1:{port}", "--airborne", "--alt", "5",
         "--mode", "GUIDED"],
        stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, env=env,
    )  # fmt: skip
    companion = subprocess.Popen(
        [sys.executable, "-m", "apf_companion", "--log-format", "json", "run", "--config", str(config),
         "--goal", "30,0,-5", "--result-json", str(result)],
        stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True, env=env,
    )  # fmt: skip
    try:
        assert companion.stderr is not None
        deadline = time.monotonic() + 60.0  # bounds a hang only
        events: list[dict[str, Any]] = []
        while time.monotonic() < deadline:
            line = companion.stderr.readline()
            if not line:
                break
            if line.startswith("{"):
                events.append(json.loads(line))
            if any(e.get("event") == "state.change" and e.get("new") == "NAVIGATING" for e in events):
                break
        assert any(e.get("new") == "NAVIGATING" for e in events), events
        vehicle.send_signal(signal.SIGTERM)  # the vehicle process stops: no more HEARTBEATs
        assert vehicle.wait(timeout=30) == 0
        _out, err = companion.communicate(timeout=60)
        assert companion.returncode == 3, err
    finally:
        for proc in (vehicle, companion):
            if proc.poll() is None:
                proc.kill()
                proc.wait()
    events += [json.loads(line) for line in err.splitlines() if line.startswith("{")]
    rec = json.loads(result.read_text())
    assert rec["outcome"] == "link_lost" and rec["state"] == "LINK_LOST"
    lost = [e for e in events if e.get("event") == "link.lost"]
    assert lost and lost[-1]["ends_run"] is True and lost[-1]["lost_s"] > 3.0 and lost[-1]["goal"] == "kept"


def test_exit_when_done_ends_the_run_when_the_autopilot_is_never_heard() -> None:
    """A wrong address or a dead autopilot: no HEARTBEAT ever came, so no goal was taken and a scripted run waited
    for ever. ``max_link_lost_s`` counts from the start then; without ``exit_when_done`` the service waits."""
    svc, clock = _service(exit_when_done=True, max_link_lost_s=20.0)
    start = clock.t
    assert _cycle_at(svc, clock, start + 19.9) is State.IDLE and not svc._stop.is_set()
    _cycle_at(svc, clock, start + 20.1)
    assert svc._stop.is_set() and svc.result().outcome == "link_lost"
    assert _exit_code(svc.result().outcome) == EXIT_STUCK
    waits, wclock = _service(max_link_lost_s=20.0)
    _cycle_at(waits, wclock, wclock.t + 3600.0)
    assert not waits._stop.is_set() and waits.result().outcome == "stopped"
    heard, hclock = _service(exit_when_done=True, max_link_lost_s=20.0)
    hclock.t += 19.0
    _heartbeat(heard, hclock)  # heard at last: the limit counts from the last HEARTBEAT again
    assert _cycle_at(heard, hclock, hclock.t + 2.0) is not State.LINK_LOST and not heard._stop.is_set()
