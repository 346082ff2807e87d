"""Where the study's chunks run: this machine's process pool, or a Dask cluster (``--dask local|ADDRESS``).

Every chunk's result depends only on (config, planner, density, chunk, seed) (see ``sim.study.engine``), so any
``concurrent.futures.Executor`` gives the same table; this module only picks and owns one:

- no ``--dask``: ``engine.default_executor(workers)`` (worker processes, forked or spawned as
  ``engine.start_method`` decides, or in-process for one worker);
- ``--dask local``: a ``distributed.LocalCluster`` of ``workers`` single-threaded worker processes bound to
  127.0.0.1, no dashboard, BLAS limited to one thread per worker;
- ``--dask tcp://HOST:PORT`` (any Dask scheduler address): a ``distributed.Client`` of a running cluster
  (``dask scheduler`` + ``dask worker tcp://HOST:PORT`` on each machine, each with this package installed).

Dask is an optional dependency (``pip install 'apf-companion[dask]'``); it is imported only here, and only when
asked for.
"""

from __future__ import annotations

import contextlib
import logging
import os
import warnings
from collections.abc import Iterator
from concurrent.futures import Executor
from dataclasses import dataclass
from typing import Any

from apf_companion.errors import ConfigError
from sim.study import _worker

LOCAL = "local"
"""``--dask local``: start a LocalCluster on loopback for this run."""

MALLOC_TRIM_CONFIG = "distributed.nanny.pre-spawn-environ.MALLOC_TRIM_THRESHOLD_"
"""Dask's nannies start workers with MALLOC_TRIM_THRESHOLD_=65536. Setting it turns off glibc's dynamic mmap
threshold, so every temporary array over 128 kB of the lockstep engine is mmap'ed and unmapped again: measured
3.3x the page faults and 2-4x the chunk time of the same chunk outside Dask. Our workers start without it."""

log = logging.getLogger(__name__)

CONNECT_TIMEOUT_S = 10.0
"""How long to wait for a remote scheduler before giving up with a clear error."""


@dataclass(frozen=True, slots=True)
class ExecutorInfo:
    """What ran the chunks (printed under the table and written to the JSON summary)."""

    kind: str
    """``processes``, ``dask-local`` or ``dask``."""
    workers: int
    """Worker processes (Dask: workers connected when the run started)."""
    address: str = ""
    """The Dask scheduler address (empty for the local process pool)."""

    def describe(self) -> str:
        if self.kind == "processes":
            return f"{self.workers} worker(s)"
        return f"{self.workers} Dask worker(s) at {self.address}"


def check_dask_address(address: str) -> str:
    """``local`` or a scheduler address with a scheme (``tcp://10.0.0.5:8786``); raise ``ConfigError`` otherwise."""
    text = address.strip()
    if text == LOCAL:
        return text
    scheme, sep, rest = text.partition("://")
    if not sep or not scheme or not rest:
        msg = f"--dask: expected 'local' or a scheduler address like tcp://HOST:8786, got {address!r}"
        raise ConfigError(msg)
    return text


def _import_distributed() -> Any:
    try:
        import distributed
    except ImportError as err:
        msg = "--dask needs dask.distributed: pip install 'apf-companion[dask]'"
        raise ConfigError(msg) from err
    return distributed


def _quiet_dask_logs() -> None:
    """Dask logs its start-up and shut-down at INFO on its own handler: follow ``--log-level`` instead."""
    root_level = logging.getLogger().getEffectiveLevel()
    dask_log = logging.getLogger("distributed")
    if dask_log.getEffectiveLevel() < root_level:
        dask_log.setLevel(root_level)


def dask_config_set(values: dict[str, Any]) -> contextlib.AbstractContextManager[Any]:
    import dask

    return dask.config.set(values)


@contextlib.contextmanager
def _without_env(name: str) -> Iterator[None]:
    saved = os.environ.pop(name, None)
    try:
        yield
    finally:
        os.environ.pop(name, None)
        if saved is not None:
            os.environ[name] = saved


