"""apf-companion command line: check-config, config errors, overrides, a short real run."""

from __future__ import annotations

import dataclasses
import json
import os
import signal
import socket
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

import pytest

from apf_companion.cli import build_parser, main
from apf_companion.planning import ALL_PLANNER_NAMES, DEFAULT_PLANNER, PlannerParams
from tests.conftest import HANG_S, free_port

REPO = Path(__file__).resolve().parents[2]


def test_check_config_ok_prints_effective_config(capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["check-config", str(REPO / "deploy" / "apf-companion.toml")]) == 0
    out = json.loads(capsys.readouterr().out)
    assert out["cycle"]["rate_hz"] == 10.0 and out["autopilot"]["profile"] == "ardupilot"


def test_check_config_prints_the_planner_parameters_in_effect(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """Not only the overrides: the preset's values with the overrides applied, every PlannerParams field."""
    cfg = tmp_path / "c.toml"
    cfg.write_text('[planner]\npreset = "paper"\n[planner.params]\nrho_l_m = 0.5\n')
    assert main(["check-config", str(cfg)]) == 0
    params = json.loads(capsys.readouterr().out)["planner"]["params"]
    expected = dataclasses.replace(PlannerParams.from_preset("paper"), rho_l_m=0.5)
    assert set(params) == {f.name for f in dataclasses.fields(PlannerParams)}
    assert params["rho_l_m"] == 0.5 and params["step_m"] == expected.step_m and params["dim"] == 2


def _not_used(tmp_path: Path, capsys: pytest.CaptureFixture[str], toml: str) -> tuple[dict[str, Any], dict[str, str]]:
    cfg = tmp_path / "c.toml"
    cfg.write_text(toml)
    assert main(["check-config", str(cfg)]) == 0
    out = json.loads(capsys.readouterr().out)
    return out["planner"], out["not_used"]


@pytest.mark.parametrize("planner", [p for p in ALL_PLANNER_NAMES if p != "bapf-nav"])
def test_check_config_says_the_fence_settings_are_not_used_by_planners_that_ignore_the_fence(
    planner: str, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """Only bapf-nav plans over the autopilot's fence (service._fence_reader): for the paper's planners and
    bendyruler check-config printed fence_area = true as if the fence would be read."""
    section, not_used = _not_used(tmp_path, capsys, f'[planner]\nname = "{planner}"\nfence_area = true\n')
    assert section["fence_area"] is True and section["fence_poll_s"] == 5.0  # what the file says, printed
    why = f"only bapf-nav plans over the autopilot's fence; {planner} does not read it"
    assert not_used["planner.fence_area"] == why and not_used["planner.fence_poll_s"] == why
    assert not_used["planner.params.nav_*"] == f"bapf-nav's parameters; {planner} does not read them"
    assert ("planner.params.br_*" in not_used) is (planner != "bendyruler")
    assert ("planner.params.capf_*" in not_used) is (planner != "capf")


def test_check_config_says_when_bapf_nav_does_not_read_the_fence(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    _, not_used = _not_used(tmp_path, capsys, "")  # the default: bapf-nav reads the fence
    assert not any(k.startswith(("planner.fence", "planner.params.nav_")) for k in not_used)
    assert set(not_used) == {"planner.params.br_*", "planner.params.capf_*"}
    area = "[planner.params]\nnav_area_ne_m = [-5.0, -5.0, 30.0, 30.0]\n"
    _, not_used = _not_used(tmp_path, capsys, area)
    assert "the config's zones win" in not_used["planner.fence_area"] and "planner.fence_poll_s" in not_used
    _, not_used = _not_used(tmp_path, capsys, "[planner]\nfence_area = false\n")
    assert "planner.fence_area" not in not_used  # false is the setting in effect
    assert not_used["planner.fence_poll_s"] == "planner.fence_area is false: the fence is not read"
    _, not_used = _not_used(tmp_path, capsys, "dry_run = true\n")
    assert "dry run" in not_used["planner.fence_area"]


def test_check_config_names_the_bad_key(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    bad = tmp_path / "bad.toml"
    bad.write_text("[link]\ncomponent_id = 400\n")
    assert main(["check-config", str(bad)]) == 2
    assert "link.component_id must be an integer in [1, 255], got 400" in capsys.readouterr().err
    typo = tmp_path / "typo.toml"
    typo.write_text("[planner]\nnmae = 'bapf'\n")
    assert main(["check-config", str(typo)]) == 2
    assert "did you mean 'name'" in capsys.readouterr().err
    typo.write_text("[planner.params]\nvehicle_radus_m = 0.3\n")
    assert main(["check-config", str(typo)]) == 2
    assert "planner.params.vehicle_radus_m; did you mean 'vehicle_radius_m'?" in capsys.readouterr().err


def test_run_refuses_bad_overrides(capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["run", "--planner", "apf"]) == 2
    assert "planner.name must be one of" in capsys.readouterr().err
    assert main(["run", "--goal", "1,nope"]) == 2
    assert "--goal must be 'NORTH,EAST[,DOWN]'" in capsys.readouterr().err


def test_run_dry_run_process_stops_cleanly_on_sigint(tmp_path: Path) -> None:
    """Two Ctrl-C in quick succession stop it as one does (exit 0, not 130); --result-json's directory is created
    (as --tlog's is), so the result is not lost at exit."""
    result = tmp_path / "not" / "yet" / "result.json"
    proc = subprocess.Popen(
        [
            sys.executable,
            "-m",
            "apf_companion",
            "run",
            "--connect",
            "udpin:127.0.0.1:0",
            "--dry-run",
            "--goal",
            "10,0,-5",
            "--result-json",
            str(result),
        ],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        env=os.environ | {"OPENBLAS_NUM_THREADS": "1"},
    )
    try:
        deadline = time.monotonic() + 30.0
        assert proc.stderr is not None
        while time.monotonic() < deadline:
            line = proc.stderr.readline()
            if "service.start" in line:
                break
        proc.send_signal(signal.SIGINT)
        proc.send_signal(signal.SIGINT)
        assert proc.wait(timeout=20) == 0, proc.stderr.read()
    finally:
        if proc.poll() is None:
            proc.kill()
    rec = json.loads(result.read_text())
    assert rec["outcome"] == "stopped" and rec["state"] == "IDLE"
    assert rec["counters"]["setpoints_sent"] == 0
    # The startup heap (tens of thousands of objects: numpy, pymavlink's dialect, the service) was frozen before
    # the flight, so no full collection walks it mid-flight (apf_companion/heap.py).
    assert rec["gc"]["frozen"] > 10_000


def test_check_config_refuses_the_autopilots_own_ids_for_the_companion(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """A review's config (``component_id = 1``) passed: the service would have sent HEARTBEAT and setpoints as 1/1,
    the autopilot's ids (we send with its system id). Another component id with the same autopilot passes."""
    bad = tmp_path / "bad.toml"
    bad.write_text("[link]\ncomponent_id = 1\n")
    assert main(["check-config", str(bad)]) == 2
    assert "link.component_id must be different from link.autopilot_compid" in capsys.readouterr().err
    bad.write_text("[link]\nautopilot_compid = 196\ncomponent_id = 196\n")
    assert main(["check-config", str(bad)]) == 2
    assert "link.component_id" in capsys.readouterr().err
    bad.write_text("[link]\nautopilot_compid = 1\ncomponent_id = 196\n")
    assert main(["check-config", str(bad)]) == 0


def test_check_config_refuses_a_connection_string_run_would_refuse(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    bad = tmp_path / "bad.toml"
    bad.write_text('[link]\nconnect = "udpin:127.0.0.1"\n')  # no port
    assert main(["check-config", str(bad)]) == 2
    assert "link.connect" in capsys.readouterr().err
    bad.write_text('[link]\nconnect = "com3:57600"\n')
    assert main(["check-config", str(bad)]) == 2
    assert "unknown scheme 'com3'" in capsys.readouterr().err


@pytest.mark.parametrize(
    ("argv", "env", "says"),
    [
        (["--log-level", "LOUD", "check-config", "x.toml"], {}, "invalid log level 'LOUD'"),
        (["--log-format", "xml", "check-config", "x.toml"], {}, "invalid log format 'xml'"),
        (["check-config", "x.toml"], {"APF_LOG_FORMAT": "yaml"}, "invalid log format 'yaml'"),
        (["check-config", "x.toml"], {"APF_LOG_LEVEL": "verbose"}, "invalid log level 'verbose'"),
    ],
)
def test_bad_log_level_or_format_is_a_clear_error(
    argv: list[str], env: dict[str, str], says: str, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    for key, value in env.items():
        monkeypatch.setenv(key, value)
    with pytest.raises(SystemExit) as exc:
        main(argv)
    assert exc.value.code == 2
    err = capsys.readouterr().err
    assert says in err and "Traceback" not in err


@pytest.mark.parametrize("name", ["APF_LOG_LEVEL", "APF_LOG_FORMAT"])
def test_an_empty_log_variable_counts_as_unset(
    name: str, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    monkeypatch.setenv(name, "")
    assert main(["check-config", str(REPO / "deploy" / "apf-companion.toml")]) == 0
    assert "OK" in capsys.readouterr().err
    args = build_parser().parse_args(["check-config", "x.toml"])
    assert (args.log_level, args.log_format) == ("INFO", "text")


def test_run_help_lists_every_registered_planner(
    monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    monkeypatch.setenv("COLUMNS", "400")  # one line per option: no name broken at a hyphen
    with pytest.raises(SystemExit) as exc:
        main(["run", "--help"])
    assert exc.value.code == 0
    line = next(x for x in capsys.readouterr().out.splitlines() if x.lstrip().startswith("--planner"))
    assert f"default {DEFAULT_PLANNER};" in line
    assert line.endswith(f"one of {', '.join(ALL_PLANNER_NAMES)})")
    assert {"bapf-nav", "bendyruler", "cr-bapf*"} <= set(ALL_PLANNER_NAMES)


def test_a_startup_error_is_said_once(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    result = tmp_path / "result.json"
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as taken:
        taken.bind(("127.0.0.1", 0))
        port = taken.getsockname()[1]
        argv = ["run", "--connect", f"udpin:127.0.0.1:{port}", "--dry-run", "--result-json", str(result)]
        assert main(argv) == 1
    err = capsys.readouterr().err
    lines = [line for line in err.splitlines() if "cannot open MAVLink endpoint" in line]
    assert len(lines) == 1, err  # not also as an ERROR log line
    assert lines[0].startswith(f"apf-companion: cannot open MAVLink endpoint udpin:127.0.0.1:{port}: ")
    assert "service.open_failed" not in err
    rec = json.loads(result.read_text())  # the run ended while opening: its result is written all the same
    assert rec["outcome"] == "error" and f"apf-companion: {rec['error']}" == lines[0] and rec["steps"] == 0


def test_an_unreachable_zenoh_router_is_said_plainly_and_the_result_written(tmp_path: Path) -> None:
    """The bug: with the zenoh router down, `run` logged a WARNING per attempt (14 in 60 s) carrying a Python repr
    and zenoh's Rust source paths, and its final error wrote no --result-json. A real process (zenoh's own
    logging would write to its stdout; RUST_LOG set, as a user debugging it might) and a real zenoh client."""
    router = f"tcp/127.0.0.1:{free_port()}"  # nothing listens there
    cfg = tmp_path / "zenoh.toml"
    cfg.write_text(
        f'[link]\nconnect = "udpin:127.0.0.1:0"\n[zenoh]\nenabled = true\nmode = "client"\n'
        f'connect = ["{router}"]\nrouter_wait_s = 1.5\n'
    )
    result = tmp_path / "result.json"
    argv = [sys.executable, "-m", "apf_companion", "run", "--config", str(cfg), "--result-json", str(result)]
    env = os.environ | {"OPENBLAS_NUM_THREADS": "1", "RUST_LOG": "debug"}
    proc = subprocess.run(argv, capture_output=True, text=True, env=env, timeout=HANG_S, check=False)
    assert proc.returncode == 1, proc.stderr
    lines = proc.stderr.splitlines()
    assert [line for line in lines if "WARNING" in line or "ERROR" in line] == [
        next(line for line in lines if "zenoh.router_unreachable" in line)
    ]  # one warning, whatever the attempts
    assert f"router={router} attempts=1 " in lines[0] and "then giving up (the service exits 1)" in lines[0]
    said = f"apf-companion: zenoh router at {router} unreachable: gave up after 1."
    assert lines[-1].startswith(said) and len(lines) == 2, proc.stderr
    for text in (proc.stdout, proc.stderr):
        assert "ZenohConfig(" not in text and ".rs:" not in text and "zenoh::" not in text, text
    rec = json.loads(result.read_text())
    assert rec["outcome"] == "error" and f"apf-companion: {rec['error']}" == lines[-1]


def test_a_stop_while_waiting_for_the_zenoh_router_ends_the_run_with_its_result(tmp_path: Path) -> None:
    """SIGTERM while the service waits for its router (router_wait_s 60 s): stopped at once, exit 0, the result
    written (outcome stopped), not left for the wait to run out."""
    cfg = tmp_path / "zenoh.toml"
    cfg.write_text(
        f'[link]\nconnect = "udpin:127.0.0.1:0"\n[zenoh]\nenabled = true\nmode = "client"\n'
        f'connect = ["tcp/127.0.0.1:{free_port()}"]\n'
    )
    result = tmp_path / "result.json"
    argv = [sys.executable, "-m", "apf_companion", "run", "--config", str(cfg), "--result-json", str(result)]
    proc = subprocess.Popen(argv, stderr=subprocess.PIPE, text=True, env=os.environ | {"OPENBLAS_NUM_THREADS": "1"})
    try:
        assert proc.stderr is not None
        line = proc.stderr.readline()  # blocks until the first failed attempt is said
        assert "zenoh.router_unreachable" in line, line
        proc.send_signal(signal.SIGTERM)
        assert proc.wait(timeout=HANG_S) == 0, proc.stderr.read()
    finally:
        if proc.poll() is None:
            proc.kill()
    rec = json.loads(result.read_text())
    assert rec["outcome"] == "stopped" and rec["error"] is None and rec["steps"] == 0


@pytest.mark.parametrize("where", ["file_as_dir", "dir"])
def test_a_result_json_path_that_cannot_be_written_fails_at_start(
    where: str, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    (tmp_path / "plain").write_text("")
    path = tmp_path / "plain" / "result.json" if where == "file_as_dir" else tmp_path
    argv = ["run", "--connect", "udpin:127.0.0.1:0", "--dry-run", "--result-json", str(path)]
    assert main(argv) == 1  # before anything opens: no run to lose
    err = capsys.readouterr().err
    assert err.startswith(f"apf-companion: --result-json {path}: cannot write the result there (")
    assert "Traceback" not in err and "service.start" not in err
