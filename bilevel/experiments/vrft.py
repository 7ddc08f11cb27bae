"""Reproduction of the paper's VRFT results: Table 1, figures 2-6, conventions side by side.

Every attack is one sweep task (resumable JSONL rows); seeds come from SeedSequence(seed).spawn(sims),
and sim i uses the same data in every (eps_u, eps_y) cell (common random numbers).
"""

from __future__ import annotations

import json
import os
from typing import Any, Callable

import numpy as np

from ..attacks.outcome import attack_stat, unstable
from ..attacks.vrft_batch import attack_budget_paths, attack_many
from ..attacks.vrft_methods import attack, attack_budget_path, attack_value
from ..defaults import param
from ..files import atomic_open
from ..problems.vrft_instance import CONVENTIONS, PAPER_EPS_Y, VRFTAttack, attack_instance
from ..result import BilevelResult
from .stats import mean_interval, wilson_interval
from .executor import BatchTask, open_executor
from .sweep import (FINITE, NUMBER, check_fields, committed_timings, load_timings, run_sweep, settings_of,
                    sim_seeds, stderr_progress)

EPS_U = (0.0, 0.1, 0.2)
EPS_Y = PAPER_EPS_Y
PAPER_TABLE1 = {
    ("A", 0.0): (0.0, 0.0, 0.0, 0.0, 0.0), ("A", 0.1): (0.78, 0.58, 13.9, 1.56, 0.78),
    ("A", 0.2): (47.1, 29.7, 19.8, 1.76, 1.56),
    ("B", 0.0): (0.0, 0.0, 0.0, 0.2, 0.0), ("B", 0.1): (0.0, 0.0, 34.4, 74.6, 75.2),
    ("B", 0.2): (0.0, 1.75, 54.7, 84.2, 88.9),
}
"""The paper's Table 1: % unstable closed loops out of 512 simulations (rows eps_u, columns eps_y)."""
N_SAMPLES, NORM = 512, "l2"
ROW_SCHEMA = {"value": NUMBER, "unstable": bool, "learner_loss": NUMBER, "wall_time": FINITE, "theta_poisoned": list}
"""The fields of a row (of each cell of a budget-path row) that the summaries read."""

def attack_summary(result: BilevelResult) -> dict[str, Any]:
    """Scalars of a VRFT attack result, one row of the reproduction's tables and of the CLI's output."""
    attack_stat(result, "learner_loss")
    st, cert = result.stats, result.certificate
    return {"method": result.method, "objective": st["objective"], "status": result.status.value,
            "value": attack_value(result), "value_clean": st["value_clean"], "learner_loss": st["learner_loss"],
            "spectral_radius": st["spectral_radius"], "spectral_radius_clean": st["spectral_radius_clean"],
            "delta_u": st["delta_u"], "delta_y": st["delta_y"], "wall_time": result.wall_time,
            "iterations": result.nit, "evaluations": st["evaluations"], "learner_stationarity": cert.stationarity,
            "refit_distance": cert.y_distance, "unstable": unstable(result), "certified": cert.passed}


def make_attack(task: dict[str, Any]) -> VRFTAttack:
    """The VRFTAttack instance described by a task dict."""
    return attack_instance(task["objective"], task["scenario"], task["eps_u"], task["eps_y"], task["seed"],
                           task.get("N", N_SAMPLES), task["convention"], task.get("norm", NORM))


def attack_task(task: dict[str, Any]) -> dict[str, Any]:
    """Run one attack (or a budget path: a list of cells in increasing eps_y); rows keep scalars and theta."""
    if task["method"] == "path":
        atk = make_attack({**task, "eps_y": task["eps_y"][0]})
        return {"cells": [{**attack_summary(r), "eps_y": eps, "theta_poisoned": r.y["theta"].tolist()}
                          for eps, r in zip(task["eps_y"], attack_budget_path(atk, task["eps_y"], seed=task["seed"]))]}
    limit = {"max_iter": task["max_iter"]} if "max_iter" in task else {}  # part of the task, so of its digest
    res = attack(make_attack(task), task["method"], seed=task["seed"], **limit)
    return {**attack_summary(res), "theta_poisoned": res.y["theta"].tolist()}


