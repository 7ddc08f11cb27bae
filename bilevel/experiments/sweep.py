"""Resumable sweeps: each finished task is appended to a JSONL file as it completes, on any executor.

A task is a JSON-serializable dict with a unique "key"; fn(task) may depend on nothing else. Tasks that a
sweep's `shared` function maps to one value compute the same row: one of them runs and the row is written for each
(with its own key, task and digest); tasks its `together` function maps to one value run in one worker, one after
another (executor batches). A row
stores the task and its digest (every task field plus ALGORITHM_VERSION), and a rerun reuses a row
only when key and digest both match, so a row computed under other settings is never reused (it stays
in the file, unused). A row that is not UTF-8 or JSON, was torn by a kill mid-write, or fails the sweep's
schema (check_fields: each field's kind; "false" is no bool) is reported, set aside in `<path>.rejected` and
recomputed. Every other file is written atomically (bilevel.files). SIGINT/SIGTERM stop the workers at once and
keep every finished row.
"""

from __future__ import annotations

import hashlib
import json
import math
import os
import signal
import sys
import threading
import time
from contextlib import contextmanager
from importlib import metadata
from typing import Any, Callable, Hashable, Iterable, Iterator, Sequence

import numpy as np

from ..errors import ModelError
from ..files import atomic_open
from .executor import Executor, LocalExecutor, Together

try:
    _PACKAGE = metadata.version("bilevel")
except metadata.PackageNotFoundError:  # pragma: no cover - running from a source tree without install
    _PACKAGE = "unknown"


def _source_hash() -> str:
    """12 hex digits of a hash of every .py file of the installed package (paths and contents): any code change gives
    new digests, so rows computed by other code are never reused."""
    root = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
    h = hashlib.sha256()
    for folder, dirs, files in sorted(os.walk(root)):
        dirs.sort()
        for name in sorted(f for f in files if f.endswith(".py")):
            path = os.path.join(folder, name)
            h.update(os.path.relpath(path, root).encode())
            with open(path, "rb") as fh:
                h.update(fh.read())
    return h.hexdigest()[:12]


ALGORITHM_VERSION = f"bilevel-{_PACKAGE}/sweep-4/src-{_source_hash()}"
"""Part of every row's digest: the package version and a hash of its source, so that a rerun after any code change
recomputes (an interrupted run of the same code resumes)."""


class SweepInterrupted(KeyboardInterrupt):
    """SIGINT or SIGTERM arrived during a sweep; finished rows are on disk."""

    def __init__(self, signum: int) -> None:
        super().__init__(signal.Signals(signum).name)
        self.signum = signum


def sim_seeds(seed: int, sims: int) -> list[int]:
    """One integer seed per simulation, from SeedSequence(seed).spawn(sims)."""
    return [int(s.generate_state(1)[0]) for s in np.random.SeedSequence(seed).spawn(sims)]


def task_digest(task: dict[str, Any]) -> str:
    """Hash of every field of `task` and ALGORITHM_VERSION: equal digests mean the same computation."""
    text = json.dumps({"task": task, "version": ALGORITHM_VERSION}, sort_keys=True, default=str)
    return hashlib.sha256(text.encode()).hexdigest()[:20]


def stderr_progress(text: str) -> None:
    """Progress sink: stderr; on a terminal, a sweep's updates ("\\r"-prefixed) rewrite one line."""
    tty = sys.stderr.isatty()
    if text.startswith("\r"):
        sys.stderr.write(("\r\x1b[K" + text[1:]) if tty else text[1:] + "\n")
    else:
        sys.stderr.write(("\n" if tty else "") + text + "\n")
    sys.stderr.flush()


Kind = Any
"""A field's kind in a row schema: bool, int, str, list, dict, None, FINITE, NUMBER, NONNEGATIVE (a norm), or a tuple of
kinds."""
FINITE = "finite number"
NUMBER = "number (inf and nan allowed)"
NONNEGATIVE = "finite number >= 0"
ROW_SCHEMA: dict[str, Kind] = {"key": str, "digest": str, "version": str, "task": dict}
"""Fields every row has, whatever the sweep."""
Validator = Callable[[dict[str, Any]], str]
"""A sweep's row check: "" for a usable row, else why not (check_fields with the sweep's schema)."""


