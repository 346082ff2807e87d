"""Shared test helpers: free loopback ports, and waiting on conditions instead of sleeping.

Tests here must pass on a loaded machine (see docs/testing.md): a wait is on a condition, a message or the
simulated clock, and its deadline only bounds a hang. ``HANG_S`` is that deadline for things that should
happen at once.
"""

from __future__ import annotations

import asyncio
import itertools
import os
import random
import socket
import zlib
from collections.abc import Callable
from typing import TYPE_CHECKING, Generic, Protocol, TypeVar

import pytest

from apf_companion.service import ServiceClock
from sim.vehicle import testing as sim_testing

if TYPE_CHECKING:
    from sim.vehicle import Simulator

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

HANG_S = 30.0  # wall seconds: only reached when something hangs
POLL_S = 0.01  # how often ``until`` looks again
TICK_S = 1e-6  # resolution of SimulatorClock


#: ``free_port``'s ports lie below Linux's ephemeral range (32768-60999 by default), so no bind to port 0 on the
#: machine is handed one between the pick and the test's own bind. Each pytest-xdist worker ("gw0", "gw1", ...)
#: of a run has its own block of them, so two workers never pick the same port; the run's blocks are rotated by
#: its id, and a process starts at a random place in its block, so two runs at once are unlikely to meet.
PORT_BASE = 20000
PORT_BLOCK = 500
PORT_BLOCKS = 24  # 20000-31999
_port_picks = itertools.count(random.randrange(PORT_BLOCK))


def worker_port_block() -> int:
    """The first port of this process's block: by its pytest-xdist worker number, rotated by the run's id (the
    test run's uid under xdist, else the process id)."""
    worker = os.environ.get("PYTEST_XDIST_WORKER", "")
    index = int(worker[2:]) if worker.startswith("gw") and worker[2:].isdigit() else 0
    run = os.environ.get("PYTEST_XDIST_TESTRUNUID") or str(os.getpid())
    return PORT_BASE + (zlib.crc32(run.encode()) + index) % PORT_BLOCKS * PORT_BLOCK


def free_port(kind: int = socket.SOCK_STREAM) -> int:
    """A port on 127.0.0.1 that was free a moment ago: the next in this worker's block that binds, released."""
    base = worker_port_block()
    for _ in range(PORT_BLOCK):
        port = base + next(_port_picks) % PORT_BLOCK
        with socket.socket(socket.AF_INET, kind) as s:
            try:
                s.bind(("127.0.0.1", port))
            except OSError:  # taken, or a TCP port still in TIME_WAIT: the next one
                continue
            return port
    msg = f"no free {kind!r} port in {base}-{base + PORT_BLOCK - 1}"
    raise RuntimeError(msg)


async def until(condition: Callable[[], object], timeout_s: float = HANG_S, what: str = "condition") -> None:
    """Wait until ``condition()`` is true; AssertionError naming ``what`` if it is not within ``timeout_s`` wall s."""
    try:
        async with asyncio.timeout(timeout_s):
            while not condition():
                await asyncio.sleep(POLL_S)
    except TimeoutError:
        msg = f"{what}: not within {timeout_s} s"
        raise AssertionError(msg) from None


async def reap(proc: asyncio.subprocess.Process, hang_s: float = HANG_S) -> None:
    """Wait for a subprocess told to stop (a signal, "exit" at its prompt) to end; kill it after ``hang_s``."""
    try:
        async with asyncio.timeout(hang_s):
            await proc.wait()
    except TimeoutError:
        proc.kill()
        await proc.wait()


async def within(
    now_s: Callable[[], float], condition: Callable[[], object], within_s: float, what: str, hang_s: float = HANG_S
) -> None:
    """Wait until ``condition()``; fail if the test's own clock ``now_s`` (simulated or scripted time, never wall
    time) moves on by ``within_s`` first. ``hang_s`` wall seconds only bound a hang."""
    deadline_s = now_s() + within_s
    await until(lambda: condition() or now_s() > deadline_s, hang_s, what)
    assert condition(), f"{what}: not within {within_s} s of the test's clock"


async def counter_advances(read: Callable[[], int], by: int, what: str, hang_s: float = HANG_S) -> None:
    """Wait until the counter ``read()`` has grown by ``by`` from now: for checks that something did NOT happen,
    a positive event (cycles run, steps taken, messages received) proves that enough happened meanwhile."""
    target = read() + by
    await until(lambda: read() >= target, hang_s, f"{what}: {by} more")


class ManualClock(ServiceClock):
    """Service time set by the test (``t``, starting at 100 s): socket-free tests drive the service with it."""

    def __init__(self) -> None:
        super().__init__(1.0)
        self.t = 100.0

    def now(self) -> float:
        return self.t


class _HasSimTime(Protocol):
    @property
    def t_s(self) -> float: ...


