"""``apf-sim``'s own options and its subcommands' user-facing errors (in-process: exit code and stderr)."""

from __future__ import annotations

import sys
from pathlib import Path

import pytest

from sim.cli import build_parser, main


@pytest.mark.parametrize(
    ("argv", "env", "says"),
    [
        (["--log-level", "bogus", "study"], {}, "invalid log level 'bogus'"),
        (["study"], {"APF_LOG_LEVEL": "bogus"}, "invalid log level 'bogus'"),
    ],
)
def test_bad_log_level_is_a_clear_error_like_apf_companions(
    argv: list[str], env: dict[str, str], says: str, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    for key, value in env.items():
        monkeypatch.setenv(key, value)
    with pytest.raises(SystemExit) as exc:
        main(argv)
    assert exc.value.code == 2
    err = capsys.readouterr().err
    assert says in err and "choose from DEBUG, INFO, WARNING, ERROR, CRITICAL" in err
    assert "Traceback" not in err


@pytest.mark.parametrize(("env", "level"), [(None, "WARNING"), ("", "WARNING"), ("debug", "DEBUG")])
def test_log_level_default_comes_from_the_environment_and_empty_counts_as_unset(
    env: str | None, level: str, monkeypatch: pytest.MonkeyPatch
) -> None:
    if env is None:
        monkeypatch.delenv("APF_LOG_LEVEL", raising=False)
    else:
        monkeypatch.setenv("APF_LOG_LEVEL", env)
    args = build_parser().parse_args(["study"])
    assert args.log_level == level
    assert build_parser().parse_args(["--log-level", "info", "study"]).log_level == "INFO"


def _without(monkeypatch: pytest.MonkeyPatch, *modules: str) -> None:
    """Make ``import <module>`` fail in this process, as on an install without the extra."""
    for module in modules:
        monkeypatch.setitem(sys.modules, module, None)


def test_study_plots_without_matplotlib_stops_before_the_study(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    _without(monkeypatch, "matplotlib")
    plots = tmp_path / "plots"
    argv = ["study", "--trials", "1", "--workers", "1", "--planners", "bapf", "--no-progress", "--plots", str(plots)]
    assert main(argv) == 2
    out, err = capsys.readouterr()
    assert err == "apf-sim study: --plots needs matplotlib: pip install 'apf-companion[sim]'\n"
    assert out == "" and not plots.exists()  # no table: the study did not run


def test_sweep_heatmaps_without_matplotlib_stop_before_the_sweep(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    _without(monkeypatch, "matplotlib")
    out_dir = tmp_path / "sweep"
    argv = ["sweep", "--param", "mu_o=100", "--trials", "1", "--workers", "1", "--no-progress", "--out", str(out_dir)]
    assert main(argv) == 2
    out, err = capsys.readouterr()
    assert "needs matplotlib: pip install 'apf-companion[sim]'" in err and "--no-plots" in err
    assert out == "" and not out_dir.exists()


@pytest.mark.parametrize(
    ("missing", "says"),
    [
        ("matplotlib", "apf-sim mcap-plot needs matplotlib: pip install 'apf-companion[sim]'"),
        ("mcap", "apf-sim mcap-plot needs mcap: pip install 'apf-companion[viz]'"),
        ("mcap_protobuf", "apf-sim mcap-plot needs mcap-protobuf-support: pip install 'apf-companion[viz]'"),
    ],
)
def test_mcap_plot_names_the_missing_extra(
    missing: str, says: str, tmp_path: Path, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    _without(monkeypatch, missing)
    assert main(["mcap-plot", str(tmp_path / "flight.mcap"), "-o", str(tmp_path / "flight.png")]) == 2
    assert capsys.readouterr().err == says + "\n"


def test_sensor_without_an_output_names_the_flags(capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["sensor", "--autopilot", "udpin:127.0.0.1:9"]) == 2
    err = capsys.readouterr().err
    assert err.startswith("apf-sim sensor: needs an output: --output ENDPOINT")
    assert "--zenoh-connect/--zenoh-listen, or --to-autopilot" in err
    assert "also_to_autopilot" not in err and "outputs" not in err


_SENSOR = ["sensor", "--autopilot", "udpin:127.0.0.1:9", "--output", "udpout:127.0.0.1:9"]


@pytest.mark.parametrize(
    ("flag", "value", "says"),
    [
        ("--rate", "0", "argument --rate: must be a number in [0.1, 100] Hz, got '0'"),
        ("--dropout", "2", "argument --dropout: must be a number in [0, 1], got '2'"),
        ("--noise", "-1", "argument --noise: must be a number in [0, inf) m, got '-1'"),
        ("--noise", "inf", "argument --noise: must be a number in [0, inf) m, got 'inf'"),
        ("--range", "nan", "argument --range: must be a number in (0, inf) m, got 'nan'"),
        ("--sysid", "0", "argument --sysid: must be an integer in [1, 255], got '0'"),
        ("--compid", "300", "argument --compid: must be an integer in [1, 255], got '300'"),
    ],
)
def test_sensor_flags_are_checked_at_parsing_by_their_names(
    flag: str, value: str, says: str, capsys: pytest.CaptureFixture[str]
) -> None:
    with pytest.raises(SystemExit) as exc:
        main([*_SENSOR, flag, value])
    assert exc.value.code == 2
    assert says in capsys.readouterr().err


def test_sensor_min_range_must_be_below_its_range(capsys: pytest.CaptureFixture[str]) -> None:
    assert main([*_SENSOR, "--min-range", "9"]) == 2
    assert capsys.readouterr().err == "apf-sim sensor: --min-range (9 m) must be less than --range (8 m)\n"


@pytest.mark.parametrize("item", ["FENCE_MARGIN=abc", "FENCE_MARGIN", "=1", "FENCE_MARGIN=nan"])
def test_vehicle_param_is_checked_at_parsing_as_flys(item: str, capsys: pytest.CaptureFixture[str]) -> None:
    """``apf-sim vehicle --param`` takes the same NAME=VALUE check as ``apf-sim fly --vehicle-param``."""
    with pytest.raises(SystemExit) as exc:
        main(["vehicle", "--param", item])
    assert exc.value.code == 2
    assert f"argument --param: must be NAME=VALUE with a finite number VALUE, got {item!r}" in capsys.readouterr().err
