"""The wheel: builds without deprecation warnings, carries the package data and license, and its commands run.

Building takes ~10-30 s, so the test is marked slow. Installing the wheel with its dependencies into a fresh venv
(what ``pipx install`` does) needs the package index and another ~50 s; it was done by hand (docs/ecosystem.md,
Packaging). Here the wheel is unpacked with ``pip install --no-deps --target`` and run with the dependencies of
this venv, so the code and data that run are the wheel's.
"""

from __future__ import annotations

import os
import subprocess
import sys
import zipfile
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent


@pytest.mark.slow
def test_wheel_builds_cleanly_and_runs(tmp_path: Path) -> None:
    dist = tmp_path / "dist"
    build = subprocess.run(
        [sys.executable, "-m", "pip", "wheel", "--no-deps", "-w", str(dist), str(ROOT)],
        capture_output=True,
        text=True,
        timeout=300,
        env={**os.environ, "PIP_DISABLE_PIP_VERSION_CHECK": "1"},
    )
    assert build.returncode == 0, build.stderr
    assert "deprecat" not in (build.stdout + build.stderr).lower()
    (wheel,) = dist.glob("apf_companion-*.whl")
    with zipfile.ZipFile(wheel) as zf:
        names = set(zf.namelist())
        meta_name = next(n for n in names if n.endswith(".dist-info/METADATA"))
        metadata = zf.read(meta_name).decode()
        entry_points = zf.read(meta_name.replace("METADATA", "entry_points.txt")).decode()
    assert {"sim/world/examples/forest.toml", "apf_companion/py.typed", "sim/py.typed"} <= names
    assert any(n.endswith(".dist-info/licenses/LICENSE") for n in names)
    assert not any(n.startswith(("tests/", "benchmarks/")) for n in names)
    assert "License-Expression: MIT" in metadata
    assert "apf-companion = apf_companion.cli:main" in entry_points
    assert "apf-sim = sim.cli:main" in entry_points

    target = tmp_path / "site"
    unpack = subprocess.run(
        [sys.executable, "-m", "pip", "install", "--no-deps", "--no-index", "--target", str(target), str(wheel)],
        capture_output=True,
        text=True,
        timeout=300,
    )
    assert unpack.returncode == 0, unpack.stderr
    env = {**os.environ, "PYTHONPATH": str(target)}
    for command in ("apf-companion", "apf-sim"):
        result = subprocess.run(
            [str(target / "bin" / command), "--help"], capture_output=True, text=True, timeout=60, env=env
        )
        assert result.returncode == 0, result.stderr
        assert f"usage: {command}" in result.stdout
    where = subprocess.run(
        [sys.executable, "-c", "import sim.world, pathlib; print(pathlib.Path(sim.world.__file__).parent)"],
        capture_output=True,
        text=True,
        timeout=60,
        env=env,
        cwd=tmp_path,
    )
    world_dir = Path(where.stdout.strip())
    assert world_dir.is_relative_to(target)  # the wheel's copy, not the checkout
    bundled = sorted(p.name for p in (ROOT / "sim" / "world" / "examples").glob("*.toml"))
    assert len(bundled) >= 10  # the four first worlds and the six adversarial ones of issue 7
    assert sorted(p.name for p in (world_dir / "examples").glob("*.toml")) == bundled
