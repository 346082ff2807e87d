"""``apf-sim fly --signing-key``: both processes get the key (the service's config, the vehicle's argv), and a key
file others can read stops the flight before anything starts. The signed flight itself is in
tests/service/test_service_signing.py (in-process) and docs/hardening.md (this command, measured)."""

from __future__ import annotations

import os
from pathlib import Path

import pytest

from apf_companion.config import load_config
from sim.cli import main as sim_main
from sim.fly import FlyOptions, _service_toml, _sim_argv


def test_fly_gives_both_processes_the_key(tmp_path: Path) -> None:
    key = tmp_path / "apf.key"
    key.write_bytes(bytes(range(32)))
    opt = FlyOptions(signing_key=key, out=tmp_path / "out")
    toml = tmp_path / "service.toml"
    toml.write_text(_service_toml(opt, 14550, tmp_path / "c.tlog"))
    link = load_config(toml).link
    assert link.signing_key_file == str(key.resolve()) and link.require_signed_telemetry
    assert link.signing_timestamp_file == str((tmp_path / "out" / "signing.timestamp").resolve())
    argv = _sim_argv(opt, 14550, 14551)
    assert argv[argv.index("--signing-key") + 1] == str(key.resolve())
    unsigned = FlyOptions(out=tmp_path / "out")
    toml.write_text(_service_toml(unsigned, 14550, tmp_path / "c.tlog"))
    assert load_config(toml).link.signing_key_file == "" and "--signing-key" not in _sim_argv(unsigned, 1, 2)


def test_fly_refuses_a_key_file_others_can_read(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    key = tmp_path / "apf.key"
    key.write_bytes(bytes(range(32)))
    os.chmod(key, 0o644)
    assert sim_main(["fly", "--world", "corridor", "--signing-key", str(key), "--out", str(tmp_path / "o")]) == 2
    err = capsys.readouterr().err
    assert str(key) in err and "0o644" in err
    assert not (tmp_path / "o").exists()