def _path_row(results: list[BilevelResult], eps_y: list[float]) -> dict[str, Any]:
    return {"cells": [{**attack_summary(r), "eps_y": eps, "theta_poisoned": r.y["theta"].tolist()}
                      for eps, r in zip(eps_y, results)]}


def attack_tasks(tasks: list[dict[str, Any]]) -> list[dict[str, Any]]:
    """attack_task's rows for a batch of tasks, the alternating attacks and the budget paths of equal settings solved
    together (bilevel.attacks.vrft_batch), the other methods one at a time."""
    rows: list[dict[str, Any] | None] = [None] * len(tasks)
    groups: dict[tuple, list[int]] = {}
    for i, t in enumerate(tasks):
        if t["method"] in ("alternating", "path"):
            groups.setdefault((t["method"], t.get("max_iter"), tuple(np.atleast_1d(t["eps_y"]))
                               if t["method"] == "path" else ()), []).append(i)
        else:
            rows[i] = attack_task(t)
    for (method, max_iter, eps_y), idx in groups.items():
        seeds = [tasks[i]["seed"] for i in idx]
        if method == "path":
            atks = [make_attack({**tasks[i], "eps_y": eps_y[0]}) for i in idx]
            for i, path in zip(idx, attack_budget_paths(atks, list(eps_y), seeds=seeds)):
                rows[i] = _path_row(path, list(eps_y))
            continue
        limit = {} if max_iter is None else {"max_iter": max_iter}
        for i, res in zip(idx, attack_many([make_attack(tasks[i]) for i in idx], "alternating", seeds, **limit)):
            rows[i] = {**attack_summary(res), "theta_poisoned": res.y["theta"].tolist()}
    return rows  # type: ignore[return-value]


BATCHED_TASKS = BatchTask(attack_tasks)
"""The reproduction's sweep function: each batch of tasks (same_data) through attack_tasks."""


def cell_tasks(sims: int, seed: int, convention: str, objective: str, method: str,
               eps_u: tuple[float, ...] = EPS_U, eps_y: tuple[float, ...] = EPS_Y) -> list[dict[str, Any]]:
    """Tasks of a Table-1-shaped sweep: scenarios A and B x eps_u x eps_y x sims; method "path" makes one
    task per (scenario, eps_u, sim) that attacks every eps_y in increasing order (attack_budget_path)."""
    tasks = []
    for scenario in ("A", "B"):
        for i, s in enumerate(sim_seeds(seed, sims)):
            for eu in eps_u:
                cells = [("*", sorted(eps_y))] if method == "path" else [(ey, ey) for ey in eps_y]
                for label, ey in cells:
                    tasks.append({"key": f"{convention}/{objective}/{method}/{scenario}/{eu}/{label}/{i}",
                                  "convention": convention, "objective": objective, "method": method,
                                  "scenario": scenario, "eps_u": eu, "eps_y": ey, "sim": i, "seed": s,
                                  "root_seed": seed, "N": N_SAMPLES, "norm": NORM,
                                  **({"max_iter": param("vrft.max_iter.targeted")} if objective == "targeted" else {})})
    return tasks


SEEDLESS = ("alternating", "path", "joint")
"""Methods whose attack draws nothing from the task's seed (one start, a deterministic first one: attack_task passes
the defaults); white noise draws its signals from it."""


def same_attack(task: dict[str, Any]) -> str:
    """A value shared by the tasks that run the same attack (run_sweep's `shared`): scenario A's data are a step
    pulse whatever the seed, so with a seedless method every simulation of a scenario-A cell is one attack."""
    if task["scenario"] != "A" or task["method"] not in SEEDLESS:
        return task["key"]
    return json.dumps({k: v for k, v in task.items() if k not in ("key", "sim", "seed")}, sort_keys=True)


