"""``--version`` of both commands comes from the installed distribution's metadata."""

from __future__ import annotations

import importlib.metadata
from collections.abc import Callable, Sequence

import pytest

from apf_companion.cli import main as companion_main
from sim.cli import main as sim_main


@pytest.mark.parametrize(("prog", "main"), [("apf-companion", companion_main), ("apf-sim", sim_main)])
def test_version_is_the_installed_distributions(
    prog: str, main: Callable[[Sequence[str] | None], int], capsys: pytest.CaptureFixture[str]
) -> None:
    with pytest.raises(SystemExit) as stop:
        main(["--version"])
    assert stop.value.code == 0
    version = importlib.metadata.version("apf-companion")
    assert version.count(".") >= 2
    assert capsys.readouterr().out == f"{prog} {version}\n"
