"""Stealthy poisoning of state-space identification over data sets and budgets (issue 28's experiment, without figures).

One task per (T, delta, simulation): the flexible transmission's data (seed from SeedSequence(seed).spawn(sims), the
same data in every delta cell), budgets ||dX||_F <= delta ||X||_F and ||dU||_F <= delta ||U||_F, stealth delta on the
three residual statistics; the engine's attack (METHOD) on the problem declared once per worker process
(bilevel.problems.identification.problem_for). A row keeps ||d[A B]||_2 and ||d[A B]||_F of the numpy refit on the
poisoned data, the status and certificate, each test's statistic and p-value before and after, and the wall time.
"""

from __future__ import annotations

import json
import os
from typing import Any, Callable

import numpy as np

from ..files import atomic_open
from ..problems.identification import problem_for
from ..problems.identification_instance import attack_instance, least_squares_fit
from .executor import open_executor
from .sweep import FINITE, NUMBER, check_fields, run_sweep, sim_seeds, stderr_progress

DELTAS = (0.01, 0.025, 0.05, 0.075, 0.1)
HORIZONS = (100, 500)
METHOD = {"method": "ipopt", "starts": 1, "max_iter": 300, "ipopt": {"hessian_approximation": "limited-memory"}}
"""IPOPT with a limited-memory Hessian (the exact one takes minutes to prepare at T = 100, docs/identification.md);
its solved runs take 10 to 100 iterations, the ones it does not solve run to the limit."""
ROW_SCHEMA = {"norm2": NUMBER, "frobenius": NUMBER, "status": str, "certified": bool, "wall_time": FINITE,
              "before": dict, "after": dict}


def attack_task(task: dict[str, Any]) -> dict[str, Any]:
    """Run one stealthy attack and judge it with the defender's tests on the returned data."""
    atk = attack_instance("ss", T=task["T"], eps=task["delta"], stealth=task["delta"], seed=task["seed"],
                          lags=task["lags"])
    result = problem_for(atk).solve(**METHOD, seed=0)
    signals = {k: atk.signals[k] + np.reshape(result.x[f"d{k}"], atk.signals[k].shape) for k in atk.signals}
    Y, Z = atk.regression(signals)
    d = least_squares_fit(Y, Z) - atk.theta0
    tests = {"before": atk.tests(), "after": atk.tests(signals)}
    return {"norm2": float(np.linalg.norm(d, 2)), "frobenius": float(np.linalg.norm(d)),
            "status": result.status.value, "certified": bool(result.certificate.passed),
            "wall_time": float(result.wall_time),
            **{when: {k: {"statistic": t.statistic, "p_value": t.p_value} for k, t in ts.items()}
               for when, ts in tests.items()}}


def cell_tasks(sims: int, seed: int, horizons: tuple[int, ...] = HORIZONS, deltas: tuple[float, ...] = DELTAS,
               lags: int = 10) -> list[dict[str, Any]]:
    """Tasks T x delta x sims (simulation i has the same data in every delta cell of a T)."""
    return [{"key": f"ss/{T}/{delta}/{i}", "T": T, "delta": delta, "sim": i, "seed": s, "root_seed": seed,
             "lags": lags, "method": json.dumps(METHOD, sort_keys=True)}
            for T in horizons for delta in deltas for i, s in enumerate(sim_seeds(seed, sims))]


def summarize(rows: list[dict[str, Any]]) -> dict[str, dict[str, Any]]:
    """Per (T, delta) cell: quartiles of ||d[A B]||_2 over the certified solved rows, how many those are, and the
    median p-value of each test before and after."""
    cells: dict[str, list[dict[str, Any]]] = {}
    for r in rows:
        cells.setdefault(f"T={r['task']['T']}, delta={r['task']['delta']}", []).append(r)
    out = {}
    for cell, rs in cells.items():
        good = [r for r in rs if r["certified"] and r["status"] == "solved"]
        norms = np.array([r["norm2"] for r in good]) if good else np.full(1, np.nan)
        out[cell] = {"runs": len(rs), "solved_certified": len(good),
                     "norm2_quartiles": np.quantile(norms, [0.25, 0.5, 0.75]).tolist(),
                     **{f"median_p_{when}": {k: float(np.median([r[when][k]["p_value"] for r in rs]))
                                             for k in rs[0][when]} for when in ("before", "after")}}
    return out


def run_identification(sims: int = 100, out_dir: str = "out/identification", seed: int = 0,
                       workers: int | None = None, horizons: tuple[int, ...] = HORIZONS,
                       deltas: tuple[float, ...] = DELTAS, progress: Callable[[str], None] | None = stderr_progress,
                       dask: str | None = None) -> str:
    """The sweep (resumable rows in out_dir/stealthy.jsonl) and its summary (out_dir/summary.json); returns the
    summary's path. Tasks run on `workers` local processes or on the Dask cluster `dask`."""
    if sims < 1 or seed < 0:
        raise ValueError(f"identification sweep: sims must be >= 1 and seed >= 0, got sims={sims}, seed={seed}")
    os.makedirs(out_dir, exist_ok=True)
    with open_executor(workers, dask) as executor:
        rows = run_sweep(attack_task, cell_tasks(sims, seed, horizons, deltas),
                         os.path.join(out_dir, "stealthy.jsonl"), executor, progress, "identification",
                         valid=lambda row: check_fields(row, ROW_SCHEMA))
    path = os.path.join(out_dir, "summary.json")
    with atomic_open(path) as fh:
        json.dump(summarize(rows), fh, indent=1)
    if progress:
        progress(f"wrote {path}")
    return path
