"""Parallel, resumable sweeps: each finished task is appended to a JSONL file as it completes.

A task is a JSON-serializable dict with a unique "key"; rerunning skips keys already in the file,
so an interrupted sweep resumes without losing finished work. Progress lines show count and ETA.
"""

from __future__ import annotations

import json
import os
import time
from concurrent.futures import ProcessPoolExecutor, as_completed
from typing import Any, Callable, Iterable

from ..threads import single_threaded


def read_rows(path: str) -> list[dict[str, Any]]:
    """All rows of a JSONL results file (a truncated last line from an interrupted run is ignored)."""
    if not os.path.exists(path):
        return []
    rows = []
    with open(path, encoding="utf-8") as fh:
        for line in fh:
            try:
                rows.append(json.loads(line))
            except json.JSONDecodeError:
                continue
    return rows


def load_timings(path: str) -> dict[str, tuple[int, float]]:
    """Sweep name -> (attacks run, wall seconds) recorded by earlier invocations in a timings.json file."""
    if not os.path.exists(path):
        return {}
    with open(path, encoding="utf-8") as fh:
        return {k: (int(v[0]), float(v[1])) for k, v in json.load(fh).items()}


def record_timing(path: str, timings: dict[str, tuple[int, float]], name: str, count: int, seconds: float) -> None:
    """Store one sweep's (attacks run, wall seconds) in `timings` and rewrite timings.json (kept across resumes)."""
    timings[name] = (int(count), float(seconds))
    with open(path, "w", encoding="utf-8") as fh:
        json.dump(timings, fh, indent=1)


def _run(fn: Callable[[dict[str, Any]], dict[str, Any]], task: dict[str, Any]) -> dict[str, Any]:
    with single_threaded():
        return {"key": task["key"], **fn(task)}


def run_sweep(fn: Callable[[dict[str, Any]], dict[str, Any]], tasks: Iterable[dict[str, Any]], path: str,
              workers: int | None = None, progress: Callable[[str], None] | None = print,
              label: str = "sweep",
              timed: Callable[[list[dict[str, Any]], float], None] | None = None) -> list[dict[str, Any]]:
    """Run fn on every task not yet in `path` (on `workers` processes), appending rows as they finish;
    if any ran, timed(tasks run, wall seconds) is called after the last one (e.g. to record_timing)."""
    tasks = list(tasks)
    keys = [t["key"] for t in tasks]
    if len(set(keys)) != len(keys):
        raise ValueError(f"{label}: task keys must be unique")
    done = {r["key"]: r for r in read_rows(path)}
    todo = [t for t in tasks if t["key"] not in done]
    os.makedirs(os.path.dirname(os.path.abspath(path)), exist_ok=True)
    if todo and progress:
        progress(f"[{label}] {len(done)} of {len(tasks)} already done; running {len(todo)} on "
                 f"{workers or os.cpu_count()} workers -> {path}")
    t0, finished = time.perf_counter(), 0
    report_every = max(1, len(todo) // 20)
    with open(path, "a", encoding="utf-8") as fh:
        if workers == 1:
            results = (_run(fn, t) for t in todo)
            pool = None
        else:
            pool = ProcessPoolExecutor(max_workers=workers or os.cpu_count())
            results = (f.result() for f in as_completed([pool.submit(_run, fn, t) for t in todo]))
        try:
            for row in results:
                fh.write(json.dumps(row) + "\n")
                fh.flush()
                done[row["key"]] = row
                finished += 1
                if progress and (finished % report_every == 0 or finished == len(todo)):
                    rate = (time.perf_counter() - t0) / finished
                    progress(f"[{label}] {finished}/{len(todo)} done, {rate * 1000:.0f} ms/task, "
                             f"ETA {rate * (len(todo) - finished):.0f} s")
        finally:
            if pool is not None:
                pool.shutdown(cancel_futures=True)
    if todo and timed is not None:
        timed(todo, time.perf_counter() - t0)
    return [done[k] for k in keys]