def _warn_malloc_trim(client: Any) -> None:
    """Say once per run when workers carry Dask's MALLOC_TRIM_THRESHOLD_ (slow; see MALLOC_TRIM_CONFIG)."""
    values = client.run(os.environ.get, "MALLOC_TRIM_THRESHOLD_")
    slow = sorted(addr for addr, value in values.items() if value is not None)
    if slow:
        log.warning(
            "%d Dask worker(s) run with MALLOC_TRIM_THRESHOLD_ set (Dask's default), which makes the study "
            "2-4x slower; start them with 'distributed: nanny: pre-spawn-environ: MALLOC_TRIM_THRESHOLD_: null' "
            "in ~/.config/dask/distributed.yaml (docs/ecosystem.md)",
            len(slow),
        )


def _single_thread_env() -> dict[str, str]:
    return dict.fromkeys(_worker._SINGLE_THREAD_ENV, "1")


def _local_client(stack: contextlib.ExitStack, distributed: Any, workers: int | None) -> Any:
    """Start a LocalCluster on loopback (closed with ``stack``) and return its client."""
    n = workers if workers is not None else (os.cpu_count() or 1)
    stack.enter_context(dask_config_set({MALLOC_TRIM_CONFIG: None}))
    # A nanny also writes the variable into this process's environment, which spawned workers inherit.
    stack.enter_context(_without_env("MALLOC_TRIM_THRESHOLD_"))
    # With the dashboard off the scheduler still serves /health on 127.0.0.1:8787, or a free port when another
    # cluster has it; that fallback is fine and not worth a warning.
    stack.enter_context(warnings.catch_warnings())
    warnings.filterwarnings("ignore", message=r"Port \d+ is already in use", category=UserWarning)
    cluster = stack.enter_context(
        distributed.LocalCluster(
            n_workers=n,
            threads_per_worker=1,
            processes=True,
            host="127.0.0.1",
            dashboard_address=None,
            # Dask's nannies set these too (distributed.nanny.pre-spawn-environ); say it explicitly.
            env=_single_thread_env(),
        )
    )
    return stack.enter_context(distributed.Client(cluster))


def _remote_client(stack: contextlib.ExitStack, distributed: Any, address: str, workers: int | None) -> Any:
    if workers is not None:
        msg = "--workers sizes a local pool or --dask local; a remote Dask cluster has its own workers"
        raise ConfigError(msg)
    try:
        return stack.enter_context(distributed.Client(address, timeout=CONNECT_TIMEOUT_S))
    except (OSError, TimeoutError) as err:
        msg = f"--dask {address}: no Dask scheduler answered within {CONNECT_TIMEOUT_S:.0f} s ({err})"
        raise ConfigError(msg) from err


@contextlib.contextmanager
def dask_executor(address: str, *, workers: int | None = None) -> Iterator[tuple[Executor, ExecutorInfo]]:
    """A ``concurrent.futures.Executor`` backed by Dask (``Client.get_executor``), closed on exit.

    ``address`` is ``local`` (start a LocalCluster of ``workers`` processes, default all cores, on 127.0.0.1) or the
    address of a running scheduler (``workers`` must then be None: the cluster has its own).
    """
    address = check_dask_address(address)
    distributed = _import_distributed()
    _quiet_dask_logs()
    with contextlib.ExitStack() as stack:
        if address == LOCAL:
            client = _local_client(stack, distributed, workers)
        else:
            client = _remote_client(stack, distributed, address, workers)
        n_workers = len(client.scheduler_info().get("workers", {}))
        if n_workers == 0:
            msg = f"--dask {address}: the scheduler has no workers (start some: dask worker {address})"
            raise ConfigError(msg)
        _warn_malloc_trim(client)
        kind = "dask-local" if address == LOCAL else "dask"
        info = ExecutorInfo(kind=kind, workers=n_workers, address=str(client.scheduler.address))
        # pure=False: every chunk is its own task even if two were equal (Dask would otherwise run one once).
        executor = stack.enter_context(client.get_executor(pure=False))
        yield executor, info


@contextlib.contextmanager
def study_executor(dask: str | None, workers: int | None) -> Iterator[tuple[Executor, ExecutorInfo]]:
    """The executor for ``--dask``/``--workers``: Dask when ``dask`` is given, else this machine's pool."""
    if dask is not None:
        with dask_executor(dask, workers=workers) as pair:
            yield pair
        return
    from sim.study.engine import default_executor

    n = workers if workers is not None else (os.cpu_count() or 1)
    executor = default_executor(n)
    try:
        yield executor, ExecutorInfo(kind="processes", workers=n)
    finally:
        executor.shutdown(wait=True, cancel_futures=True)
