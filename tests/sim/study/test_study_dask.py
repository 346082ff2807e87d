"""``apf-sim study --dask``: a real Dask cluster on loopback gives the same table as the local process pool."""

from __future__ import annotations

import argparse
import csv
import logging
import os
import re
import sys
from collections.abc import Iterator
from pathlib import Path
from typing import TYPE_CHECKING

import pytest

from sim.study import executors
from sim.study.cli import register
from tests.conftest import free_port

if TYPE_CHECKING:
    from distributed import LocalCluster

distributed = pytest.importorskip("distributed", reason="dask.distributed not installed (pip install '.[dask]')")

_STUDY = [
    "--trials", "40", "--chunk-trials", "10", "--densities", "20-45,45-70", "--planners", "bapf,cr-bapf*",
    "--seed", "7", "--no-progress",
]  # fmt: skip


def _run(argv: list[str]) -> int:
    parser = argparse.ArgumentParser()
    sub = parser.add_subparsers(dest="command", required=True)
    register(sub)
    args = parser.parse_args(["study", *argv])
    code: int = args.func(args)
    return code


def _table_and_trials(
    argv: list[str], tmp_path: Path, name: str, capsys: pytest.CaptureFixture[str]
) -> tuple[list[str], list[list[str]], str]:
    """The markdown table without its T_a columns and the per-trial CSV without time_ms (wall-clock values)."""
    out_csv = tmp_path / f"{name}.csv"
    assert _run([*_STUDY, *argv, "--csv", str(out_csv)]) == 0
    out = capsys.readouterr().out
    rows = [line.split("|") for line in out.splitlines() if line.startswith("|")]
    head = [c.strip() for c in rows[0]]
    t_a = [i for i, c in enumerate(head) if "T_a" in c]
    table = ["|".join(c for i, c in enumerate(r) if i not in t_a) for r in rows]
    with out_csv.open() as fh:
        records = list(csv.reader(fh))
    time_col = records[0].index("time_ms")
    trials = [[c for i, c in enumerate(r) if i != time_col] for r in records]
    return table, trials, out


