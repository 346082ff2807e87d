"""``apf-sim``'s own options and its subcommands' user-facing errors (in-process: exit code and stderr)."""

from __future__ import annotations

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