def same_data(task: dict[str, Any]) -> tuple:
    """A value shared by the tasks of defaults["vrft.batch_sims"] consecutive data sets (run_sweep's `together`): run in
    one worker, their attacks are solved together (attack_tasks) and reuse the data and conditioning starts the worker
    keeps (bilevel.solvers.engine.starts, by data and output budget)."""
    return task["convention"], task["scenario"], task.get("N", N_SAMPLES), task["sim"] // param("vrft.batch_sims")


def valid_row(row: dict[str, Any]) -> str:
    """"" if a row has every field the summaries read, of its kind (each cell of a budget-path row too)."""
    if "cells" not in row:
        return check_fields(row, ROW_SCHEMA)
    cells = row["cells"]
    if not isinstance(cells, list) or not all(isinstance(c, dict) for c in cells):
        return "cells: not a list of objects"
    return next((f"cell {i}: {why}" for i, c in enumerate(cells)
                 if (why := check_fields(c, {**ROW_SCHEMA, "eps_y": FINITE}))), "")


def cell_rows(rows: list[dict[str, Any]]) -> list[dict[str, Any]]:
    """One row per (scenario, eps_u, eps_y, sim): budget-path rows are split into their cells."""
    out = []
    for r in rows:
        if "cells" not in r:
            out.append(r)
            continue
        head, tail = r["key"].split("/*/")
        out += [{**c, "key": f"{head}/{c['eps_y']}/{tail}"} for c in r["cells"]]
    return out


def summarize(rows: list[dict[str, Any]]) -> dict[tuple[str, float, float], dict[str, float]]:
    """Per (scenario, eps_u, eps_y): instability rate with Wilson CI, mean objective with t CI, median time
    (of the cell's own attack; a budget-path cell also carries its warm start)."""
    cells: dict[tuple[str, float, float], list[dict[str, Any]]] = {}
    for r in cell_rows(rows):
        key = r["key"].split("/")
        cells.setdefault((key[3], float(key[4]), float(key[5])), []).append(r)
    out = {}
    for k, rs in cells.items():
        n = len(rs)
        unstable = sum(bool(r["unstable"]) for r in rs)
        lo, hi = wilson_interval(unstable, n)
        m, mlo, mhi = mean_interval(np.array([r["value"] for r in rs]))
        loss = mean_interval(np.array([r["learner_loss"] for r in rs]))
        out[k] = {"n": n, "unstable": unstable, "rate": 100 * unstable / n, "rate_lo": 100 * lo,
                  "rate_hi": 100 * hi, "value": m, "value_lo": mlo, "value_hi": mhi, "loss": loss[0],
                  "loss_lo": loss[1], "loss_hi": loss[2],
                  "time_ms": 1000 * float(np.median([r["wall_time"] for r in rs]))}
    return out


def table_markdown(summary: dict, title: str, paper: dict | None = None) -> str:
    """Table-1-shaped Markdown: % unstable [95% CI] per cell, the paper's value beside ours when given."""
    lines = [f"**{title}**", ""]
    for scenario in ("A", "B"):
        head = " | ".join(f"eps_y = {e}" for e in EPS_Y)
        lines += [f"| Scenario {scenario} | {head} |", "|---" * (len(EPS_Y) + 1) + "|"]
        for eu in EPS_U:
            cells = []
            for j, ey in enumerate(EPS_Y):
                c = summary.get((scenario, eu, ey))
                if c is None:
                    cells.append("-")
                    continue
                text = f"{c['rate']:.1f}% [{c['rate_lo']:.1f}, {c['rate_hi']:.1f}]"
                if paper is not None:
                    text += f" (paper {paper[(scenario, eu)][j]}%)"
                cells.append(text)
            lines.append(f"| eps_u = {eu} | " + " | ".join(cells) + " |")
        lines.append("")
    n = next(iter(summary.values()))["n"] if summary else 0
    lines.append(f"{n} simulations per cell; brackets: 95% Wilson interval.")
    return "\n".join(lines) + "\n"


