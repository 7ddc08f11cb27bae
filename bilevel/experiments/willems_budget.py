"""How much input poisoning it takes (issue 12): the distribution over data sets of delta_u*, the smallest linf input
budget at which the destabilizing attack makes the true closed loop unstable (smallest_destabilizing_budget: the
budget path, then bisection), with its median, quartiles and CDF figure, per
horizon and learner selection. One resumable sweep task per data set (bilevel.experiments.sweep)."""

from __future__ import annotations

import dataclasses
import os
from typing import Any, Callable

import matplotlib

matplotlib.use("Agg")
import numpy as np  # noqa: E402
from matplotlib.figure import Figure  # noqa: E402

from ..attacks.willems import destabilize_attack  # noqa: E402
from ..errors import ModelError  # noqa: E402
from ..files import atomic_open, atomic_path, write_rows_csv  # noqa: E402
from ..problems.willems import kept_attack  # noqa: E402
from ..problems.willems_instance import WillemsSetting  # noqa: E402
from ..attacks.budget_search import BudgetSearch, smallest_budget  # noqa: E402
from .executor import open_executor  # noqa: E402
from .sweep import NUMBER, check_fields, committed_timings, run_sweep, stderr_progress  # noqa: E402
from .willems import sim_seeds  # noqa: E402

BUDGET_SCHEMA = {"horizon": int, "selection": str, "data_seed": int, "delta_star": NUMBER, "attacks": int}
"""A row's fields and kinds (delta_star inf: not destabilized up to 1.0)."""
HORIZONS = (15, 50)
SELECTIONS = ("min-norm", "clarabel", "scs")
"""The learners delta_u* is reported for: the default and the two SDP solvers' own Q (tikhonov is the
session-1 sweep's selection, kept for reruns of it, not a learner a user would pick)."""


def smallest_destabilizing_budget(setting: WillemsSetting, path: tuple[float, ...] = (0.1, 0.2, 0.3, 0.5, 0.7, 1.0),
                                  rel_tol: float = 0.05, **options: Any) -> BudgetSearch:
    """delta_u* of one data set: the framework's budget search (bilevel.attacks.budget_search) with destabilize_attack
    (options passed on) as the attack and an unstable true loop (spectral radius >= 1) as the goal."""
    if setting.poison != "u":
        raise ModelError(f"smallest_destabilizing_budget searches delta_u with input poisoning; got poison="
                         f"{setting.poison!r}: use poison='u'")

    def radius(delta: float) -> float:
        attack = kept_attack(dataclasses.replace(setting, objective="destabilize", delta_u=delta))
        return destabilize_attack(attack, **options).stats["spectral_radius"]

    return smallest_budget(radius, lambda rho: rho >= 1.0, path, rel_tol)


def budget_task(task: dict[str, Any]) -> dict[str, Any]:
    """delta_u* of one data set (task: horizon, selection, seed, attack_seed, starts)."""
    setting = WillemsSetting(objective="destabilize", horizon=task["horizon"], seed=task["seed"],
                             selection=task["selection"])
    found = smallest_destabilizing_budget(setting, starts=task["starts"], seed=task["attack_seed"])
    return {"horizon": task["horizon"], "selection": task["selection"], "data_seed": task["seed"],
            "delta_star": found.delta, "attacks": len(found.runs)}


def budget_distribution(horizons: tuple[int, ...], selections: tuple[str, ...], sims: int, path: str, seed: int = 0,
                        starts: int = 8, workers: int | None = None, dask: str | None = None,
                        progress: Callable[[str], None] | None = stderr_progress) -> list[dict[str, Any]]:
    """delta_u* (inf: not destabilized up to 1.0) for the data of the reproduction's first `sims` simulations, per
    horizon and selection; rows are appended to the JSONL file `path` as they finish, so a rerun resumes."""
    seeds = list(enumerate(sim_seeds(seed, sims)))
    tasks = [{"key": f"budget|N={n}|selection={sel}|sim={i}", "horizon": n, "selection": sel, "seed": data_seed,
              "attack_seed": attack_seed, "starts": starts, "root_seed": seed}
             for n in horizons for sel in selections for i, (data_seed, attack_seed) in seeds]
    with open_executor(workers, dask) as executor:
        rows = run_sweep(budget_task, tasks, path, executor, progress, "willems-budget",
                         valid=lambda r: check_fields(r, BUDGET_SCHEMA), reference=committed_timings("willems/budget"))
    return [{k: r[k] for k in BUDGET_SCHEMA} for r in rows]


