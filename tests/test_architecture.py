"""The README's dependency arrows hold: service -> perception/links -> planning; sim -> public API only."""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]


def imported_modules(path: Path) -> set[str]:
    tree = ast.parse(path.read_text(), filename=str(path))
    names: set[str] = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            names.update(alias.name for alias in node.names)
        elif isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
            names.add(node.module)
    return names


def sources(package: str) -> list[Path]:
    return sorted((ROOT / package).rglob("*.py"))


@pytest.mark.parametrize("path", sources("apf_companion"), ids=lambda p: str(p.relative_to(ROOT)))
def test_apf_companion_never_imports_sim(path: Path) -> None:
    bad = {m for m in imported_modules(path) if m == "sim" or m.startswith("sim.")}
    assert not bad, f"{path} imports {bad}"


IO_MODULES = {"socket", "asyncio", "logging", "time", "zenoh", "pymavlink", "serial", "random", "threading"}


@pytest.mark.parametrize("path", sources("apf_companion/planning"), ids=lambda p: str(p.relative_to(ROOT)))
def test_planning_core_is_pure(path: Path) -> None:
    mods = imported_modules(path)
    bad = {m for m in mods if m.split(".")[0] in IO_MODULES}
    assert not bad, f"{path} imports I/O or global-state modules {bad}"
    upper = ("apf_companion.service", "apf_companion.links", "apf_companion.perception")
    upward = {m for m in mods if m.startswith(upper)}
    assert not upward, f"{path} imports upward: {upward}"


@pytest.mark.parametrize("path", sources("apf_companion/perception"), ids=lambda p: str(p.relative_to(ROOT)))
def test_perception_does_not_import_the_service(path: Path) -> None:
    bad = {m for m in imported_modules(path) if m.startswith(("apf_companion.service", "apf_companion.cli"))}
    assert not bad, f"{path} imports {bad}"
