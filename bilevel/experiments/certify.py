"""`bilevel reproduce certify` (issue 46): per learner family and data set, delta_lb (the largest budget a certificate
proves safe: bilevel.robust.certified_margin), delta_ub (the smallest budget at which the project's attack
destabilizes the true loop, or for DeePC raises its tracking cost to robust.deepc_cost_factor times the clean one),
their ratio and times, and the sampling check of soundness at delta_lb (random poisonings on the budget sphere and
the attacks' answers, judged by a numpy re-fit). Families: VRFT, identification + CE LQR, the De Persis–Tesi
learners (batch reactor at T = 15 and 50, the 2-state N2_PLANT at T = 15; min-norm and Clarabel selections; input
poisoning, RMS budget per entry) and DeePC (tracking cost). One resumable sweep task per data set; certify.md,
certify.csv and a figure of the sorted brackets."""

from __future__ import annotations

import csv
import os
from dataclasses import dataclass
from typing import Any, Callable

import matplotlib

matplotlib.use("Agg")
import numpy as np  # noqa: E402
from matplotlib.figure import Figure  # noqa: E402

from ..files import atomic_open, atomic_path, write_rows_csv  # noqa: E402
from ..problems.deepc_instance import attack_instance as deepc_instance  # noqa: E402
from ..problems.identification_instance import attack_instance as ident_instance  # noqa: E402
from ..problems.vrft_instance import attack_instance as vrft_instance  # noqa: E402
from ..problems.willems import build_attack  # noqa: E402
from ..problems.willems_instance import WillemsSetting  # noqa: E402
from ..robust import Target, as_target, attack_bound, certified_margin, certify, sample_soundness  # noqa: E402
from .executor import open_executor  # noqa: E402
from .sweep import NUMBER, check_fields, check_subset, run_sweep, sim_seeds, stderr_progress  # noqa: E402

ROW_SCHEMA = {"family": str, "size": int, "data_seed": int, "delta_lb": NUMBER, "delta_ub": NUMBER, "ratio": NUMBER,
              "certificate_seconds": NUMBER, "seconds_lb": NUMBER, "seconds_ub": NUMBER, "samples": int,
              "unstable": int, "worst_radius": NUMBER, "attack_radius": NUMBER}
"""A row's fields (delta_lb 0: nothing proven; ratio inf then; worst_radius: the largest true spectral radius among
the samples at delta_lb, attack_radius: the largest among the attacks' answers there)."""


N2_PLANT = (((1.1, 0.4), (0.0, 0.7)), ((0.0,), (1.0,)))
"""An open-loop unstable 2-state, 1-input plant (eigenvalues 1.1 and 0.7, controllable): the De Persis–Tesi families
where the stability-triangle mechanism is exact."""
DEEPC_BUDGETS = (5e-5, 1e-4, 2e-4, 5e-4)
"""DeePC: the fixed budgets at which the certified bound on the tracking cost is set beside the attack's value."""


@dataclass(frozen=True)
class Family:
    """A learner family of the reproduction: its data-set builder (size, seed) -> declaration, the sizes of the full
    run and the size of the quick one, the attack's starts (None: the target's own attack takes none), its label, the
    brackets' relative tolerance (None: the robust.* defaults), an extra measurement per data set
    (target, delta_lb, attack seed) -> fields kept in certify.jsonl (None: none) and the starts of the attacks in the
    full run's soundness check at delta_lb (None: the attack's)."""

    build: Callable[[int, int], Any]
    sizes: tuple[int, ...]
    quick_size: int
    starts: int | None
    label: str
    rel_tol: float | None = None
    extra: Callable[[Target, float, int], dict[str, Any]] | None = None
    check_starts: int | None = None


def _dpt(plant: Any, selection: str) -> Callable[[int, int], Any]:
    """The De Persis–Tesi builder: input poisoning of the destabilize attack on `plant` (None: the batch reactor)."""
    return lambda n, seed: build_attack(WillemsSetting(objective="destabilize", horizon=n, seed=seed,
                                                       selection=selection, plant=plant))


def deepc_budget_table(target: Target, delta_lb: float, seed: int) -> dict[str, Any]:
    """DeePC at each of DEEPC_BUDGETS: the certified bound on the tracking cost and the attack's true cost, both over
    the clean cost (the bound inf where no bound is proven)."""
    clean = target.declaration.clean_cost
    table = []
    for delta in DEEPC_BUDGETS:
        bound = certify(target, delta).bound
        attack = target.true_radius(target.attacks["engine"](delta, seed)) * target.declaration.level / clean
        table.append([delta, float("inf") if bound is None else bound / clean, attack])
    return {"budgets": table}


