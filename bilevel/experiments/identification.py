"""`bilevel reproduce identification`: stealthy poisoning of state-space identification over data sets and budgets
(issue 28's experiment), the SLSQP baseline beside it, figures and report.md.

One task per (T, delta, simulation): the flexible transmission's data (seed from SeedSequence(seed).spawn(sims), the
same data in every delta cell), budgets ||dX||_F <= delta ||X||_F and ||dU||_F <= delta ||U||_F, stealth delta on the
three residual statistics; the engine's attack (METHOD) on the problem declared once per worker process
(bilevel.problems.identification.problem_for) and compiled there by a warm-up attack on data no task uses (warm_up),
so that every row's time is one attack's. The baseline sweep runs SLSQP (identification_baseline) on the first
`baseline_sims` simulations of every cell. Every row is judged by the defender's tests on a numpy refit of the
returned data (identification_baseline.judge). Both sweeps are resumable JSONL files written as rows finish.
"""

from __future__ import annotations

import json
import os
import time
from dataclasses import dataclass
from typing import Any, Callable

import numpy as np

from ..files import atomic_open
from ..problems.identification import problem_for
from ..problems.identification_instance import IdentificationAttack, attack_instance
from .executor import open_executor
from .identification_baseline import SLSQP_ITERATIONS, START_SCALE, judge, slsqp_attack
from .sweep import FINITE, NONNEGATIVE, NUMBER, check_fields, committed_timings, load_timings, run_sweep, \
    settings_of, sim_seeds, stderr_progress

DELTAS = (0.01, 0.025, 0.05, 0.075, 0.1)
HORIZONS = (100, 500)
LAGS = 10
METHOD = {"method": "reduced", "starts": 1, "nlp_tol": 1e-6}
"""IPOPT over the poisoning alone, the learner's fits and the statistics as functions of it with exact derivatives
(bilevel.solvers.reduced), from the start load_instance suggests (problems.identification.stealth_start). IPOPT on
the KKT form (method ipopt, limited-memory Hessian) found the same points at delta = 0.05 (T = 100, 10 data sets) in
about three times the CPU time (median 0.30 s against 0.10 s), and at delta = 0.1 ended at max_iter on non-stealthy
points (benchmarks/bench_identification). IPOPT's tol 1e-6 (the certificate's, against reduced's default 1e-8): the
points it ends at gave the same ||d[A B]||_2 to 7 digits as at 1e-8 (T = 100, 19 data sets at delta = 0.05 and
0.1), and the last 3-4 of 20-45 iterations (from the start before its restoration) are saved."""
WARM_UP_SEED = 2**32 - 1
"""Seed of the warm-up instance's data; the warm-up's result is discarded."""
JUDGED = {"norm2": NONNEGATIVE, "frobenius": NONNEGATIVE, "stealthy": bool, "max_relative_change": NUMBER,
          "budget_used": dict,
          "residual_norm": dict, "before": dict, "after": dict, "wall_time": FINITE, "cpu_time": FINITE}
"""wall_time: the solve's (engine: problem_for's re-targeting excluded) or the baseline's; cpu_time: the process's
CPU seconds in problem_for and the solve, or in the baseline (comparable under other load)."""
ROW_SCHEMA = {**JUDGED, "status": str, "certified": bool, "warm_up_cpu_time": FINITE}
"""warm_up_cpu_time: CPU seconds of the warm-up (declaring and compiling the problem) this task's process ran just
before it, 0 where the process had already run it for the task's T."""
_WARMED: set[tuple[int, int]] = set()
"""(T, lags) whose problem this process has declared and compiled."""
BASELINE_SCHEMA = {**JUDGED, "iterations": int}


@dataclass(frozen=True)
class Plan:
    """Sizes of one reproduction run."""

    sims: int
    baseline_sims: int
    horizons: tuple[int, ...]
    deltas: tuple[float, ...]