def _is(value: Any, kind: Kind) -> bool:
    if isinstance(kind, tuple):
        return any(_is(value, k) for k in kind)
    if kind is None:
        return value is None
    if kind in (FINITE, NUMBER, NONNEGATIVE):
        number = isinstance(value, (int, float)) and not isinstance(value, bool)
        return number and (kind == NUMBER or math.isfinite(value)) and (kind != NONNEGATIVE or value >= 0)
    if kind is int:
        return isinstance(value, int) and not isinstance(value, bool)
    return isinstance(value, kind)  # bool is exact: the string "false" is no bool


def _kind_name(kind: Kind) -> str:
    if isinstance(kind, tuple):
        return " or ".join(map(_kind_name, kind))
    return "null" if kind is None else kind if isinstance(kind, str) else kind.__name__


def check_subset(names: Sequence[str] | None, valid: Sequence[str], what: str, context: str) -> tuple[str, ...]:
    """The chosen names in `valid`'s order (None: all of them); an unknown or repeated name, or none, is refused
    ("{context}: unknown {what}(s) ...")."""
    if names is None:
        return tuple(valid)
    names = [str(name).strip() for name in names]
    unknown = [name for name in names if name not in valid]
    if unknown or not names or len(set(names)) != len(names):
        problem = (f"unknown {what}(s) {', '.join(map(repr, unknown))}" if unknown else
                   f"no {what} given" if not names else f"a {what} is repeated in {','.join(names)}")
        raise ModelError(f"{context}: {problem}; give a comma-separated subset of {','.join(valid)}")
    return tuple(name for name in valid if name in names)


def check_fields(row: dict[str, Any], schema: dict[str, Kind], what: str = "result field") -> str:
    """"" if `row` has every field of `schema` with its kind, else the problems ("lacks result fields (value)",
    "unstable: 'false' is not bool")."""
    missing = [f for f in schema if f not in row]
    if missing:
        return f"lacks {what}s ({', '.join(missing)})"
    wrong = [f"{f}: {row[f]!r:.30} is not {_kind_name(k)}" for f, k in schema.items() if not _is(row[f], k)]
    return "; ".join(wrong)


def _malformed(line: bytes, valid: Validator | None) -> tuple[dict[str, Any] | None, str]:
    """(row, "") for a usable row, else (None, why not)."""
    if not line.endswith(b"\n"):
        return None, "truncated line"
    try:
        row = json.loads(line.decode("utf-8"))
    except UnicodeDecodeError:
        return None, "not UTF-8"
    except json.JSONDecodeError as exc:
        return None, f"not JSON ({exc.msg})"
    if not isinstance(row, dict):
        return None, "not a JSON object"
    missing = [f for f in ROW_SCHEMA if f not in row]
    if missing:
        return None, f"lacks {', '.join(missing)}"
    why = check_fields(row, ROW_SCHEMA, "row field") or (valid(row) if valid is not None else "")
    return (None, why) if why else (row, "")


def load_rows(path: str, valid: Validator | None = None,
              report: Callable[[str], None] | None = None) -> list[dict[str, Any]]:
    """The usable rows of a JSONL results file; malformed lines (bad UTF-8 or JSON, a torn last line, a field
    missing or of the wrong kind) are moved to `<path>.rejected` and reported in one line."""
    if not os.path.exists(path):
        return []
    with open(path, "rb") as fh:
        lines = [line for line in fh if line.strip()]
    rows, good, bad = [], [], []
    for i, line in enumerate(lines, 1):
        row, why = _malformed(line, valid)
        if row is None:
            bad.append((i, why, line if line.endswith(b"\n") else line + b"\n"))
        else:
            rows.append(row)
            good.append(line)
    if bad:
        rejected = path + ".rejected"
        before = b""
        if os.path.exists(rejected):
            with open(rejected, "rb") as fh:
                before = fh.read()
        with atomic_open(rejected, "wb") as fh:
            fh.write(before + b"".join(line for _, _, line in bad))
        with atomic_open(path, "wb") as fh:
            fh.writelines(good)
        if report:
            report(f"{path}: set aside {len(bad)} malformed row(s) in {rejected}, to be recomputed: "
                   + "; ".join(f"line {i}: {why}" for i, why, _ in bad[:5]) + (" ..." if len(bad) > 5 else ""))
    return rows


def settings_of(rows: Iterable[dict[str, Any]], *fields: str) -> dict[str, list[Any]]:
    """Field -> sorted distinct values among the rows' tasks (what a report states, read from the rows)."""
    out: dict[str, set] = {f: set() for f in fields}
    for r in rows:
        for f in fields:
            if f in r["task"]:
                out[f].add(json.dumps(r["task"][f], sort_keys=True))
    return {f: sorted((json.loads(v) for v in vs), key=str) for f, vs in out.items()}


