"""Solver-comparison harness: every method on every chosen problem, one sweep task per run.

Runs go through bilevel.experiments.sweep (rows in `<csv>.jsonl` as they finish, resumable, on the local
pool or Dask); a rerun reuses a (problem, method) row only if starts, seed and options match too. The CSV
is rewritten from the rows at the end.
"""

from __future__ import annotations

import csv
import math
import os
from dataclasses import asdict, dataclass, fields
from typing import Any, Callable, Sequence

from ..attacks.registry import STRUCTURED as STRUCTURED_ATTACKS
from ..errors import ModelError
from ..files import atomic_open
from ..problems import registry
from ..result import BilevelResult
from ..solvers import solve
from ..solvers.registry import METHODS_VERSION
from .executor import open_executor
from .sweep import NUMBER, check_fields, committed_timings, run_sweep, stderr_progress

NOT_APPLICABLE = "not_applicable"
"""Status of a row whose method rejected the problem as outside its scope (a ModelError, e.g. 'global' on an NLP)."""

STRUCTURED = "structured"
"""The method name of a registered problem's own structured attack (vrft-*, willems-*) in a comparison."""

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


ROW_SCHEMA = {f.name: {"str": str, "float": NUMBER, "bool": bool, "int": int}[f.type] for f in fields(CompareRow)}
"""Each CSV column's kind in a row (NaN allowed where a number is unknown)."""


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


def compare_task(task: dict[str, Any]) -> dict[str, Any]:
    """One (problem, method) run described by a sweep task; the CompareRow's fields (not_applicable when the
    method rejects the problem as outside its scope). Method STRUCTURED runs the problem's own attack
    (bilevel.attacks.registry, a BilevelResult like any method's), where it has one."""
    outside = asdict(not_applicable(task["problem"], task["method"], task["starts"], task["seed"]))
    if task["method"] == STRUCTURED:
        attack = STRUCTURED_ATTACKS.get(task["problem"])
        if attack is None or task["options"]:  # no attack of its own; the attacks take no method options
            return outside
        result = attack(starts=task["starts"], **{"seed": task["seed"], **task["params"]})  # a data seed seeds it
    else:
        problem = registry.get(task["problem"], **task["params"])
        try:
            result = solve(problem, method=task["method"], starts=task["starts"], seed=task["seed"],
                           **task["options"])
        except ModelError:
            return outside
    return asdict(row_of(task["problem"], task["method"], result, task["starts"], task["seed"]))


def compare(problems: Sequence[str], methods: Sequence[str], csv_path: str, starts: int = 8, seed: int = 0,
            method_options: dict[str, dict[str, Any]] | None = None,
            progress: Callable[[str], None] | None = stderr_progress, workers: int | None = None,
            dask: str | None = None, params: dict[str, Any] | None = None) -> list[CompareRow]:
    """Run every method on every problem (resumable rows in csv_path's .jsonl), then write csv_path; `params`
    override the defaults of each problem that has them."""
    tasks = [{"key": f"{name}/{method}", "problem": name, "method": method,
              "params": registry.params_for(name, params or {}),
              "options": dict((method_options or {}).get(method, {})), "starts": starts, "seed": seed,
              "methods_version": METHODS_VERSION}
             for name in problems for method in methods]
    with open_executor(workers, dask) as executor:
        rows = run_sweep(compare_task, tasks, os.path.splitext(csv_path)[0] + ".jsonl", executor, progress,
                         "compare", valid=lambda r: check_fields(r, ROW_SCHEMA), reference=committed_timings("compare"))
    out = [CompareRow(**{c: r[c] for c in COLUMNS}) for r in rows]
    os.makedirs(os.path.dirname(os.path.abspath(csv_path)), exist_ok=True)
    with atomic_open(csv_path, newline="") as fh:
        writer = csv.writer(fh)
        writer.writerow(COLUMNS)
        writer.writerows([getattr(r, c) for c in COLUMNS] for r in out)
    return out


def markdown_table(rows: Sequence[CompareRow], params: dict[str, Any] | None = None) -> str:
    """The comparison as a Markdown table plus a per-method summary line (`params`: the problem parameters used)."""
    lines = ["| problem | method | status | F | known F* | rel. gap | certified | max residual | time (s) |",
             "|---|---|---|---|---|---|---|---|---|"]
    for r in rows:
        resid = max(abs(r.stationarity), abs(r.complementarity), abs(r.upper_feasibility),
                    max(r.lower_gap, 0.0)) if r.certified or math.isfinite(r.stationarity) else math.nan
        lines.append(f"| {r.problem} | {r.method} | {r.status} | {r.objective:.6g} | {r.known_optimum:.6g} | "
                     f"{r.relative_gap:.1e} | {'yes' if r.certified else 'no'} | {resid:.1e} | {r.wall_time:.3f} |")
    lines += ["", "Settings read from the rows: starts " + ", ".join(map(str, sorted({r.starts for r in rows})))
              + "; seed " + ", ".join(map(str, sorted({r.seed for r in rows})))
              + "".join(f"; {k} = {v}" for k, v in (params or {}).items()) + ".", ""]
    for method in dict.fromkeys(r.method for r in rows):
        mine = [r for r in rows if r.method == method and r.status != NOT_APPLICABLE]
        skipped = sum(1 for r in rows if r.method == method and r.status == NOT_APPLICABLE)
        if not mine:
            lines.append(f"- **{method}**: applies to none of these problems")
            continue
        known = [r for r in mine if math.isfinite(r.known_optimum)]
        hit = sum(r.reached for r in known)
        t = sorted(r.wall_time for r in mine)
        outside = f"; not applicable to {skipped}" if skipped else ""
        reached = (f"known optimum reached (1e-4 relative, certified) on {hit}/{len(known)} "
                   f"({100 * hit / len(known):.0f}%)" if known else "no known optimum")
        certified = sum(r.certified and r.status == "solved" for r in mine)
        lines.append(f"- **{method}**: {reached}; solved and certified {certified}/{len(mine)}{outside}; "
                     f"median time {t[len(t) // 2]:.3f} s")
    return "\n".join(lines) + "\n"
