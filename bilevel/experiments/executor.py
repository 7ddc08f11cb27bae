"""Where sweep tasks run: a local process pool (default) or a Dask cluster, behind one small interface.

Both yield finished rows in completion order; the sweep writes them and orders results by task key, so
the numbers never depend on the executor, the worker count or which worker ran what. `abort` stops
every worker at once (used on SIGINT/SIGTERM) instead of waiting for running tasks.
"""

from __future__ import annotations

import logging
import os
import re
import signal
from abc import ABC, abstractmethod
from concurrent.futures import ProcessPoolExecutor, as_completed
from typing import Any, Callable, Iterator

from ..threads import single_threaded

Task = dict[str, Any]
Row = dict[str, Any]
DASK_ADDRESS = re.compile(r"^(local|(tcp|tls|ucx|inproc)://\S+)$")


def run_task(fn: Callable[[Task], Row], task: Task) -> Row:
    """fn(task) with one BLAS thread (every executor runs tasks through this, so they compute alike)."""
    with single_threaded():
        return fn(task)


class Executor(ABC):
    """Runs sweep tasks somewhere; a context manager that releases its workers on exit."""

    description: str

    @abstractmethod
    def imap_unordered(self, fn: Callable[[Task], Row], tasks: list[Task]) -> Iterator[tuple[Task, Row]]:
        """(task, fn(task)) for every task, in completion order."""

    @abstractmethod
    def abort(self) -> None:
        """Stop every worker now, dropping running and queued tasks."""

    def close(self) -> None:
        """Release the workers after normal completion."""

    def __enter__(self) -> Executor:
        return self

    def __exit__(self, exc_type: type | None, *_: Any) -> None:
        if exc_type is None:
            self.close()
        else:
            self.abort()


def _worker_signals() -> None:
    """Worker initializer: a Ctrl-C on the process group is the main process's to handle (it stops us), and
    SIGTERM just ends the worker (a forked worker would otherwise inherit the sweep's raising handler)."""
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    signal.signal(signal.SIGTERM, signal.SIG_DFL)


class LocalExecutor(Executor):
    """`workers` local processes (1: in the calling process, no pool)."""

    def __init__(self, workers: int | None = None) -> None:
        self.workers = workers or os.cpu_count() or 1
        self.description = f"{self.workers} local worker process{'es' if self.workers > 1 else ''}"
        self._pool: ProcessPoolExecutor | None = None

    def imap_unordered(self, fn: Callable[[Task], Row], tasks: list[Task]) -> Iterator[tuple[Task, Row]]:
        if self.workers == 1:
            for task in tasks:
                yield task, run_task(fn, task)
            return
        if self._pool is None:
            self._pool = ProcessPoolExecutor(max_workers=self.workers, initializer=_worker_signals)
        futures = {self._pool.submit(run_task, fn, t): t for t in tasks}
        for fut in as_completed(futures):
            yield futures[fut], fut.result()

    def abort(self) -> None:
        if self._pool is None:
            return
        # ProcessPoolExecutor has no terminate() before Python 3.14 and shutdown alone waits for running tasks;
        # queued futures are not cancelled first (3.11 then fails to mark them broken, with a traceback)
        for proc in list((self._pool._processes or {}).values()):
            proc.terminate()
        self._pool.shutdown(wait=False)
        self._pool = None

    def close(self) -> None:
        if self._pool is not None:
            self._pool.shutdown()
            self._pool = None


class DaskExecutor(Executor):
    """A dask.distributed cluster: a scheduler address ("tcp://host:8786") or "local" (a LocalCluster of
    `workers` single-threaded processes on 127.0.0.1). A task whose worker dies is rerun elsewhere by Dask."""

    def __init__(self, address: str, workers: int | None = None) -> None:
        try:
            from distributed import Client, LocalCluster
        except ImportError as exc:  # pragma: no cover - depends on the environment
            raise RuntimeError("--dask needs dask.distributed: pip install 'bilevel[dask]'") from exc
        self._cluster = None
        if address == "local":
            self._cluster = LocalCluster(n_workers=workers or os.cpu_count() or 1, threads_per_worker=1,
                                         processes=True, host="127.0.0.1", dashboard_address=None)
            self.client = Client(self._cluster)
        else:
            self.client = Client(address, timeout="30s")
        n = len(self.client.scheduler_info(n_workers=-1)["workers"])
        self.description = f"Dask cluster {address} ({n} worker{'s' if n != 1 else ''} at start)"
        self._futures: list[Any] = []

    def imap_unordered(self, fn: Callable[[Task], Row], tasks: list[Task]) -> Iterator[tuple[Task, Row]]:
        from distributed import as_completed as dask_completed

        # pure=False: a fresh Dask key per submission, never a result cached from another run
        futures = {self.client.submit(run_task, fn, t, pure=False): t for t in tasks}
        self._futures = list(futures)
        for fut in dask_completed(futures):
            yield futures[fut], fut.result()
        self._futures = []

    def abort(self) -> None:
        logging.getLogger("distributed").setLevel(logging.CRITICAL)  # its "connection closed" tracebacks
        if self._cluster is not None:
            # a LocalCluster's nannies give a busy worker seconds to finish; its processes are ours: kill them now
            for nanny in self._cluster.workers.values():
                nanny.auto_restart = False
                proc = getattr(getattr(nanny, "process", None), "process", None)
                if proc is not None and proc.pid:
                    os.kill(proc.pid, signal.SIGKILL)
        elif self._futures and self.client.status == "running":
            self.client.cancel(self._futures, force=True)
        self._futures = []
        self.close()

    def close(self) -> None:
        if self.client.status != "closed":
            self.client.close(timeout=3)
        if self._cluster is not None:
            self._cluster.close(timeout=3)
            self._cluster = None


def check_dask_address(address: str) -> str | None:
    """None if `address` is "local" or a scheduler URL (tcp://host:port, ...), else the reason it is not."""
    return None if DASK_ADDRESS.match(address) else f"expected 'local' or tcp://HOST:PORT, got {address!r}"


def open_executor(workers: int | None = None, dask: str | None = None) -> Executor:
    """The local pool of `workers` processes, or the Dask cluster at `dask` ("local": a LocalCluster of `workers`)."""
    return LocalExecutor(workers) if dask is None else DaskExecutor(dask, workers)
