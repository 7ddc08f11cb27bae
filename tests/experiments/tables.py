"""Helpers for comparing reproductions: every table of an output directory, timing columns dropped."""

from __future__ import annotations

import csv
import glob
import math
import os
import re
import subprocess
import sys
import time
from typing import Any

BILEVEL = [sys.executable, "-m", "bilevel.cli"]


TIMING = re.compile(r"time|(^|\W)s(\W|$)|/ ours")
"""Headers of wall-time columns: "time_ms", "median time (s)", "ours: median s / attack", "DE / ours", ..."""


def _drop_time_columns(rows: list[list[str]]) -> list[list[str]]:
    keep = [i for i, name in enumerate(rows[0]) if not TIMING.search(name)] if rows else []
    return [[r[i] for i in keep if i < len(r)] for r in rows]


def _markdown_tables(text: str) -> list[list[list[str]]]:
    blocks: list[list[list[str]]] = [[]]
    for line in text.splitlines():
        if line.startswith("|"):
            blocks[-1].append([c.strip() for c in line.strip().strip("|").split("|")])
        elif blocks[-1]:
            blocks.append([])
    return [_drop_time_columns(b) for b in blocks if b]


def tables(out_dir: str) -> dict[str, Any]:
    """table_*.csv and table_*.md of `out_dir` and the Markdown tables of report.md, wall-time columns removed
    (the only fields that differ between two runs of the same tasks)."""
    out: dict[str, Any] = {}
    for path in sorted(glob.glob(os.path.join(out_dir, "table_*.csv"))):
        with open(path, newline="", encoding="utf-8") as fh:
            out[os.path.basename(path)] = _drop_time_columns(list(csv.reader(fh)))
    for path in sorted(glob.glob(os.path.join(out_dir, "table_*.md"))) + [os.path.join(out_dir, "report.md")]:
        with open(path, encoding="utf-8") as fh:
            out[os.path.basename(path)] = _markdown_tables(fh.read())
    return out


NUMBER = re.compile(r"-?(?:\d+\.?\d*|\.\d+)(?:[eE][-+]?\d+)?|nan|-?inf")


def _cell_difference(x: str, y: str, rtol: float) -> bool:
    """Whether two cells differ beyond rounding: their text outside numbers, or a number by more than rtol relative."""
    if x == y:
        return False
    if NUMBER.sub("#", x) != NUMBER.sub("#", y):
        return True
    pairs = zip(NUMBER.findall(x), NUMBER.findall(y))
    return any(not math.isclose(float(a), float(b), rel_tol=rtol, abs_tol=1e-300) and a != b for a, b in pairs)


def table_difference(out_a: str, out_b: str, rtol: float = 1e-9) -> str:
    """"" where two output directories' tables (tables(): time columns dropped) agree, numbers to rtol relative; else
    the first cell that differs. Runs of the same tasks in processes with other histories may differ in the last
    digits (a BLAS kernel's rounding depends on its arrays' alignment in memory), never beyond rounding."""
    a, b = tables(out_a), tables(out_b)
    if sorted(a) != sorted(b):
        return f"tables {sorted(a)} against {sorted(b)}"

    def walk(x: Any, y: Any, where: str) -> str:
        if isinstance(x, str) and isinstance(y, str):
            return f"{where}: {x!r} against {y!r}" if _cell_difference(x, y, rtol) else ""
        if isinstance(x, list) and isinstance(y, list) and len(x) == len(y):
            return next((d for i, (u, v) in enumerate(zip(x, y)) if (d := walk(u, v, f"{where}[{i}]"))), "")
        return f"{where}: {x!r} against {y!r}"

    return next((d for name in sorted(a) if (d := walk(a[name], b[name], name))), "")


def row_count(path: str) -> int:
    """Lines in a JSONL file (0 if it does not exist yet)."""
    if not os.path.exists(path):
        return 0
    with open(path, encoding="utf-8") as fh:
        return sum(1 for _ in fh)


def wait_for_rows(proc: subprocess.Popen, path: str, rows: int, timeout: float = 120.0) -> None:
    """Block until `path` holds at least `rows` lines (fails if the process ends first or on timeout)."""
    t0 = time.monotonic()
    while row_count(path) < rows:
        assert proc.poll() is None, f"the run ended (rc {proc.returncode}) before {rows} rows reached {path}"
        assert time.monotonic() - t0 < timeout, f"fewer than {rows} rows in {path} after {timeout} s"
        time.sleep(0.05)
