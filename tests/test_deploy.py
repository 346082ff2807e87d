"""deploy/: the example config holds every key at its default; the systemd units pass ``systemd-analyze verify``
and rate under 3 in ``systemd-analyze security``;
``install.sh`` (--dry-run, a staged --destdir install, --uninstall) in a temporary root."""

from __future__ import annotations

import configparser
import dataclasses
import itertools
import re
import shlex
import shutil
import subprocess
import sys
import tomllib
from pathlib import Path
from typing import Any

import pytest

from apf_companion.cli import EXIT_CONFIG
from apf_companion.config import ServiceConfig, load_config

DEPLOY = Path(__file__).resolve().parent.parent / "deploy"
UNITS = ("apf-companion.service", "apf-mavproxy.service")
INSTALL = DEPLOY / "install.sh"
SYSTEMD_ANALYZE = shutil.which("systemd-analyze")
needs_systemd_analyze = pytest.mark.skipif(
    SYSTEMD_ANALYZE is None, reason="systemd-analyze not installed (apt-get install systemd; .ci/run installs it)"
)
VENV = Path(sys.executable).parent.parent


def _unit_here(name: str, tmp_path: Path) -> Path:
    """The unit with its /opt venv and /etc env file pointed at files that exist here (verify checks them)."""
    text = (DEPLOY / name).read_text()
    text = text.replace("/opt/apf-companion/venv", str(VENV))
    text = text.replace("/etc/apf-companion/mavproxy.env", str(DEPLOY / "mavproxy.env"))
    path = tmp_path / name
    path.write_text(text)
    return path


def _verify(path: Path) -> subprocess.CompletedProcess[str]:
    assert SYSTEMD_ANALYZE is not None
    return subprocess.run([SYSTEMD_ANALYZE, "verify", str(path)], capture_output=True, text=True, timeout=60)


@needs_systemd_analyze
@pytest.mark.parametrize("name", UNITS)
def test_unit_verifies_without_a_warning(name: str, tmp_path: Path) -> None:
    if name == "apf-mavproxy.service" and not (VENV / "bin" / "mavproxy.py").is_file():
        pytest.skip("MAVProxy not installed in this venv (pip install --no-deps MAVProxy)")
    result = _verify(_unit_here(name, tmp_path))
    assert (result.returncode, result.stderr) == (0, "")


@needs_systemd_analyze
def test_verify_catches_a_typo(tmp_path: Path) -> None:
    path = _unit_here("apf-companion.service", tmp_path)
    path.write_text(path.read_text().replace("ProtectSystem=strict", "ProtectSystem=stricct"))
    assert "Failed to parse protect system value" in _verify(path).stderr


@needs_systemd_analyze
@pytest.mark.parametrize("name", UNITS)
def test_security_exposure_under_3(name: str) -> None:
    assert SYSTEMD_ANALYZE is not None
    result = subprocess.run(
        [SYSTEMD_ANALYZE, "security", "--offline=yes", str(DEPLOY / name)], capture_output=True, text=True, timeout=60
    )
    match = re.search(r"Overall exposure level for \S+: (\d+\.\d+) (\w+)", result.stdout)
    assert match, result.stdout + result.stderr
    assert float(match.group(1)) < 3.0, result.stdout
    assert match.group(2) == "OK"


def _settings(name: str) -> dict[str, list[str]]:
    out: dict[str, list[str]] = {}
    for line in (DEPLOY / name).read_text().splitlines():
        key, sep, value = line.partition("=")
        if sep and not line.startswith("#"):
            out.setdefault(key.strip(), []).append(value.strip())
    return out


@pytest.mark.parametrize("name", UNITS)
def test_unit_sandbox_settings(name: str) -> None:
    s = _settings(name)
    assert s["User"] == ["apf"]
    assert s["ProtectSystem"] == ["strict"]
    assert s["CapabilityBoundingSet"] == [""]
    assert s["DevicePolicy"] == ["closed"]
    assert s["DeviceAllow"] == ["/dev/serial0 rw"]
    assert s["RestrictAddressFamilies"] == ["AF_INET AF_INET6 AF_UNIX"]
    assert s["SystemCallFilter"][0] == "@system-service"
    for key in ("NoNewPrivileges", "ProtectHome", "PrivateTmp"):
        assert s[key] == ["yes"]
    state = s["StateDirectory"][0]
    assert s["ReadWritePaths"] == [f"/var/lib/{state}"]