def test_local_cluster_gives_the_table_of_two_local_workers(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    pool_table, pool_trials, pool_out = _table_and_trials(["--workers", "2"], tmp_path, "pool", capsys)
    dask_table, dask_trials, dask_out = _table_and_trials(
        ["--dask", "local", "--workers", "2"], tmp_path, "dask", capsys
    )
    assert len(pool_table) == 2 + 4  # header, rule, 2 planners x 2 densities
    assert dask_table == pool_table
    assert len(pool_trials) == 1 + 4 * 40
    assert dask_trials == pool_trials
    assert "with 2 worker(s)" in pool_out
    assert re.search(r"with 2 Dask worker\(s\) at tcp://127\.0\.0\.1:\d+", dask_out)


@pytest.fixture(scope="module")
def quiet_dask() -> Iterator[None]:
    """Dask logs to a handler that holds the stderr of import time (pytest's capture, closed by teardown); a
    cluster living across tests would log its shutdown into it. Keep Dask to errors, on the real stderr."""
    dask_log = logging.getLogger("distributed")
    level = dask_log.level
    dask_log.setLevel(logging.ERROR)
    for handler in dask_log.handlers:
        if isinstance(handler, logging.StreamHandler):
            handler.setStream(sys.__stderr__)
    yield
    dask_log.setLevel(level)


@pytest.fixture(scope="module")
def loopback_cluster(quiet_dask: None) -> Iterator[LocalCluster]:
    with distributed.LocalCluster(
        n_workers=2,
        threads_per_worker=1,
        processes=True,
        host="127.0.0.1",
        dashboard_address=None,
        env={"OPENBLAS_NUM_THREADS": "1"},
    ) as cluster:
        yield cluster


def test_running_scheduler_by_address_gives_the_serial_table(
    loopback_cluster: LocalCluster,
    tmp_path: Path,
    capsys: pytest.CaptureFixture[str],
    caplog: pytest.LogCaptureFixture,
) -> None:
    address = loopback_cluster.scheduler_address
    assert address.startswith("tcp://127.0.0.1:")
    serial_table, serial_trials, _ = _table_and_trials(["--workers", "1"], tmp_path, "serial", capsys)
    dask_table, dask_trials, out = _table_and_trials(["--dask", address], tmp_path, "remote", capsys)
    assert dask_table == serial_table
    assert dask_trials == serial_trials
    assert f"with 2 Dask worker(s) at {address}" in out
    # This cluster's nannies kept Dask's default MALLOC_TRIM_THRESHOLD_: the run says so (slow, see executors).
    assert "2 Dask worker(s) run with MALLOC_TRIM_THRESHOLD_ set" in caplog.text


def test_dask_local_workers_run_single_threaded_blas() -> None:
    with executors.dask_executor("local", workers=1) as (executor, info):
        assert info.kind == "dask-local"
        assert info.workers == 1
        assert info.address.startswith("tcp://127.0.0.1:")
        env = executor.submit(os.environ.get, "OPENBLAS_NUM_THREADS").result()
        malloc_trim = executor.submit(os.environ.get, "MALLOC_TRIM_THRESHOLD_").result()
    assert env == "1"
    assert malloc_trim is None


def test_remote_cluster_refuses_workers_option(
    loopback_cluster: LocalCluster, capsys: pytest.CaptureFixture[str]
) -> None:
    assert _run([*_STUDY, "--dask", loopback_cluster.scheduler_address, "--workers", "2"]) == 2
    assert "a remote Dask cluster has its own workers" in capsys.readouterr().err


@pytest.mark.parametrize("address", ["127.0.0.1:8786", "tcp://", "cluster"])
def test_bad_address_is_a_config_error(address: str, capsys: pytest.CaptureFixture[str]) -> None:
    assert _run([*_STUDY, "--dask", address]) == 2
    assert "--dask: expected 'local' or a scheduler address like tcp://HOST:8786" in capsys.readouterr().err


def test_no_scheduler_is_a_clear_error(monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]) -> None:
    monkeypatch.setattr(executors, "CONNECT_TIMEOUT_S", 1.0)
    address = f"tcp://127.0.0.1:{free_port()}"
    assert _run([*_STUDY, "--dask", address]) == 2
    assert f"--dask {address}: no Dask scheduler answered within 1 s" in capsys.readouterr().err


def test_sweep_on_a_running_scheduler_writes_the_serial_table(
    loopback_cluster: LocalCluster, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    from sim.sweep_cli import register as register_sweep

    def sweep(argv: list[str]) -> str:
        parser = argparse.ArgumentParser()
        register_sweep(parser.add_subparsers(dest="command", required=True))
        args = parser.parse_args(["sweep", "--param", "rho_l=0.3,0.5", "--densities", "45-70",
                                  "--worlds", "corridor-bend", "--trials", "8", "--chunk-trials", "4",
                                  "--no-plots", "--no-progress", *argv])  # fmt: skip
        assert args.func(args) == 0
        return capsys.readouterr().out

    serial_out = sweep(["--workers", "1", "--out", str(tmp_path / "serial")])
    dask_out = sweep(["--dask", loopback_cluster.scheduler_address, "--out", str(tmp_path / "dask")])
    assert f"with 2 Dask worker(s) at {loopback_cluster.scheduler_address}" in dask_out
    table = [line for line in serial_out.splitlines() if line.startswith("|")]
    assert len(table) == 2 + 2 * 2  # 2 grid points x (1 density + 1 world)
    assert table == [line for line in dask_out.splitlines() if line.startswith("|")]
    assert (tmp_path / "serial" / "sweep.csv").read_text() == (tmp_path / "dask" / "sweep.csv").read_text()
