"""How much input poisoning it takes (issue 12): the distribution over data sets of delta_u*, the smallest linf input
budget at which the destabilizing attack makes the true closed loop unstable (bilevel.attacks.willems.
smallest_destabilizing_budget), with its median, quartiles and CDF figure, per horizon and learner selection."""

from __future__ import annotations

import csv
import os

import matplotlib

matplotlib.use("Agg")
import numpy as np  # noqa: E402
from matplotlib.figure import Figure  # noqa: E402

from ..attacks.willems import smallest_destabilizing_budget  # noqa: E402
from ..problems.willems import WillemsSetting  # noqa: E402
from .willems import sim_seeds  # noqa: E402


def budget_distribution(horizon: int, sims: int, selection: str = "min-norm", seed: int = 0,
                        starts: int = 8) -> list[dict[str, float]]:
    """delta_u* for the data of the reproduction's first `sims` simulations (inf: not destabilized up to 1.0)."""
    rows = []
    for data_seed, attack_seed in sim_seeds(seed, sims):
        setting = WillemsSetting(objective="destabilize", horizon=horizon, seed=data_seed, selection=selection)
        found = smallest_destabilizing_budget(setting, starts=starts, seed=attack_seed)
        rows.append({"horizon": horizon, "selection": selection, "data_seed": data_seed, "delta_star": found.delta,
                     "attacks": len(found.runs)})
    return rows


def summary_markdown(rows: list[dict[str, float]]) -> str:
    """One table line per (horizon, selection): sims, median, quartiles of delta_u*, and how many stayed stable."""
    lines = ["| N | selection | data sets | median delta_u* | quartiles | not destabilized up to 1.0 |",
             "|---|---|---|---|---|---|"]
    for key in sorted({(r["horizon"], r["selection"]) for r in rows}):
        d = np.array([r["delta_star"] for r in rows if (r["horizon"], r["selection"]) == key])
        q1, med, q3 = np.quantile(d, [0.25, 0.5, 0.75])  # inf sorts last: quantiles stay valid while finite
        lines.append(f"| {key[0]} | {key[1]} | {d.size} | {med:.3g} | {q1:.3g} - {q3:.3g} | {int(np.isinf(d).sum())} |")
    return "\n".join(lines) + "\n"


def write_outputs(rows: list[dict[str, float]], out_dir: str) -> str:
    """budget.csv, budget.md (summary_markdown) and fig_budget_cdf.png (empirical CDF per horizon and selection)."""
    os.makedirs(out_dir, exist_ok=True)
    with open(os.path.join(out_dir, "budget.csv"), "w", newline="", encoding="utf-8") as fh:
        writer = csv.DictWriter(fh, fieldnames=list(rows[0]))
        writer.writeheader()
        writer.writerows(rows)
    fig = Figure(figsize=(5.0, 3.4))
    ax = fig.add_subplot()
    for key in sorted({(r["horizon"], r["selection"]) for r in rows}):
        d = np.sort([r["delta_star"] for r in rows if (r["horizon"], r["selection"]) == key])
        ax.step(d, np.arange(1, d.size + 1) / d.size, where="post", label=f"N = {key[0]}, {key[1]}")
    ax.set_xlabel("delta_u* (smallest destabilizing linf input budget)")
    ax.set_ylabel("fraction of data sets")
    ax.set_xlim(0, 1.05)
    ax.set_ylim(0, 1)
    ax.grid(alpha=0.3)
    ax.legend()
    fig.tight_layout()
    fig.savefig(os.path.join(out_dir, "fig_budget_cdf.png"), dpi=150)
    table = summary_markdown(rows)
    with open(os.path.join(out_dir, "budget.md"), "w", encoding="utf-8") as fh:
        fh.write(table)
    return table