def _stored(path: str | None) -> dict[str, list[Any]]:
    """The entries of timings.json `path` as stored (name -> [count, seconds] or [count, seconds, workers]); {} where
    there is no file; ValueError (or TypeError, ...) where it is unreadable."""
    if not path or not os.path.exists(path):
        return {}
    with open(path, encoding="utf-8") as fh:
        stored = json.load(fh)
    return {str(k): [int(v[0]), float(v[1]), *([int(v[2])] if len(v) > 2 else [])] for k, v in stored.items()}


_UNREADABLE = (ValueError, TypeError, KeyError, IndexError, AttributeError)


def load_timings(path: str, report: Callable[[str], None] | None = None) -> dict[str, tuple[int, float]]:
    """Sweep name -> (attacks run, wall seconds) recorded by earlier invocations in a timings.json file; an
    unreadable one (e.g. cut by a run killed before writes were atomic) is reported and rewritten empty."""
    try:
        return {k: (v[0], v[1]) for k, v in _stored(path).items()}
    except _UNREADABLE as exc:
        if report:
            report(f"{path}: unreadable ({type(exc).__name__}); the wall times it held are lost, it now starts empty")
        with atomic_open(path) as fh:
            fh.write("{}")
        return {}


def record_timing(path: str, name: str, count: int, seconds: float, workers: int,
                  report: Callable[[str], None] | None = None) -> None:
    """Store one sweep's (attacks run, wall seconds, workers: what an estimate of a later run scales by) under `name`
    in timings.json `path`, keeping the other entries (an unreadable file is reported and replaced), atomically."""
    try:
        stored = _stored(path)
    except _UNREADABLE:
        load_timings(path, report)  # reports it and starts it empty
        stored = {}
    stored[name] = [int(count), float(seconds), int(workers)]
    with atomic_open(path) as fh:
        json.dump(stored, fh, indent=1)


_ROOT = os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
COMMITTED = os.path.join(_ROOT, "docs", "results")
"""The repository's committed results (present in a clone, absent from an installed wheel)."""


def pace(name: str, paths: Iterable[str | None]) -> tuple[float, str] | None:
    """(worker-seconds per counted unit, the timings.json it came from) of sweep `name` in the first of `paths` that
    recorded it with a positive count and its worker count; None where none did."""
    for path in paths:
        try:
            entry = _stored(path).get(name)
        except _UNREADABLE:
            continue
        if entry and len(entry) > 2 and entry[0] > 0 and entry[2] > 0 and math.isfinite(entry[1]) and entry[1] >= 0:
            return entry[1] * entry[2] / entry[0], str(path)
    return None


def committed_timings(folder: str) -> str:
    """The timings.json of the committed results in docs/results/<folder> (a reference pace for estimates)."""
    return os.path.join(COMMITTED, folder, "timings.json")


def estimate(label: str, count: int, executor: Executor, paths: Iterable[str | None]) -> str | None:
    """One line: the wall time `count` units should take on `executor` at the first recorded pace in `paths`."""
    found = pace(label, paths)
    if found is None:
        return None
    per_unit, source = found
    seconds = per_unit * count / max(1, executor.workers)
    folder = os.path.dirname(os.path.abspath(source))
    where = f"the committed run in {os.path.relpath(folder, _ROOT)}" if folder.startswith(COMMITTED) else \
        "an earlier run in this folder"
    return f"estimate ~{_duration(seconds)} on {executor.workers} worker(s), at the pace of {where}"


def _duration(seconds: float) -> str:
    """'45 s', '12 min' or '2.5 h'."""
    if seconds < 120:
        return f"{seconds:.0f} s"
    return f"{seconds / 60:.0f} min" if seconds < 7200 else f"{seconds / 3600:.1f} h"