def run_budget(sims: int = 16, out_dir: str = "out/willems-budget", seed: int = 0, workers: int | None = None,
               dask: str | None = None, progress: Callable[[str], None] | None = stderr_progress) -> str:
    """`bilevel reproduce willems-budget`: delta_u* for every horizon and selection (resumable, budget.jsonl), then
    budget.csv, budget.md and the CDF figure; returns the path of budget.md."""
    rows = budget_distribution(HORIZONS, SELECTIONS, sims, os.path.join(out_dir, "budget.jsonl"), seed, 8, workers,
                               dask, progress)
    write_outputs(rows, out_dir)
    path = os.path.join(out_dir, "budget.md")
    if progress:
        progress(f"wrote {path}")
    return path


def quantiles(values: np.ndarray, qs: tuple[float, ...]) -> np.ndarray:
    """Linear-interpolation quantiles of values that may hold +inf (never destabilized): inf where the interpolation
    reaches an inf (np.quantile gives nan there)."""
    finite = values[np.isfinite(values)]
    q = np.quantile(np.where(np.isinf(values), np.finfo(float).max, values), qs)
    return np.where(q > finite.max(initial=-np.inf), np.inf, q)


def summary_markdown(rows: list[dict[str, float]]) -> str:
    """One table line per (horizon, selection): sims, median, quartiles of delta_u*, and how many stayed stable."""
    lines = ["| N | selection | data sets | median delta_u* | quartiles | not destabilized |",
             "|---|---|---|---|---|---|"]
    for key in sorted({(r["horizon"], r["selection"]) for r in rows}):
        d = np.array([r["delta_star"] for r in rows if (r["horizon"], r["selection"]) == key])
        q1, med, q3 = quantiles(d, (0.25, 0.5, 0.75))
        lines.append(f"| {key[0]} | {key[1]} | {d.size} | {med:.3g} | {q1:.3g} - {q3:.3g} | {int(np.isinf(d).sum())} |")
    return "\n".join(lines) + "\n"


def budget_figure(rows: list[dict[str, float]]) -> Figure:
    """Empirical CDF of delta_u* per horizon and selection; the x-axis reaches 1.05 times the largest finite value."""
    fig = Figure(figsize=(5.0, 3.4))
    ax = fig.add_subplot()
    finite = [r["delta_star"] for r in rows if np.isfinite(r["delta_star"])]
    right = 1.05 * max(finite, default=1.0)  # every finite delta_u* on the axis; a set never destabilized stays off
    for key in sorted({(r["horizon"], r["selection"]) for r in rows}):
        d = np.sort([r["delta_star"] for r in rows if (r["horizon"], r["selection"]) == key])
        reached = np.arange(1, d.size + 1) / d.size
        shown = np.isfinite(d)
        ax.step(np.append(d[shown], right), np.append(reached[shown], reached[shown][-1] if shown.any() else 0.0),
                where="post", label=f"N = {key[0]}, {key[1]}")
    ax.set_xlabel("delta_u* (smallest destabilizing linf input budget, input units)")
    ax.set_ylabel("fraction of data sets")
    ax.set_xlim(0, right)
    ax.set_ylim(0, 1)
    ax.grid(alpha=0.3)
    ax.legend()
    fig.tight_layout()
    return fig


def write_outputs(rows: list[dict[str, float]], out_dir: str) -> str:
    """budget.csv, budget.md (summary_markdown) and fig_budget_cdf.png (empirical CDF per horizon and selection)."""
    os.makedirs(out_dir, exist_ok=True)
    write_rows_csv(os.path.join(out_dir, "budget.csv"), rows, rows[0])
    fig = budget_figure(rows)
    with atomic_path(os.path.join(out_dir, "fig_budget_cdf.png")) as tmp:
        fig.savefig(tmp, dpi=150)
    table = summary_markdown(rows)
    with atomic_open(os.path.join(out_dir, "budget.md")) as fh:
        fh.write(table)
    return table