def write_csv(summary: dict, path: str) -> None:
    """One row per cell."""
    import csv

    with atomic_open(path, newline="") as fh:
        w = csv.writer(fh)
        cols = ["n", "unstable", "rate", "rate_lo", "rate_hi", "value", "value_lo", "value_hi", "loss", "loss_lo",
                "loss_hi", "time_ms"]
        w.writerow(["scenario", "eps_u", "eps_y"] + cols)
        for (sc, eu, ey), c in sorted(summary.items()):
            w.writerow([sc, eu, ey] + [c[k] for k in cols])


def side_default(sims: int) -> int:
    """Simulations per cell of the side sweeps for `sims` in Table 1's: a quarter, at least 8."""
    return max(8, sims // 4)


def sweep_plan(sims: int, side: int) -> list[tuple[str, int, str, str, str]]:
    """The eight sweeps of the reproduction: (name, simulations per cell, convention, objective, method)."""
    plan = [("maxmin-paper", sims, "paper", "maxmin", "alternating"),
            ("maxmin-paper-path", sims, "paper", "maxmin", "path")]
    plan += [(f"maxmin-{c}", side, c, "maxmin", "alternating") for c in CONVENTIONS if c != "paper"]
    return plan + [("white-noise-paper", side, "paper", "maxmin", "white-noise"),
                   ("destabilize-paper", side, "paper", "destabilize", "joint"),
                   ("targeted-paper", side, "paper", "targeted", "alternating")]


def attacks_in(tasks: list[dict[str, Any]]) -> int:
    """Attacks the tasks run (a path task runs one per budget; timings.json counts attacks)."""
    return sum(len(t["eps_y"]) if t["method"] == "path" else 1 for t in tasks)


def run_reproduction(sims: int = 32, out_dir: str = "out/vrft", seed: int = 0, workers: int | None = None,
                     side_sims: int | None = None, progress: Callable[[str], None] | None = stderr_progress,
                     dask: str | None = None) -> str:
    """Table 1 (paper convention) with `sims` per cell, the other conventions, the destabilizing and
    targeted attacks and the white-noise baseline with `side_sims`, figures 2-6 and report.md; tasks run on
    `workers` local processes or on the Dask cluster `dask` (bilevel.experiments.executor.open_executor)."""
    from . import vrft_figures

    if sims < 1 or (side_sims is not None and side_sims < 1) or seed < 0:
        raise ValueError(f"vrft reproduction: sims and side_sims must be >= 1 and seed >= 0, got sims={sims}, "
                         f"side_sims={side_sims}, seed={seed}")
    side = side_sims or side_default(sims)
    os.makedirs(out_dir, exist_ok=True)
    runs: dict[str, list[dict[str, Any]]] = {}
    plan = sweep_plan(sims, side)
    with open_executor(workers, dask) as executor:
        for name, n, convention, objective, method in plan:
            tasks = cell_tasks(n, seed, convention, objective, method)
            runs[name] = run_sweep(BATCHED_TASKS, tasks, os.path.join(out_dir, f"{name}.jsonl"), executor, progress, name,
                                   valid_row, same_attack, same_data, units=attacks_in,
                                   reference=committed_timings("vrft"))
    timings = load_timings(os.path.join(out_dir, "timings.json"), progress)
    summaries = {name: summarize(rows) for name, rows in runs.items()}
    for name, s in summaries.items():
        write_csv(s, os.path.join(out_dir, f"table_{name}.csv"))
    figures = vrft_figures.make_all(summaries, out_dir, seed)
    path = os.path.join(out_dir, "report.md")
    with atomic_open(path) as fh:
        fh.write(vrft_figures.report(summaries, figures, sims, side, timings, executor.description,
                                     settings_of([r for rs in runs.values() for r in rs], "root_seed", "N", "norm")
                                     | {"version": sorted({r["version"] for rs in runs.values() for r in rs})}))
    if progress:
        progress(f"wrote {path}")
    return path
