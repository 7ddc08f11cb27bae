"""The bracket [delta_lb, delta_ub] of the smallest destabilizing input poisoning of the De Persis–Tesi learners
(issue 46; bilevel.robust.depersis_tesi): per horizon, selection and data set, delta_lb by certified_margin (bisection
with certificates), delta_ub by the budget search with the minimal attack (both to a bracket of rel_tol), their ratio
and times, and the sampling
check at delta_lb (random poisonings on the budget sphere and both attacks, judged by the numpy re-fit). Data: the
batch reactor (n = 4, m = 2) at T = 15 and 50, and a 2-state, 1-input plant (N2_PLANT) where the stability-triangle
mechanism is exact. Budgets are RMS per entry (||Du||_F <= delta sqrt(m T)). One resumable sweep task per row.
"""

from __future__ import annotations

import csv
import os
import time
from typing import Any, Callable

import numpy as np

from ..files import atomic_open, write_rows_csv
from ..problems.willems import build_attack
from ..problems.willems_instance import WillemsSetting
from ..robust import as_target, attack_bound, certified_margin, sample_soundness
from .executor import open_executor
from .sweep import NUMBER, check_fields, run_sweep, sim_seeds, stderr_progress

N2_PLANT = (((1.1, 0.4), (0.0, 0.7)), ((0.0,), (1.0,)))
"""An open-loop unstable 2-state, 1-input plant (eigenvalues 1.1 and 0.7, controllable)."""
CASES = (("reactor", 15, "min-norm"), ("reactor", 15, "clarabel"), ("reactor", 50, "min-norm"),
         ("reactor", 50, "clarabel"), ("n2", 15, "min-norm"), ("n2", 15, "clarabel"))
ROW_SCHEMA = {"plant": str, "horizon": int, "selection": str, "data_seed": int, "delta_lb": NUMBER,
              "delta_ub": NUMBER, "ratio": NUMBER, "mechanism": str, "seconds_lb": NUMBER, "seconds_ub": NUMBER,
              "samples": int, "unstable": int, "worst_sample_radius": NUMBER, "attack_radius": NUMBER}


def margin_task(task: dict[str, Any]) -> dict[str, Any]:
    """One data set's bracket and its sampling check."""
    plant = N2_PLANT if task["plant"] == "n2" else None
    target = as_target(build_attack(WillemsSetting(objective="destabilize", horizon=task["N"], seed=task["seed"],
                                                   selection=task["selection"], plant=plant)))
    delta_ub, _, seconds_ub = attack_bound(target, rel_tol=task["rel_tol"])
    margin = certified_margin(target, delta_ub=delta_ub, rel_tol=task["rel_tol"])
    t0 = time.perf_counter()
    sound = sample_soundness(target, margin.delta_lb, samples=task["samples"], seed=task["seed"])
    deciding = [e.mechanism for e in margin.certificate.evidence if e.holds] if margin.certificate else []
    return {"plant": task["plant"], "horizon": task["N"], "selection": task["selection"], "data_seed": task["seed"],
            "delta_lb": margin.delta_lb, "delta_ub": margin.delta_ub, "ratio": margin.ratio,
            "mechanism": deciding[0] if deciding else "", "seconds_lb": margin.seconds_lb,
            "seconds_ub": seconds_ub, "samples": sound.samples, "unstable": sound.unstable
            + sum(r >= 1.0 for r in sound.attack_radius.values()), "worst_sample_radius": sound.worst_radius,
            "attack_radius": max(sound.attack_radius.values()), "sampling_seconds": time.perf_counter() - t0}


