"""The dependency arrows of docs/architecture.md hold: service -> perception/links -> planning; sim -> public API."""

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


def _public_names(module: str) -> set[str] | None:
    """``__all__`` of an apf_companion module, read from its source (None when it has none)."""
    rel = Path(*module.split("."))
    path = ROOT / (str(rel) + ".py")
    if not path.exists():
        path = ROOT / rel / "__init__.py"
    for node in ast.parse(path.read_text()).body:
        if isinstance(node, ast.Assign) and any(isinstance(t, ast.Name) and t.id == "__all__" for t in node.targets):
            return {ast.literal_eval(e) for e in node.value.elts}  # type: ignore[attr-defined]
    return None


@pytest.mark.parametrize("path", sources("sim"), ids=lambda p: str(p.relative_to(ROOT)))
def test_sim_uses_only_the_public_api(path: Path) -> None:
    """sim imports from apf_companion only names a module exports in ``__all__``, never private modules or names."""
    bad: list[str] = []
    for node in ast.walk(ast.parse(path.read_text(), filename=str(path))):
        if isinstance(node, ast.Import):
            bad += [a.name for a in node.names if a.name.startswith("apf_companion") and "._" in a.name]
        elif isinstance(node, ast.ImportFrom) and node.level == 0 and (node.module or "").startswith("apf_companion"):
            module = node.module or ""
            if any(part.startswith("_") for part in module.split(".")):
                bad.append(module)
                continue
            public = _public_names(module)
            for alias in node.names:
                if alias.name.startswith("_") or public is None or alias.name not in public:
                    bad.append(f"{module}.{alias.name}")
    assert not bad, f"{path} imports non-public apf_companion names: {bad}"