def test_the_service_unit_uses_notify_and_the_watchdog() -> None:
    """apf_companion/sdnotify.py: READY=1 from the main process, WATCHDOG=1 from the planning cycle."""
    s = _settings("apf-companion.service")
    assert s["Type"] == ["notify"] and s["NotifyAccess"] == ["main"]
    assert float(s["WatchdogSec"][0]) >= 1.0  # many 10 Hz cycles per half period, even on a loaded computer
    assert s["Restart"] == ["on-failure"]  # a watchdog kill is a failure: restarted


def test_config_errors_are_not_restarted() -> None:
    assert _settings("apf-companion.service")["RestartPreventExitStatus"] == [str(EXIT_CONFIG)]


def test_no_start_command_fails_around_the_restart_rule() -> None:
    """RestartPreventExitStatus= applies to the main process only, and Restart=on-failure also restarts after a
    failing ExecStartPre= / ExecStartPost= (systemd.service(5)): a config check there was restarted until the start
    limit. So the unit has none that can fail (a "-" prefix ignores the failure); `run` checks its config itself."""
    s = _settings("apf-companion.service")
    can_fail = [v for key in ("ExecStartPre", "ExecStartPost") for v in s.get(key, []) if not v.startswith("-")]
    assert can_fail == []


@pytest.mark.parametrize(
    ("config", "message"),
    [
        ('[link]\nconnectt = "udpin:127.0.0.1:14540"\n', "unknown config key 'link.connectt'"),
        ('[goal]\nroute = "no-such-route.toml"\n', "cannot read route file"),
        ('[planner]\nname = "bapf-nav"\n[planner.params]\nrho_l_m = -1.0\n', "rho_l_m"),
    ],
    ids=["unknown-key", "route-file", "planner-parameter"],
)
def test_the_units_command_exits_with_a_status_it_does_not_restart(config: str, message: str, tmp_path: Path) -> None:
    """The unit's own ExecStart with a bad config: the exit status is in RestartPreventExitStatus (a route file
    that could not be read was exit 1 before, restarted), said on stderr (the journal), before any socket opens."""
    s = _settings("apf-companion.service")
    argv = shlex.split(s["ExecStart"][0].replace("/opt/apf-companion/venv", str(VENV)))
    path = tmp_path / "apf-companion.toml"
    path.write_text(config)
    argv[argv.index("--config") + 1] = str(path)
    result = subprocess.run(argv, capture_output=True, text=True, timeout=120, check=False)
    assert str(result.returncode) in s["RestartPreventExitStatus"][0].split(), result.stderr
    assert message in result.stderr


def test_the_mavlink_router_sample_opens_no_tcp_server() -> None:
    """mavlink-router's TCP server (all interfaces, vehicle control) is off: TcpServerPort = 0, since an absent key
    means 5760 (its examples/config.sample); the service's endpoint is UDP to localhost."""
    conf = configparser.ConfigParser()
    conf.read_string((DEPLOY / "mavlink-router.conf").read_text())
    assert conf["General"]["TcpServerPort"] == "0"
    service = conf["UdpEndpoint apf-companion"]
    assert (service["Mode"], service["Address"], service["Port"]) == ("Normal", "127.0.0.1", "14540")
    assert not [s for s in conf.sections() if s.lower().startswith("tcpendpoint")]


def _install(*args: str) -> subprocess.CompletedProcess[str]:
    return subprocess.run(["bash", str(INSTALL), *args], capture_output=True, text=True, timeout=120, check=False)


def test_dry_run_prints_the_plan_and_changes_nothing(tmp_path: Path) -> None:
    root = tmp_path / "root"
    root.mkdir()
    result = _install("--dry-run", "--with-mavproxy", "--destdir", str(root))
    assert result.returncode == 0, result.stderr
    out = result.stdout
    assert f"would run: python3 -m venv {root}/opt/apf-companion/venv" in out
    assert f"would write: {root}/etc/systemd/system/apf-companion.service" in out
    assert f"would write: {root}/etc/systemd/system/apf-mavproxy.service" in out
    assert "skipped (--destdir): systemctl enable apf-companion.service" in out
    assert not any(root.iterdir())
    plain = _install("--dry-run", "--destdir", str(root))
    assert plain.returncode == 0, plain.stderr
    assert "apf-mavproxy" not in plain.stdout
    assert "would run:" in plain.stdout
    assert not any(root.iterdir())