FAMILIES: dict[str, Family] = {
    "vrft": Family(lambda n, seed: vrft_instance("destabilize", "B", 0.0, 0.0, seed=seed, N=n), (512, 64), 64, 8,
                   "VRFT, scenario B (N samples)"),
    "ident": Family(lambda n, seed: ident_instance("ss", n, 0.0, "ce-lqr", seed=seed), (100,), 100, 1,
                    "identification + CE LQR (T samples)", check_starts=64),
    "dpt-reactor-min-norm": Family(_dpt(None, "min-norm"), (15, 50), 15, None,
                                   "De Persis-Tesi, batch reactor, min-norm (T samples)", 0.01),
    "dpt-reactor-clarabel": Family(_dpt(None, "clarabel"), (15, 50), 15, None,
                                   "De Persis-Tesi, batch reactor, Clarabel (T samples)", 0.01),
    "dpt-n2-min-norm": Family(_dpt(N2_PLANT, "min-norm"), (15,), 15, None,
                              "De Persis-Tesi, 2-state plant, min-norm (T samples)", 0.01),
    "dpt-n2-clarabel": Family(_dpt(N2_PLANT, "clarabel"), (15,), 15, None,
                              "De Persis-Tesi, 2-state plant, Clarabel (T samples)", 0.01),
    "deepc": Family(lambda n, seed: deepc_instance(T=n, seed=seed), (100,), 60, 1,
                    "DeePC tracking cost, horizon 10 (T samples)", extra=deepc_budget_table),
}
"""The families certified, by name."""


def certify_task(task: dict[str, Any]) -> dict[str, Any]:
    """One data set: the attack's delta_ub, certified_margin below it, then the sampling check at delta_lb (its attacks
    with check_starts starts) and the family's extra measurement."""
    family = FAMILIES[task["family"]]
    target = as_target(family.build(task["size"], task["seed"]),
                       **({} if family.starts is None else {"starts": family.starts}))
    delta_ub, runs, seconds_ub = attack_bound(target, task["attack_seed"], family.rel_tol)
    margin = certified_margin(target, seed=task["attack_seed"], delta_ub=delta_ub, rel_tol=family.rel_tol)
    cert = margin.certificate
    row = {"family": task["family"], "size": task["size"], "data_seed": task["seed"], "delta_lb": margin.delta_lb,
           "delta_ub": margin.delta_ub, "ratio": margin.ratio,
           "certificate_seconds": float("nan") if cert is None else cert.seconds, "seconds_lb": margin.seconds_lb,
           "seconds_ub": seconds_ub, "samples": 0, "unstable": 0, "worst_radius": float("nan"),
           "attack_radius": float("nan"),
           "mechanism": next((e.mechanism for e in cert.evidence if e.holds), "") if cert else "",
           "attack_runs": [list(r) for r in runs]}
    if margin.delta_lb > 0:
        checked = target if task["check_starts"] == family.starts else \
            as_target(family.build(task["size"], task["seed"]), starts=task["check_starts"])
        found = sample_soundness(checked, margin.delta_lb, task["samples"], seed=task["attack_seed"])
        row.update(samples=found.samples, unstable=found.unstable, worst_radius=found.worst_radius,
                   attack_radius=max(found.attack_radius.values(), default=float("nan")))
    if family.extra is not None:
        row.update(family.extra(target, margin.delta_lb, task["attack_seed"]))
    return row


def certify_tasks(sims: int, quick: bool, seed: int, samples: int, families: tuple[str, ...]) -> list[dict[str, Any]]:
    """One task per (family, size, data set): the quick size, or every size of the full run."""
    seeds = list(enumerate(zip(sim_seeds(seed, sims), sim_seeds(seed + 1, sims))))
    tasks = []
    for name in families:
        family = FAMILIES[name]
        starts = family.starts if quick or family.check_starts is None else family.check_starts
        for size in (family.quick_size,) if quick else family.sizes:
            tasks += [{"key": f"{name}|size={size}|sim={i}", "family": name, "size": size, "seed": data_seed,
                       "attack_seed": attack_seed, "samples": samples, "root_seed": seed, "check_starts": starts}
                      for i, (data_seed, attack_seed) in seeds]
    return tasks