class SimulatorClock(ServiceClock):
    """Service time that IS the simulator's time, for a service flying the in-process simulator.

    The default ``ServiceClock`` is wall time times ``time_scale``. On a loaded machine the simulator falls
    behind its speed-up (it re-bases rather than burst to catch up) while wall time runs on, so the service
    would see the vehicle crawl: pose ages, progress timeouts and takeover deadlines would all be off by the
    lag. With this clock both sides share one time base and a loaded machine only makes the flight slower.

    Until ``follow(sim)`` (the service opens before the simulator that connects to it) time stands still.
    """

    def __init__(self, speedup: float) -> None:
        super().__init__(time_scale=speedup)
        self._sim: _HasSimTime | None = None
        self._offset_s = 0.0
        self._last_s = 0.0

    def follow(self, sim: _HasSimTime) -> None:
        """From now on, advance with ``sim.t_s`` (continuing from the current reading)."""
        self._offset_s = self.now() - sim.t_s
        self._sim = sim

    def now(self) -> float:
        """Simulated seconds, strictly increasing from one reading to the next.

        The simulator's time moves in physics steps, so two messages read within one step would get the same
        receive stamp, and the navigator refuses a pose no newer than the last one. Like a real clock with
        microsecond resolution, a repeated reading moves on by ``TICK_S``; readings stay within a few
        milliseconds of the simulator's time (the next physics step overtakes them).
        """
        if self._sim is not None:
            self._last_s = max(self._sim.t_s + self._offset_s, self._last_s + TICK_S)
        return self._last_s

    async def sleep(self, dt_s: float) -> None:
        """Until simulated time has advanced by ``dt_s`` (however long that takes on the wall clock)."""
        until_s = self.now() + dt_s
        while (left_s := until_s - self.now()) > 0:
            await asyncio.sleep(self.to_wall(left_s))
        await asyncio.sleep(0)


async def until_sim_time(clock: ServiceClock, t_s: float, hang_s: float = HANG_S) -> None:
    """Wait until ``clock`` (a ``SimulatorClock``, or any service clock) reaches ``t_s``."""
    await until(lambda: clock.now() >= t_s, hang_s, f"simulated time {t_s:.1f} s")


async def wait_for(sim: Simulator, predicate: Callable[[Simulator], bool], *, timeout_s: float = HANG_S) -> None:
    """``sim.vehicle.testing.wait_for`` with a hang-only wall deadline: for conditions that stay true once met."""
    await sim_testing.wait_for(sim, predicate, timeout_s=timeout_s)


async def wait_sim_time(sim: Simulator, t_s: float, *, timeout_s: float = HANG_S) -> None:
    """``sim.vehicle.testing.wait_sim_time`` with a hang-only wall deadline."""
    await sim_testing.wait_sim_time(sim, t_s, timeout_s=timeout_s)


_SampleT = TypeVar("_SampleT")


class StepWatch(Generic[_SampleT]):
    """Looks at an in-process simulator after every physics step, so nothing between two polls is missed.

    Polling ``sim.vehicle`` from the test's task sees the vehicle only when that task runs; on a loaded machine
    the simulator may have run many steps meanwhile, past a state that lasts a second or two of simulated time
    (a velocity before GUID_TIMEOUT). ``first`` and ``sample_at`` are exact in simulated time instead.
    """

    def __init__(self, sim: Simulator, sample: Callable[[Simulator], _SampleT]) -> None:
        self._sim = sim
        self._sample = sample
        self.t_s: list[float] = []
        self.samples: list[_SampleT] = []
        self._waiters: list[tuple[Callable[[Simulator], bool], float, asyncio.Future[tuple[float, bool]]]] = []
        step = sim.engine.step

        def step_and_watch() -> None:
            step()
            self._after_step()

        sim.engine.step = step_and_watch  # type: ignore[method-assign]

    def _after_step(self) -> None:
        t_s = self._sim.t_s
        self.t_s.append(t_s)
        self.samples.append(self._sample(self._sim))
        for predicate, deadline_s, fut in self._waiters:
            if fut.done():
                continue
            if predicate(self._sim):
                fut.set_result((t_s, True))
            elif t_s >= deadline_s:
                fut.set_result((t_s, False))
        self._waiters = [w for w in self._waiters if not w[2].done()]

    async def first(self, predicate: Callable[[Simulator], bool], *, within_s: float, hang_s: float = HANG_S) -> float:
        """Simulated time of the first step (from now) where ``predicate`` holds; fails after ``within_s`` sim s."""
        if predicate(self._sim):
            return self._sim.t_s
        fut: asyncio.Future[tuple[float, bool]] = asyncio.get_running_loop().create_future()
        self._waiters.append((predicate, self._sim.t_s + within_s, fut))
        async with asyncio.timeout(hang_s):
            t_s, met = await fut
        assert met, f"not within {within_s} simulated s (at {t_s:.2f} s)"
        return t_s

    def sample_at(self, t_s: float) -> _SampleT:
        """The sample of the first step at or after simulated time ``t_s`` (that step must have run)."""
        for t, sample in zip(self.t_s, self.samples, strict=True):
            if t >= t_s - 1e-9:
                return sample
        msg = f"no step at or after {t_s} s yet (last {self.t_s[-1] if self.t_s else None})"
        raise AssertionError(msg)


@pytest.fixture
def udp_port() -> int:
    return free_port(socket.SOCK_DGRAM)


@pytest.fixture
def tcp_port() -> int:
    return free_port(socket.SOCK_STREAM)
