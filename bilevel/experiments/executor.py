"""Where sweep tasks run: a local process pool (default) or a Dask cluster, behind one small interface.

Both yield finished rows in completion order; the sweep writes them and orders results by task key, so
the numbers never depend on the executor, the worker count or which worker ran what. Tasks go to the workers in
batches, one message each way per batch: the tasks a sweep groups together run one after another in one worker,
sharing what that process keeps (data, starts). `abort` stops every worker at once (used on SIGINT/SIGTERM) instead
of waiting for running tasks. A local worker that dies (SIGKILL, the OOM killer) costs a new pool and a rerun of
the unfinished tasks (its whole batch); local workers die with the main process, even when it is killed with
SIGKILL.
"""

from __future__ import annotations

import ctypes
import glob
import logging
import os
import re
import shutil
import signal
import sys
import tempfile
import threading
import time
from abc import ABC, abstractmethod
from collections import Counter
from concurrent.futures import ProcessPoolExecutor, as_completed
from concurrent.futures.process import BrokenProcessPool
from typing import Any, Callable, Hashable, Iterator

from ..errors import WorkerLost
from ..threads import single_threaded

Task = dict[str, Any]
Row = dict[str, Any]
Together = Callable[[Task], Hashable]
"""Tasks with equal together(task) form one batch."""
DASK_ADDRESS = re.compile(r"^(local|(tcp|tls|ucx|inproc)://\S+)$")
WORKER_DEATHS = 2
"""A task whose worker process dies this many times stops the sweep (WorkerLost) instead of being retried."""
_PR_SET_PDEATHSIG = 1
_MARKS: str = ""
MARKS_PREFIX = "bilevel-workers-"
"""In a local worker: the directory where it notes which task it is running (file named by its pid)."""


class BatchTask:
    """A sweep function that computes a batch of tasks in one call, many(tasks) -> their rows in order (e.g. the
    instances of one declaration solved together: bilevel.solvers.batch); every executor hands it each batch of
    `together` whole, and a task alone is many([task])[0]. Picklable where `many` is a module-level function."""

    def __init__(self, many: Callable[[list[Task]], list[Row]]) -> None:
        self.many = many
        self.__name__ = getattr(many, "__name__", "batch")

    def __call__(self, task: Task) -> Row:
        return self.many([task])[0]


def run_task(fn: Callable[[Task], Row], task: Task) -> Row:
    """fn(task) with one BLAS thread, as run_batch runs each task (every executor runs tasks through one of them, so
    they compute alike)."""
    with single_threaded():
        return fn(task)


def run_batch(fn: Callable[[Task], Row], tasks: list[Task]) -> list[Row]:
    """fn on each task in order, with one BLAS thread (run_task's rule, set once for the batch)."""
    with single_threaded():
        return fn.many(list(tasks)) if isinstance(fn, BatchTask) else [fn(t) for t in tasks]


def batches(tasks: list[Task], together: Together | None) -> list[list[int]]:
    """Indices of `tasks` grouped by together(task) (None: each task alone), in order of first appearance."""
    groups: dict[Hashable, list[int]] = {}
    for i, t in enumerate(tasks):
        groups.setdefault(i if together is None else together(t), []).append(i)
    return list(groups.values())


class Executor(ABC):
    """Runs sweep tasks somewhere; a context manager that releases its workers on exit."""

    description: str
    workers: int

    @abstractmethod
    def imap_unordered(self, fn: Callable[[Task], Row], tasks: list[Task],
                       report: Callable[[str], None] | None = None,
                       together: Together | None = None) -> Iterator[tuple[Task, Row]]:
        """(task, fn(task)) for every task, in completion order, a batch's tasks (`together`) one after another in
        one worker; `report` hears of workers lost and replaced."""

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