def test_staged_install_keeps_config_and_uninstalls(tmp_path: Path) -> None:
    root = tmp_path / "root"
    result = _install("--destdir", str(root), "--no-venv", "--with-mavproxy", "--prefix", "/opt/apf")
    assert result.returncode == 0, result.stderr
    unit = (root / "etc/systemd/system/apf-companion.service").read_text()
    assert "ExecStart=/opt/apf/venv/bin/apf-companion run --config /etc/apf-companion/apf-companion.toml" in unit
    assert "/opt/apf-companion" not in unit.replace("apf-companion.service", "")
    config = root / "etc/apf-companion/apf-companion.toml"
    assert 'tlog = "/var/lib/apf-companion/companion.tlog"' in config.read_text()
    assert (root / "etc/apf-companion/mavproxy.env").is_file()
    assert (root / "etc/systemd/system/apf-mavproxy.service").stat().st_mode & 0o777 == 0o644

    config.write_text(config.read_text() + "# edited\n")
    again = _install("--destdir", str(root), "--no-venv")
    assert "kept existing" in again.stdout
    assert config.read_text().endswith("# edited\n")

    removed = _install("--destdir", str(root), "--uninstall")
    assert removed.returncode == 0, removed.stderr
    assert not list((root / "etc/systemd/system").iterdir())
    assert config.is_file()  # kept without --purge
    purged = _install("--destdir", str(root), "--uninstall", "--purge")
    assert purged.returncode == 0, purged.stderr
    assert not (root / "etc/apf-companion").exists()


def test_install_help_prints_the_comment_block_only() -> None:
    """--help prints the script's leading comment block without its "# " and stops there (it printed a fixed line
    range that ended with `set -euo pipefail`)."""
    result = _install("--help")
    assert (result.returncode, result.stderr) == (0, "")
    lines = INSTALL.read_text().splitlines()[1:]
    block = [re.sub(r"^# ?", "", line) for line in itertools.takewhile(lambda line: line.startswith("#"), lines)]
    assert result.stdout.splitlines() == block
    assert block[0].startswith("Install apf-companion as a sandboxed systemd service")
    assert "--no-venv" in block[-1]
    assert "set -euo pipefail" not in result.stdout


@pytest.mark.parametrize(
    ("args", "message"),
    [
        (["--purge"], "--purge goes with --uninstall"),
        (["--prefix", "opt/x", "--dry-run"], "--prefix must be an absolute path"),
        (["--bogus"], "unknown option --bogus"),
    ],
)
def test_install_option_errors(args: list[str], message: str) -> None:
    result = _install(*args)
    assert result.returncode == 2
    assert message in result.stderr


def _uncommented(text: str) -> dict[str, Any]:
    """The example config with its commented-out keys and sections (``# [goal]``, ``# north_m = 22.0``) read too."""
    lines = (re.sub(r"^# (?=\[[a-z_.]+\]|[a-z_]+ = )", "", line) for line in text.splitlines())
    return tomllib.loads("\n".join(lines))


def test_the_example_config_holds_every_key_at_its_default() -> None:
    """deploy/apf-companion.toml says "Every value below is the default": every key of every section is there (set,
    or commented out where a value would change behaviour: [goal], [planner.params]), and what it sets is the
    default."""
    path = DEPLOY / "apf-companion.toml"
    cfg = load_config(path)
    assert cfg == ServiceConfig(base_dir=cfg.base_dir)
    data = _uncommented(path.read_text())
    missing = []
    for section in dataclasses.fields(ServiceConfig):
        if section.name == "base_dir":
            continue
        kind = section.default_factory if section.default_factory is not dataclasses.MISSING else None
        if isinstance(kind, type) and dataclasses.is_dataclass(kind):
            keys = data.get(section.name, {})
            missing += [f"{section.name}.{f.name}" for f in dataclasses.fields(kind) if f.name not in keys]
        elif section.name not in data:
            missing.append(section.name)
    assert missing == []
