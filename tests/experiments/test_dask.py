"""Sweeps on a Dask cluster (scheduler and two workers on 127.0.0.1, as separate processes): a worker killed
mid-run has its tasks rerun elsewhere, nothing is lost or duplicated, and the numbers equal the local pool's."""

from __future__ import annotations

import json
import os
import signal
import socket
import subprocess
import sys
import time
from collections.abc import Iterator
from contextlib import contextmanager

import pytest

pytest.importorskip("distributed")

from bilevel.experiments import vrft  # noqa: E402
from bilevel.experiments.executor import DaskExecutor, LocalExecutor  # noqa: E402
from bilevel.experiments.sweep import run_sweep  # noqa: E402

from .tables import BILEVEL, table_difference, wait_for_rows  # noqa: E402

DASK = os.path.join(os.path.dirname(sys.executable), "dask")


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


@contextmanager
def dask_cluster(workers: int = 2) -> Iterator[tuple[str, list[subprocess.Popen]]]:
    """`dask scheduler` and `workers` single-threaded `dask worker` processes (no nanny) on 127.0.0.1."""
    from distributed import Client

    address = f"tcp://127.0.0.1:{_free_port()}"
    quiet = {"stdout": subprocess.DEVNULL, "stderr": subprocess.DEVNULL}
    procs = [subprocess.Popen([DASK, "scheduler", "--host", "127.0.0.1", "--port", address.rsplit(":", 1)[1],
                               "--no-dashboard"], **quiet)]
    try:
        procs += [subprocess.Popen([DASK, "worker", address, "--nthreads", "1", "--no-nanny", "--no-dashboard",
                                    "--host", "127.0.0.1"], **quiet) for _ in range(workers)]
        with Client(address, timeout="30s") as client:
            client.wait_for_workers(workers, timeout=60)
        yield address, procs[1:]
    finally:
        for p in reversed(procs):
            p.terminate()
        for p in procs:
            try:
                p.wait(timeout=10)
            except subprocess.TimeoutExpired:
                p.kill()


def _rows_without_times(rows: list[dict]) -> list[dict]:
    return [{k: v for k, v in r.items() if k != "wall_time"} for r in rows]


def test_worker_killed_mid_sweep_loses_and_duplicates_nothing(tmp_path) -> None:
    """A VRFT sweep on two Dask workers; one is SIGKILLed after the first rows: every task has exactly one row,
    equal (bar wall time) to the in-process run."""
    tasks = vrft.cell_tasks(2, 0, "paper", "maxmin", "alternating", eps_u=(0.1, 0.2))
    local = run_sweep(vrft.attack_task, tasks, str(tmp_path / "local.jsonl"), LocalExecutor(1), None)
    path = str(tmp_path / "dask.jsonl")
    with dask_cluster() as (address, workers):
        killed: list[int] = []

        def kill_first_worker(line: str) -> None:
            if "done" in line and not killed:
                workers[0].send_signal(signal.SIGKILL)
                killed.append(workers[0].wait(timeout=10))

        with DaskExecutor(address) as executor:
            rows = run_sweep(vrft.attack_task, tasks, path, executor, kill_first_worker, "dask")
    assert killed == [-signal.SIGKILL]
    with open(path, encoding="utf-8") as fh:
        keys = [json.loads(line)["key"] for line in fh]
    assert sorted(keys) == sorted(t["key"] for t in tasks)
    assert _rows_without_times(rows) == _rows_without_times(local)


@pytest.mark.slow
def test_cli_reproduction_on_dask_with_a_killed_worker_equals_the_local_pool(tmp_path) -> None:
    """`bilevel reproduce vrft --sims 4 --dask tcp://127.0.0.1:PORT`, one worker killed mid-run: every table
    equals `--workers 2` on the local pool (5 min on a shared 2-core machine)."""
    local, remote = str(tmp_path / "local"), str(tmp_path / "dask")
    subprocess.run(BILEVEL + ["reproduce", "vrft", "--sims", "4", "--workers", "2", "--out", local], check=True,
                   stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    with dask_cluster() as (address, workers):
        proc = subprocess.Popen(BILEVEL + ["reproduce", "vrft", "--sims", "4", "--dask", address, "--out", remote],
                                stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
        wait_for_rows(proc, os.path.join(remote, "maxmin-paper.jsonl"), 20)
        workers[0].send_signal(signal.SIGKILL)
        t0 = time.monotonic()
        _, err = proc.communicate(timeout=900)
    assert proc.returncode == 0, err
    assert workers[0].returncode == -signal.SIGKILL and time.monotonic() - t0 > 1
    for name in ("maxmin-paper", "targeted-paper"):
        with open(os.path.join(remote, f"{name}.jsonl"), encoding="utf-8") as fh:
            keys = [json.loads(line)["key"] for line in fh]
        assert len(keys) == len(set(keys))
    assert not (diff := table_difference(remote, local)), diff