def _die_with(parent: int) -> None:
    """End this process when `parent` ends, however it ends (Linux: PR_SET_PDEATHSIG; elsewhere a watchdog)."""
    if sys.platform.startswith("linux"):
        ctypes.CDLL(None, use_errno=True).prctl(_PR_SET_PDEATHSIG, signal.SIGKILL)
    else:  # pragma: no cover - not Linux
        def watch() -> None:
            while os.getppid() == parent:
                time.sleep(0.5)
            os._exit(1)

        threading.Thread(target=watch, daemon=True).start()
    if os.getppid() != parent:  # the parent died before the above took effect
        os._exit(1)


def _worker_init(parent: int, marks: str) -> None:
    """Worker initializer: a Ctrl-C on the process group is the main process's to handle (it stops us), SIGTERM
    just ends the worker (a forked worker would otherwise inherit the sweep's raising handler), the worker dies
    with its parent, and it notes its running task in `marks`."""
    global _MARKS
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    signal.signal(signal.SIGTERM, signal.SIG_DFL)
    _die_with(parent)
    _MARKS = marks


def _run_marked(fn: Callable[[Task], Row], batch: list[tuple[int, Task]]) -> list[Row]:
    """run_batch in a local worker, the index of the running task noted in the marks directory."""
    mark = os.path.join(_MARKS, str(os.getpid()))
    if isinstance(fn, BatchTask):  # one call for the batch: its first task is noted as the running one
        with open(mark, "w", encoding="utf-8") as fh:
            fh.write(str(batch[0][0]))
        try:
            return run_batch(fn, [t for _, t in batch])
        finally:
            os.remove(mark)

    def marked(item: tuple[int, Task]) -> Row:
        with open(mark, "w", encoding="utf-8") as fh:
            fh.write(str(item[0]))
        return fn(item[1])

    try:
        return run_batch(marked, batch)
    finally:
        os.remove(mark)


def _remove_stale_marks() -> None:
    """Remove the marks directories of main processes that were killed (they could not clean up)."""
    for path in glob.glob(os.path.join(tempfile.gettempdir(), f"{MARKS_PREFIX}*-*")):
        pid = os.path.basename(path)[len(MARKS_PREFIX):].split("-")[0]
        try:
            os.kill(int(pid), 0)
        except ProcessLookupError:
            shutil.rmtree(path, ignore_errors=True)
        except (ValueError, PermissionError):  # not ours, or another user's live process
            pass


def _name(task: Task, index: int) -> str:
    return str(task.get("key", f"#{index}"))


