"""Solver-comparison harness: every method on every chosen problem, one CSV row per run, written as made.

Rerunning with the same output file skips (problem, method) pairs already recorded, so an
interrupted comparison resumes without losing finished work.
"""

from __future__ import annotations

import csv
import math
import os
from dataclasses import dataclass
from typing import Any, Callable, Sequence

from ..errors import ModelError
from ..problems import registry
from ..result import BilevelResult
from ..solvers import solve

NOT_APPLICABLE = "not_applicable"
"""Status of a row whose method rejected the problem as outside its scope (a ModelError, e.g. 'global' on an NLP)."""

COLUMNS = ["problem", "method", "status", "objective", "known_optimum", "relative_gap", "certified",
           "stationarity", "complementarity", "lower_gap", "upper_feasibility", "wall_time", "nit", "starts", "seed"]


@dataclass(frozen=True)
class CompareRow:
    """One (problem, method) run; the CSV row of the comparison table."""

    problem: str
    method: str
    status: str
    objective: float
    known_optimum: float
    relative_gap: float
    certified: bool
    stationarity: float
    complementarity: float
    lower_gap: float
    upper_feasibility: float
    wall_time: float
    nit: int
    starts: int
    seed: int

    @property
    def reached(self) -> bool:
        """Known optimum reached to 1e-4 relative with a passing certificate."""
        return self.certified and math.isfinite(self.relative_gap) and self.relative_gap <= 1e-4


def relative_gap(value: float | None, known: float | None) -> float:
    """|value - known| / max(1, |known|); nan when either is unknown."""
    if value is None or known is None:
        return math.nan
    return abs(value - known) / max(1.0, abs(known))


def row_of(name: str, method: str, result: BilevelResult, starts: int, seed: int) -> CompareRow:
    """Summarize a result against the registered optimum."""
    known = registry.spec(name).optimum
    c = result.certificate
    nan = math.nan
    return CompareRow(name, method, result.status.value,
                      nan if result.upper_objective is None else result.upper_objective,
                      nan if known is None else known, relative_gap(result.upper_objective, known),
                      bool(c is not None and c.passed), c.stationarity if c else nan,
                      c.complementarity if c else nan, c.lower_gap if c else nan,
                      c.upper_feasibility if c else nan, result.wall_time, result.nit, starts, seed)


def not_applicable(name: str, method: str, starts: int, seed: int) -> CompareRow:
    """The row of a method that rejects the problem as outside its scope (no objective, no time)."""
    known = registry.spec(name).optimum
    nan = math.nan
    return CompareRow(name, method, NOT_APPLICABLE, nan, nan if known is None else known, nan, False, nan, nan, nan,
                      nan, 0.0, 0, starts, seed)


def _read(path: str) -> list[CompareRow]:
    if not os.path.exists(path):
        return []
    with open(path, newline="", encoding="utf-8") as fh:
        rows = []
        for r in csv.DictReader(fh):
            rows.append(CompareRow(r["problem"], r["method"], r["status"], float(r["objective"]),
                                   float(r["known_optimum"]), float(r["relative_gap"]), r["certified"] == "True",
                                   float(r["stationarity"]), float(r["complementarity"]), float(r["lower_gap"]),
                                   float(r["upper_feasibility"]), float(r["wall_time"]), int(r["nit"]),
                                   int(r["starts"]), int(r["seed"])))
        return rows


def compare(problems: Sequence[str], methods: Sequence[str], csv_path: str, starts: int = 8, seed: int = 0,
            method_options: dict[str, dict[str, Any]] | None = None,
            progress: Callable[[str], None] | None = print) -> list[CompareRow]:
    """Run every method on every problem, appending each row to csv_path as it finishes (resumable)."""
    done = {(r.problem, r.method): r for r in _read(csv_path)}
    new_file = not os.path.exists(csv_path)
    os.makedirs(os.path.dirname(os.path.abspath(csv_path)), exist_ok=True)
    total, k = len(problems) * len(methods), 0
    with open(csv_path, "a", newline="", encoding="utf-8") as fh:
        writer = csv.writer(fh)
        if new_file:
            writer.writerow(COLUMNS)
        for name in problems:
            for method in methods:
                k += 1
                if (name, method) in done:
                    continue
                opts = dict((method_options or {}).get(method, {}))
                try:
                    result = solve(registry.get(name), method=method, starts=starts, seed=seed, **opts)
                    row = row_of(name, method, result, starts, seed)
                except ModelError:
                    row = not_applicable(name, method, starts, seed)
                writer.writerow([getattr(row, c) for c in COLUMNS])
                fh.flush()
                done[(name, method)] = row
                if progress:
                    progress(f"[{k}/{total}] {name} / {method}: {row.status}, F = {row.objective:.6g}, "
                             f"gap {row.relative_gap:.1e}, {row.wall_time:.2f} s")
    return [done[(n, m)] for n in problems for m in methods]


def markdown_table(rows: Sequence[CompareRow]) -> str:
    """The comparison as a Markdown table plus a per-method summary line."""
    lines = ["| problem | method | status | F | known F* | rel. gap | certified | max residual | time (s) |",
             "|---|---|---|---|---|---|---|---|---|"]
    for r in rows:
        resid = max(abs(r.stationarity), abs(r.complementarity), abs(r.upper_feasibility),
                    max(r.lower_gap, 0.0)) if r.certified or math.isfinite(r.stationarity) else math.nan
        lines.append(f"| {r.problem} | {r.method} | {r.status} | {r.objective:.6g} | {r.known_optimum:.6g} | "
                     f"{r.relative_gap:.1e} | {'yes' if r.certified else 'no'} | {resid:.1e} | {r.wall_time:.3f} |")
    lines.append("")
    for method in dict.fromkeys(r.method for r in rows):
        mine = [r for r in rows if r.method == method and r.status != NOT_APPLICABLE]
        skipped = sum(1 for r in rows if r.method == method and r.status == NOT_APPLICABLE)
        if not mine:
            lines.append(f"- **{method}**: applies to none of these problems")
            continue
        hit = sum(r.reached for r in mine)
        t = sorted(r.wall_time for r in mine)
        outside = f"; not applicable to {skipped}" if skipped else ""
        lines.append(f"- **{method}**: known optimum reached (1e-4 relative, certified) on {hit}/{len(mine)} "
                     f"({100 * hit / len(mine):.0f}%){outside}; median time {t[len(t) // 2]:.3f} s")
    return "\n".join(lines) + "\n"
