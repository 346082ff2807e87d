"""MAVProxy as a ground station in tests: where it is installed (``pip install --no-deps MAVProxy``), and an
interactive session typed at its prompt."""

from __future__ import annotations

import asyncio
import contextlib
import shutil
import sys
from collections.abc import AsyncIterator
from pathlib import Path

from tests.conftest import HANG_S, reap

__all__ = ["MavproxyPrompt", "mavproxy_path", "mavproxy_session"]


def mavproxy_path() -> str | None:
    """mavproxy.py beside this interpreter (installed --no-deps in the venv), else on PATH."""
    beside = Path(sys.executable).parent / "mavproxy.py"
    return str(beside) if beside.is_file() else shutil.which("mavproxy.py")


class MavproxyPrompt:
    """An interactive MAVProxy process: what it printed (``lines``), lines typed at its prompt."""

    def __init__(self, proc: asyncio.subprocess.Process) -> None:
        self.proc = proc
        self.lines: list[str] = []

    async def read_until(self, needle: str) -> None:
        assert self.proc.stdout is not None
        while not any(needle in line for line in self.lines):
            line = (await self.proc.stdout.readline()).decode(errors="replace")
            if not line:
                raise AssertionError(f"MAVProxy exited; output: {self.lines}")
            self.lines.append(line.rstrip())

    def type_in(self, command: str) -> None:
        assert self.proc.stdin is not None
        self.proc.stdin.write(command.encode() + b"\n")


@contextlib.asynccontextmanager
async def mavproxy_session(mavproxy: str, master: str, component: str, basedir: Path) -> AsyncIterator[MavproxyPrompt]:
    """MAVProxy on ``master``, talking to system 1, ``component``; its prompt, within 2 x HANG_S (it starts slowly
    on a loaded machine); "exit" typed at the end (an interactive MAVProxy waits long on SIGTERM)."""
    proc = await asyncio.create_subprocess_exec(
        sys.executable, "-u", mavproxy, f"--master={master}", "--target-system=1",
        f"--target-component={component}", f"--state-basedir={basedir}",
        stdin=asyncio.subprocess.PIPE, stdout=asyncio.subprocess.PIPE, stderr=asyncio.subprocess.STDOUT,
        cwd=basedir,
    )  # fmt: skip
    prompt = MavproxyPrompt(proc)
    try:
        async with asyncio.timeout(HANG_S * 2):
            yield prompt
    finally:
        if proc.returncode is None:
            prompt.type_in("exit")
            assert proc.stdin is not None
            proc.stdin.close()
            await reap(proc)