def make_plan(sims: int, quick: bool, baseline_sims: int | None = None) -> Plan:
    """The issue's grid (T = 100, 500; five deltas; SLSQP on max(2, sims // 10) simulations per cell), or the CI
    grid when quick (T = 100, delta = 0.01 and 0.05, at most 2 simulations, SLSQP on 1)."""
    if sims < 1 or (baseline_sims is not None and baseline_sims < 0):
        raise ValueError(f"identification reproduction: sims must be >= 1 and baseline_sims >= 0, got sims={sims}, "
                         f"baseline_sims={baseline_sims}")
    if quick:
        sims = min(sims, 2)
        return Plan(sims, min(sims, 1 if baseline_sims is None else baseline_sims), (100,), (0.01, 0.05))
    base = max(2, sims // 10) if baseline_sims is None else baseline_sims
    return Plan(sims, min(sims, base), HORIZONS, DELTAS)


def instance(task: dict[str, Any]) -> IdentificationAttack:
    """The stealthy state-space instance of a task."""
    return attack_instance("ss", T=task["T"], eps=task["delta"], stealth=task["delta"], seed=task["seed"],
                           lags=task["lags"])


def warm_up(task: dict[str, Any]) -> float:
    """Declare and compile the engine's problem for the task's T and lags in this process, once, by an attack on the
    data of WARM_UP_SEED; its CPU seconds, 0.0 where already done."""
    if (task["T"], task["lags"]) in _WARMED:
        return 0.0
    cpu = time.process_time()
    problem_for(instance({**task, "seed": WARM_UP_SEED})).solve(**METHOD, seed=0)
    _WARMED.add((task["T"], task["lags"]))
    return time.process_time() - cpu


def attack_task(task: dict[str, Any]) -> dict[str, Any]:
    """Run the engine's stealthy attack on one task (after this process's warm-up for its T) and judge its data with
    the defender's tests."""
    warm = warm_up(task)
    atk = instance(task)
    cpu = time.process_time()
    result = problem_for(atk).solve(**METHOD, seed=0)
    cpu = time.process_time() - cpu
    signals = {k: atk.signals[k] + np.reshape(result.x[f"d{k}"], atk.signals[k].shape) for k in atk.signals}
    return {**judge(atk, signals), "status": result.status.value, "certified": bool(result.certificate.passed),
            "wall_time": float(result.wall_time), "cpu_time": cpu, "warm_up_cpu_time": warm}


def baseline_task(task: dict[str, Any]) -> dict[str, Any]:
    """Run the SLSQP baseline on one task (its start drawn from the task's seed) and judge its data."""
    atk = instance(task)
    cpu = time.process_time()
    signals, seconds, iterations = slsqp_attack(atk, task["seed"], task["maxiter"], task["start_scale"])
    cpu = time.process_time() - cpu
    return {**judge(atk, signals), "iterations": iterations, "wall_time": seconds, "cpu_time": cpu}


def cell_tasks(sims: int, seed: int, horizons: tuple[int, ...] = HORIZONS, deltas: tuple[float, ...] = DELTAS,
               lags: int = LAGS, baseline: bool = False) -> list[dict[str, Any]]:
    """Tasks T x delta x sims (simulation i has the same data in every delta cell of a T) of the engine's attack, or
    of the SLSQP baseline."""
    method = {"maxiter": SLSQP_ITERATIONS, "start_scale": START_SCALE} if baseline \
        else {"method": json.dumps(METHOD, sort_keys=True), "warm_up_seed": WARM_UP_SEED}
    return [{"key": f"ss/{T}/{delta}/{i}", "T": T, "delta": delta, "sim": i, "seed": s, "root_seed": seed,
             "lags": lags, **method}
            for T in horizons for delta in deltas for i, s in enumerate(sim_seeds(seed, sims))]


def cells(rows: list[dict[str, Any]]) -> dict[tuple[int, float], list[dict[str, Any]]]:
    """Rows by (T, delta), in the rows' order."""
    out: dict[tuple[int, float], list[dict[str, Any]]] = {}
    for r in rows:
        out.setdefault((r["task"]["T"], r["task"]["delta"]), []).append(r)
    return out


def compare(rows: list[dict[str, Any]], baseline: list[dict[str, Any]]) -> dict[tuple[int, float], dict[str, Any]]:
    """Per (T, delta) cell with baseline rows, over the data sets both ran: how many, on how many the engine's attack
    is stealthy and reaches at least the baseline's ||d[A B]||_2 (or the baseline is not stealthy), and the median
    CPU-time ratio baseline / engine."""
    engine = {r["key"]: r for r in rows}
    out = {}
    for cell, bs in cells(baseline).items():
        pairs = [(engine[b["key"]], b) for b in bs if b["key"] in engine]
        if not pairs:
            continue
        wins = sum(e["stealthy"] and (e["norm2"] >= b["norm2"] * (1 - 1e-6) or not b["stealthy"]) for e, b in pairs)
        out[cell] = {"n": len(pairs), "at_least_baseline": wins,
                     "time_ratio": float(np.median([b["cpu_time"] / e["cpu_time"] for e, b in pairs]))}
    return out


def run_reproduction(sims: int = 100, out_dir: str = "out/identification", quick: bool = False, seed: int = 0,
                     workers: int | None = None, baseline_sims: int | None = None,
                     progress: Callable[[str], None] | None = stderr_progress, dask: str | None = None) -> str:
    """The engine's sweep (out_dir/stealthy.jsonl), the SLSQP baseline's (out_dir/slsqp.jsonl), figures and
    report.md; returns the report's path. Tasks run on `workers` local processes or on the Dask cluster `dask`."""
    from . import identification_figures

    plan = make_plan(sims, quick, baseline_sims)
    if seed < 0:
        raise ValueError(f"identification reproduction: seed must be >= 0, got {seed}")
    os.makedirs(out_dir, exist_ok=True)
    sweeps = {"stealthy": (attack_task, plan.sims, False, ROW_SCHEMA),
              "slsqp": (baseline_task, plan.baseline_sims, True, BASELINE_SCHEMA)}
    runs: dict[str, list[dict[str, Any]]] = {}
    with open_executor(workers, dask) as executor:
        for name, (fn, n, baseline, schema) in sweeps.items():
            tasks = cell_tasks(n, seed, plan.horizons, plan.deltas, baseline=baseline) if n else []
            runs[name] = run_sweep(fn, tasks, os.path.join(out_dir, f"{name}.jsonl"), executor, progress, name,
                                   lambda row, schema=schema: check_fields(row, schema),
                                   reference=committed_timings("identification")) if tasks else []
    timings = load_timings(os.path.join(out_dir, "timings.json"), progress)
    figures = identification_figures.make_all(runs["stealthy"], runs["slsqp"], out_dir)
    settings = settings_of(runs["stealthy"], "root_seed", "lags", "method") \
        | {"version": sorted({r["version"] for rs in runs.values() for r in rs})}
    path = os.path.join(out_dir, "report.md")
    with atomic_open(path) as fh:
        fh.write(identification_figures.report(runs["stealthy"], runs["slsqp"], figures, plan, timings,
                                               executor.description, settings))
    if progress:
        progress(f"wrote {path}")
    return path