class LocalExecutor(Executor):
    """`workers` local processes (1: in the calling process, no pool)."""

    def __init__(self, workers: int | None = None) -> None:
        self.workers = workers or os.cpu_count() or 1
        self.description = f"{self.workers} local worker process{'es' if self.workers > 1 else ''}"
        self._pool: ProcessPoolExecutor | None = None
        self._marks = ""

    def _start(self) -> ProcessPoolExecutor:
        if self._pool is None:
            _remove_stale_marks()
            self._marks = tempfile.mkdtemp(prefix=f"{MARKS_PREFIX}{os.getpid()}-")
            self._pool = ProcessPoolExecutor(max_workers=self.workers, initializer=_worker_init,
                                             initargs=(os.getpid(), self._marks))
        return self._pool

    def imap_unordered(self, fn: Callable[[Task], Row], tasks: list[Task],
                       report: Callable[[str], None] | None = None,
                       together: Together | None = None) -> Iterator[tuple[Task, Row]]:
        if self.workers == 1 and isinstance(fn, BatchTask):
            for b in batches(tasks, together):
                yield from zip([tasks[i] for i in b], run_batch(fn, [tasks[i] for i in b]))
            return
        if self.workers == 1:
            for task in tasks:
                yield task, run_task(fn, task)
            return
        left, deaths = dict(enumerate(batches(tasks, together))), Counter[int]()
        while left:
            pool = self._start()
            try:
                futures = {pool.submit(_run_marked, fn, [(i, tasks[i]) for i in b]): k for k, b in left.items()}
                for fut in as_completed(futures):
                    rows = fut.result()
                    for i, row in zip(left.pop(futures[fut]), rows):
                        yield tasks[i], row
            except BrokenProcessPool:
                lost = self._lost()
                self.abort()
                deaths.update(lost.keys() or [-1])  # -1: deaths outside any task (a worker failed to start)
                if deaths[-1] >= WORKER_DEATHS:
                    raise WorkerLost(f"worker processes died {deaths[-1]} times outside any task; check that "
                                     "`python -c 'import bilevel'` works and memory is free, then rerun") from None
                named = ", ".join(f"{_name(tasks[i], i)} ({why})" for i, why in lost.items()) or "no task"
                if worst := [i for i in lost if deaths[i] >= WORKER_DEATHS]:
                    raise WorkerLost(f"task {_name(tasks[worst[0]], worst[0])} lost its worker process "
                                     f"{deaths[worst[0]]} times ({lost[worst[0]]}); finished rows are kept: free "
                                     "memory or use fewer workers, then rerun the same command to resume") from None
                if report:
                    report(f"a worker process died running {named}: new pool, rerunning "
                           f"{sum(map(len, left.values()))} unfinished task(s)")

    def _lost(self) -> dict[int, str]:
        """Index -> how its worker died, for the tasks whose worker died (not those the broken pool stopped)."""
        manager = getattr(self._pool, "_executor_manager_thread", None)
        if manager is not None:
            manager.join(5)  # it stops and reaps every worker of the broken pool: exit codes are final after this
        running: dict[int, str] = {}
        for proc in list((self._pool._processes or {}).values()) if self._pool else []:
            try:
                with open(os.path.join(self._marks, str(proc.pid)), encoding="utf-8") as fh:
                    index = int(fh.read())
            except (OSError, ValueError):
                continue
            code = proc.exitcode
            running[index] = "exit code None" if code is None else (
                signal.Signals(-code).name if code < 0 and -code in signal.valid_signals() else f"exit code {code}")
        died = {i: why for i, why in running.items() if why not in ("exit code None", "SIGTERM")}
        return died or running  # SIGTERM from outside looks like the pool's own clean-up: suspect every one

    def abort(self) -> None:
        if self._pool is None:
            return
        # ProcessPoolExecutor has no terminate() before Python 3.14 and shutdown alone waits for running tasks;
        # queued futures are not cancelled first (3.11 then fails to mark them broken, with a traceback)
        procs = list((self._pool._processes or {}).values())
        manager = getattr(self._pool, "_executor_manager_thread", None)
        for proc in procs:
            proc.terminate()
        self._pool.shutdown(wait=False)
        for proc in procs:
            proc.join(5)
        if manager is not None:  # its clean-up closes the wake-up pipe: done before exit, where 3.11's exit hook
            manager.join(5)      # writes to that pipe unlocked (a traceback "Bad file descriptor" on a stop)
        self._pool = None
        shutil.rmtree(self._marks, ignore_errors=True)

    def close(self) -> None:
        if self._pool is not None:
            self._pool.shutdown()
            self._pool = None
            shutil.rmtree(self._marks, ignore_errors=True)


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
        self.workers = n
        self.description = f"Dask cluster {address} ({n} worker{'s' if n != 1 else ''} at start)"
        self._futures: list[Any] = []

    def imap_unordered(self, fn: Callable[[Task], Row], tasks: list[Task],
                       report: Callable[[str], None] | None = None,
                       together: Together | None = None) -> Iterator[tuple[Task, Row]]:
        from distributed import as_completed as dask_completed

        # pure=False: a fresh Dask key per submission, never a result cached from another run
        futures = {self.client.submit(run_batch, fn, [tasks[i] for i in b], pure=False): b
                   for b in batches(tasks, together)}
        self._futures = list(futures)
        for fut in dask_completed(futures):
            for i, row in zip(futures[fut], fut.result()):
                yield tasks[i], row
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