def summarize(rows: list[dict[str, Any]]) -> list[dict[str, Any]]:
    """Per family and size: data sets, how many brackets are consistent (0 < delta_lb <= delta_ub), median and worst
    ratio, median delta_lb and delta_ub, median time per certificate, and the samples' and attacks' unstable count."""
    out = []
    for key in sorted({(r["family"], r["size"]) for r in rows}):
        rs = [r for r in rows if (r["family"], r["size"]) == key]
        ratio = np.array([r["ratio"] for r in rs])
        out.append({"family": key[0], "size": key[1], "data_sets": len(rs),
                    "consistent": sum(0 < r["delta_lb"] <= r["delta_ub"] for r in rs),
                    "median_ratio": float(np.median(ratio)), "worst_ratio": float(np.max(ratio)),
                    "median_delta_lb": float(np.median([r["delta_lb"] for r in rs])),
                    "median_delta_ub": float(np.median([r["delta_ub"] for r in rs])),
                    "median_certificate_seconds": float(np.nanmedian([r["certificate_seconds"] for r in rs]))
                    if any(np.isfinite(r["certificate_seconds"]) for r in rs) else float("nan"),
                    "samples": sum(r["samples"] for r in rs),
                    "unstable": sum(r["unstable"] for r in rs) + sum(r["attack_radius"] >= 1 for r in rs),
                    "mechanisms": ", ".join(sorted({r.get("mechanism", "") for r in rs} - {""}))})
    return out


def summary_markdown(rows: list[dict[str, Any]]) -> str:
    lines = ["| family | size | data sets | 0 < lb <= ub | median ub/lb | worst ub/lb | median delta_lb | median "
             "delta_ub | s per certificate | samples at lb | unstable at lb | mechanism |", "|" + "---|" * 12]
    for s in summarize(rows):
        lines.append(f"| {s['family']} | {s['size']} | {s['data_sets']} | {s['consistent']} | {s['median_ratio']:.3g} "
                     f"| {s['worst_ratio']:.3g} | {s['median_delta_lb']:.3g} | {s['median_delta_ub']:.3g} | "
                     f"{s['median_certificate_seconds']:.2g} | {s['samples']} | {s['unstable']} | {s['mechanisms']} |")
    return "\n".join(lines) + "\n"


def budget_markdown(rows: list[dict[str, Any]]) -> str:
    """DeePC rows with a budget table (deepc_budget_table): per size and budget, the median and worst (largest) ratio
    of the certified bound to the attack's cost, and the medians of both over the clean cost ("" if none)."""
    rs = [r for r in rows if r.get("budgets")]
    lines = []
    for size in sorted({r["size"] for r in rs}):
        table = np.array([r["budgets"] for r in rs if r["size"] == size], dtype=float)  # (data sets, budgets, 3)
        lines += [f"\nDeePC, T = {size}: certified bound on the tracking cost against the attack's, both over the "
                  f"clean cost ({len(table)} data sets)\n", "| delta | median bound / J0 | median attack / J0 | "
                  "median bound / attack | worst bound / attack |", "|---|---|---|---|---|"]
        for j in range(table.shape[1]):
            ratio = table[:, j, 1] / table[:, j, 2]
            lines.append(f"| {table[0, j, 0]:g} | {np.median(table[:, j, 1]):.4g} | {np.median(table[:, j, 2]):.4g} | "
                         f"{np.median(ratio):.4g} | {np.max(ratio):.4g} |")
    return "\n".join(lines) + ("\n" if lines else "")


