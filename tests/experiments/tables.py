"""Helpers for comparing reproductions: every table of an output directory, timing columns dropped."""

from __future__ import annotations

import csv
import glob
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