@contextmanager
def _signals_raise() -> Iterator[None]:
    """While inside: SIGINT and SIGTERM raise SweepInterrupted in the main thread (no-op in other threads)."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return

    def handler(signum: int, _frame: Any) -> None:
        raise SweepInterrupted(signum)

    old = {s: signal.signal(s, handler) for s in (signal.SIGINT, signal.SIGTERM)}
    try:
        yield
    finally:
        for s, h in old.items():
            signal.signal(s, h)


def run_sweep(fn: Callable[[dict[str, Any]], dict[str, Any]], tasks: Iterable[dict[str, Any]], path: str,
              executor: Executor | None = None, progress: Callable[[str], None] | None = stderr_progress,
              label: str = "sweep", valid: Validator | None = None,
              shared: Callable[[dict[str, Any]], Hashable] | None = None, together: Together | None = None,
              timing: str | None = None, units: Callable[[list[dict[str, Any]]], int] = len,
              reference: str | None = None) -> list[dict[str, Any]]:
    """Run fn on every task without a matching row in `path` (on `executor`, default all local cores), appending
    rows as they finish; rows come back in task order. Tasks with equal shared(task) are computed once (the first of
    them); those with equal together(task) in one worker, in task order. The sweep's (units(tasks computed), wall
    seconds, workers) is recorded under `timing` (default `label`) in timings.json beside `path`; before starting it
    prints an estimate at the pace recorded there by an earlier run, else in `reference` (a committed timings.json)."""
    tasks = list(tasks)
    keys = [t["key"] for t in tasks]
    if len(set(keys)) != len(keys):
        raise ValueError(f"{label}: task keys must be unique")
    digests = {t["key"]: task_digest(t) for t in tasks}
    rows = load_rows(path, valid, progress)
    done = {}
    for r in rows:
        if digests.get(r["key"]) == r["digest"]:
            done.setdefault(r["key"], r)
    todo = [t for t in tasks if t["key"] not in done]
    stale = sum(r["key"] in digests and r["digest"] != digests[r["key"]] for r in rows)
    if not todo:
        return [done[k] for k in keys]
    groups: dict[Hashable, list[dict[str, Any]]] = {}
    for t in todo:
        groups.setdefault(t["key"] if shared is None else shared(t), []).append(t)
    computed = [g[0] for g in groups.values()]
    same = {g[0]["key"]: g for g in groups.values()}
    os.makedirs(os.path.dirname(os.path.abspath(path)), exist_ok=True)
    own = executor is None
    executor = executor or LocalExecutor()
    beside = os.path.join(os.path.dirname(os.path.abspath(path)), "timings.json")
    timing = timing or label
    guess = estimate(timing, units(computed), executor, [beside, reference]) if progress else None
    if progress:
        progress(f"[{label}] {len(done)} of {len(tasks)} already done"
                 + (f" ({stale} row(s) of other settings not reused)" if stale else "")
                 + f"; running {len(todo)}" + (f" ({len(computed)} distinct)" if len(computed) < len(todo) else "")
                 + f" on {executor.description} -> {path}")
        progress(f"[{label}] {guess or 'no earlier run recorded to estimate from; an ETA follows the first task'}")
    t0, ran = time.perf_counter(), 0
    t_first = t0
    report_every = max(1, len(computed) // 20)
    try:
        with _signals_raise(), open(path, "a", encoding="utf-8") as fh:
            for first, result in executor.imap_unordered(fn, computed, progress, together):
                for task in same[first["key"]]:
                    row = {**result, "key": task["key"], "digest": digests[task["key"]], "version": ALGORITHM_VERSION,
                           "task": {k: v for k, v in task.items() if k != "key"}}
                    fh.write(json.dumps(row) + "\n")
                    done[task["key"]] = row
                fh.flush()
                ran += 1
                now = time.perf_counter()
                t_first = now if ran == 1 else t_first
                if progress and ran == 1 and guess:
                    progress(f"\r[{label}] {len(done)}/{len(tasks)} done, the first after {now - t0:.1f} s "
                             "(with the workers' start-up)")
                elif progress and (ran == 1 or ran % report_every == 0 or ran == len(computed)):
                    # once every worker has finished a task, the pace since the first excludes the start-up; batches
                    # (`together`) arrive as bursts of rows, so there the pace counts from the start
                    rate = (ran - 1) / max(now - t_first, 1e-9) if ran > max(1, executor.workers) and together is None \
                        else ran / max(now - t0, 1e-9)
                    progress(f"\r[{label}] {len(done)}/{len(tasks)} done, {rate:.2f} tasks/s, "
                             f"ETA {(len(computed) - ran) / max(rate, 1e-9):.0f} s")
    except SweepInterrupted as exc:
        executor.abort()
        if progress:
            progress(f"[{label}] {exc}: workers stopped; {len(done)} of {len(tasks)} rows kept in {path}; "
                     "rerun the same command to resume")
        raise
    except BaseException:
        executor.abort()
        raise
    if own:
        executor.close()
    record_timing(beside, timing, units(computed), time.perf_counter() - t0, executor.workers, progress)
    return [done[k] for k in keys]