def linf_markdown(rows: list[dict[str, Any]], frontier_csv: str) -> str:
    """The reactor's min-norm delta_lb (proven for the l2 ball, so for the linf box |Du_ij| <= delta inside it) against
    delta* of the defenses frontier (`frontier_csv`: the undefended De Persis–Tesi learner, reg 1e-8, under the
    project's linf destabilize attack) on the same data sets (equal data seeds): per horizon, paired median, worst
    and best ratio delta* / delta_lb."""
    with open(frontier_csv, newline="") as fh:
        frontier = [r for r in csv.DictReader(fh) if r["learner"] == "willems" and float(r["param"]) == 1e-8]
    lines = ["\nThe linf input budget: the reactor's min-norm delta_lb against the linf attack's delta*\n",
             "| T | data sets | median delta_lb | median linf delta* | median ratio | worst ratio | best ratio |",
             "|---|---|---|---|---|---|---|"]
    for horizon in sorted({r["size"] for r in rows if r["family"] == "dpt-reactor-min-norm"}):
        star = {int(r["data_seed"]): float(r["delta_star"]) for r in frontier if int(r["N"]) == horizon}
        pairs = np.array([(r["delta_lb"], star[r["data_seed"]]) for r in rows if (r["family"], r["size"]) ==
                          ("dpt-reactor-min-norm", horizon) and r["data_seed"] in star])
        if pairs.size:
            ratio = pairs[:, 1] / pairs[:, 0]
            lines.append(f"| {horizon} | {len(pairs)} | {np.median(pairs[:, 0]):.4g} | {np.median(pairs[:, 1]):.4g} | "
                         f"{np.median(ratio):.3g} | {ratio.max():.3g} | {ratio.min():.3g} |")
    return "\n".join(lines) + "\n"


def bracket_figure(rows: list[dict[str, Any]]) -> Figure:
    """Per family, the brackets [delta_lb, delta_ub] of the data sets sorted by delta_ub (log scale)."""
    keys = sorted({(r["family"], r["size"]) for r in rows})
    fig = Figure(figsize=(5.0, 2.6 * len(keys)))
    for i, key in enumerate(keys):
        ax = fig.add_subplot(len(keys), 1, i + 1)
        rs = sorted((r for r in rows if (r["family"], r["size"]) == key), key=lambda r: r["delta_ub"])
        x = np.arange(len(rs))
        lb = np.array([max(r["delta_lb"], 1e-8) for r in rs])
        ub = np.array([r["delta_ub"] for r in rs])
        ax.vlines(x, lb, ub, color="0.6")
        ax.plot(x, ub, "v", label="delta_ub (attack)")
        ax.plot(x, lb, "^", label="delta_lb (certificate)")
        ax.set_yscale("log")
        ax.set_title(f"{FAMILIES[key[0]].label}, size {key[1]}", fontsize=9)
        ax.set_xlabel("data set (sorted by delta_ub)")
        ax.set_ylabel("relative budget")
        ax.grid(alpha=0.3)
        ax.legend(fontsize=7)
    fig.tight_layout()
    return fig


def write_outputs(rows: list[dict[str, Any]], out_dir: str, frontier_csv: str | None = None) -> str:
    """certify.csv (ROW_SCHEMA's fields), certify.md (the summary, DeePC's budget table, and with frontier_csv the
    linf comparison) and fig_brackets.png; returns the path of certify.md."""
    os.makedirs(out_dir, exist_ok=True)
    write_rows_csv(os.path.join(out_dir, "certify.csv"), rows, ROW_SCHEMA)
    with atomic_path(os.path.join(out_dir, "fig_brackets.png")) as tmp:
        bracket_figure(rows).savefig(tmp, dpi=120)
    path = os.path.join(out_dir, "certify.md")
    with atomic_open(path) as fh:
        fh.write(summary_markdown(rows) + budget_markdown(rows)
                 + ("" if frontier_csv is None else linf_markdown(rows, frontier_csv)))
    return path


def run_certify(sims: int = 32, out_dir: str = "out/certify", quick: bool = False, seed: int = 0,
                workers: int | None = None, dask: str | None = None, families: tuple[str, ...] | None = None,
                progress: Callable[[str], None] | None = stderr_progress, frontier_csv: str | None = None) -> str:
    """`bilevel reproduce certify`: the chosen families' brackets (None: all; rows appended to certify.jsonl as they
    finish, so a rerun resumes), then the outputs; quick: 2 data sets, each family's quick size (VRFT N = 64,
    De Persis-Tesi T = 15, DeePC T = 60), 200 samples, the soundness check's attacks with the attack's own starts."""
    chosen = check_subset(families, tuple(FAMILIES), "family", "certify families")
    samples = 200 if quick else 10_000
    tasks = certify_tasks(min(sims, 2) if quick else sims, quick, seed, samples, chosen)
    with open_executor(workers, dask) as executor:
        rows = run_sweep(certify_task, tasks, os.path.join(out_dir, "certify.jsonl"), executor, progress, "certify",
                         valid=lambda r: check_fields(r, ROW_SCHEMA))
    path = write_outputs(rows, out_dir, frontier_csv)
    if progress:
        progress(f"wrote {path}")
    return path