def summary_markdown(rows: list[dict[str, Any]]) -> str:
    """Per (plant, horizon, selection): data sets, median and worst ratio, median delta_lb and delta_ub, median
    seconds of the certified side and of the attack side, and the sampling check's unstable count."""
    lines = ["| plant | T | selection | data sets | 0 < lb <= ub | median ratio | worst ratio | median delta_lb | "
             "median delta_ub | mechanism | median s (lb) | median s (ub) | unstable at delta_lb (samples + attacks) |",
             "|---|---|---|---|---|---|---|---|---|---|---|---|---|"]
    for key in dict.fromkeys((r["plant"], r["horizon"], r["selection"]) for r in rows):
        rs = [r for r in rows if (r["plant"], r["horizon"], r["selection"]) == key]
        ratio = np.array([r["ratio"] for r in rs])
        ok = sum(0 < r["delta_lb"] <= r["delta_ub"] for r in rs)
        mechanisms = ", ".join(sorted({r["mechanism"] for r in rs}))
        lines.append(f"| {key[0]} | {key[1]} | {key[2]} | {len(rs)} | {ok} | {np.median(ratio):.4g} | "
                     f"{ratio.max():.4g} | {np.median([r['delta_lb'] for r in rs]):.4g} | "
                     f"{np.median([r['delta_ub'] for r in rs]):.4g} | {mechanisms} | "
                     f"{np.median([r['seconds_lb'] for r in rs]):.3g} | {np.median([r['seconds_ub'] for r in rs]):.3g}"
                     f" | {sum(r['unstable'] for r in rs)} of {sum(r['samples'] + 2 for r in rs)} |")
    return "\n".join(lines) + "\n"


def linf_markdown(rows: list[dict[str, Any]], frontier_csv: str) -> str:
    """The reactor's min-norm delta_lb (proven for the l2 ball, so for the linf box |Du_ij| <= delta inside it) against
    delta* of the defenses frontier (`frontier_csv`: the undefended De Persis–Tesi learner, reg 1e-8, under the
    project's linf destabilize attack) on the same data sets (equal data seeds): per horizon, paired median, worst
    and best ratio delta* / delta_lb."""
    with open(frontier_csv, newline="") as fh:
        frontier = [r for r in csv.DictReader(fh) if r["learner"] == "willems" and float(r["param"]) == 1e-8]
    lines = ["| T | data sets | median delta_lb | median linf delta* | median ratio | worst ratio | best ratio |",
             "|---|---|---|---|---|---|---|"]
    for horizon in sorted({r["horizon"] for r in rows if r["plant"] == "reactor"}):
        star = {int(r["data_seed"]): float(r["delta_star"]) for r in frontier if int(r["N"]) == horizon}
        pairs = np.array([(r["delta_lb"], star[r["data_seed"]]) for r in rows if (r["plant"], r["horizon"],
                          r["selection"]) == ("reactor", horizon, "min-norm") and r["data_seed"] in star])
        if pairs.size:
            ratio = pairs[:, 1] / pairs[:, 0]
            lines.append(f"| {horizon} | {len(pairs)} | {np.median(pairs[:, 0]):.4g} | {np.median(pairs[:, 1]):.4g} | "
                         f"{np.median(ratio):.3g} | {ratio.max():.3g} | {ratio.min():.3g} |")
    return "\n".join(lines) + "\n"


def run_dpt_margins(sims: int = 32, out_dir: str = "out/certify-dpt", seed: int = 0, samples: int = 10_000,
                    rel_tol: float = 0.01, workers: int | None = None, frontier_csv: str | None = None,
                    progress: Callable[[str], None] | None = stderr_progress) -> str:
    """Every case of CASES on `sims` data sets (resumable, margins.jsonl), margins.csv and margins.md (with
    linf_markdown against frontier_csv where given); returns the table."""
    tasks = [{"key": f"{plant}|N={n}|{selection}|sim={i}", "plant": plant, "N": n, "selection": selection,
              "seed": data_seed, "samples": samples, "rel_tol": rel_tol, "root_seed": seed}
             for plant, n, selection in CASES for i, data_seed in enumerate(sim_seeds(seed, sims))]
    with open_executor(workers, None) as executor:
        rows = run_sweep(margin_task, tasks, os.path.join(out_dir, "margins.jsonl"), executor, progress,
                         "certify-dpt", valid=lambda r: check_fields(r, ROW_SCHEMA))
    os.makedirs(out_dir, exist_ok=True)
    write_rows_csv(os.path.join(out_dir, "margins.csv"), rows, ROW_SCHEMA)
    table = summary_markdown(rows)
    if frontier_csv is not None:
        table += ("\nThe linf input budget: delta_lb against the linf attack's delta*\n\n"
                  + linf_markdown(rows, frontier_csv))
    with atomic_open(os.path.join(out_dir, "margins.md")) as fh:
        fh.write(table)
    return table
