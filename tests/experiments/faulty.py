"""A tiny sweep whose tasks can kill their own worker, importable by worker processes; run as a script it is a
whole reproduction in miniature (rows, timings.json, a CSV table, report.md, a result JSON, a figure, an npz).

    python -m tests.experiments.faulty OUT_DIR TASKS SLEEP
"""

from __future__ import annotations

import csv
import json
import os
import signal
import sys
import time
from typing import Any

import numpy as np

from bilevel.experiments.executor import LocalExecutor
from bilevel.experiments.sweep import FINITE, NUMBER, check_fields, load_timings, run_sweep
from bilevel.files import atomic_open, atomic_path
from bilevel.result import BilevelResult, Status

DIE_MARKS = "FAULTY_DIE_MARKS"
"""Environment variable: directory of kill marks. A task with "die": n kills its worker until n marks exist."""
SCHEMA = {"value": NUMBER, "unstable": bool, "wall_time": FINITE, "theta": list}


def toy_task(task: dict[str, Any]) -> dict[str, Any]:
    """A deterministic row from task["x"]; with "die": n, SIGKILLs its own process the first n times it runs."""
    if task.get("die"):
        marks = os.environ[DIE_MARKS]
        done = len(os.listdir(marks))
        if done < task["die"]:
            open(os.path.join(marks, str(done)), "w").close()
            os.kill(os.getpid(), signal.SIGKILL)
    time.sleep(task.get("sleep", 0.0))
    x = task["x"]
    return {"value": x * x / 7 if x % 5 else float("inf"), "unstable": x % 3 == 0, "wall_time": 0.001 * x,
            "theta": [x / 3, -x / 11]}


def valid(row: dict[str, Any]) -> str:
    """The toy sweep's row schema."""
    return check_fields(row, SCHEMA)


def tasks(n: int, sleep: float = 0.0, die: dict[int, int] | None = None) -> list[dict[str, Any]]:
    """n tasks; die: x -> how many times task x kills its worker."""
    return [{"key": f"x={x}", "x": x, "sleep": sleep, **({"die": die[x]} if x in (die or {}) else {})}
            for x in range(n)]


_RAN: list[int] = []
"""The x of each task this process ran, in order (by ordered_task)."""


def ordered_task(task: dict[str, Any]) -> dict[str, Any]:
    """The worker's pid and the tasks it ran before this one (x's), then this one's x."""
    _RAN.append(task["x"])
    return {"pid": os.getpid(), "ran": list(_RAN)}


def reproduce(out: str, n: int, sleep: float = 0.0, workers: int = 2, progress: Any = None,
              die: dict[int, int] | None = None, together: Any = None) -> list[dict[str, Any]]:
    """Run (or resume) the toy sweep and write every kind of output file a reproduction writes; together: the
    sweep's batches."""
    os.makedirs(out, exist_ok=True)
    with LocalExecutor(workers) as executor:
        rows = run_sweep(toy_task, tasks(n, sleep, die), os.path.join(out, "rows.jsonl"), executor, progress, "toy",
                         valid, together=together)
    load_timings(os.path.join(out, "timings.json"), progress)  # as the reproductions read it for their reports
    with atomic_open(os.path.join(out, "table_toy.csv"), newline="") as fh:
        w = csv.writer(fh)
        w.writerow(["x", "value", "unstable", "time_ms"])
        w.writerows([r["task"]["x"], r["value"], r["unstable"], 1000 * r["wall_time"]] for r in rows)
    unstable = sum(bool(r["unstable"]) for r in rows)
    with atomic_open(os.path.join(out, "report.md")) as fh:
        fh.write(f"| rows | unstable |\n|---|---|\n| {len(rows)} | {unstable} |\n")
    best = min(rows, key=lambda r: r["value"])
    BilevelResult(Status.SOLVED, "toy", "toy", "toy", {"theta": np.array(best["theta"])}, {}, {}, best["value"],
                  None, None, 0.0, 0).to_json(os.path.join(out, "best.json"))
    with atomic_path(os.path.join(out, "theta.npz")) as tmp:
        np.savez(tmp, theta=np.array([r["theta"] for r in rows]))
    from matplotlib.figure import Figure

    fig = Figure(figsize=(2, 2))
    fig.add_subplot().plot([r["value"] for r in rows if np.isfinite(r["value"])])
    with atomic_path(os.path.join(out, "fig_toy.png")) as tmp:
        fig.savefig(tmp, dpi=40)
    return rows


if __name__ == "__main__":
    out_dir, count, pause = sys.argv[1], int(sys.argv[2]), float(sys.argv[3])
    reproduce(out_dir, count, pause, progress=lambda text: print(text, file=sys.stderr, flush=True))
    print(json.dumps(load_timings(os.path.join(out_dir, "timings.json"))))
