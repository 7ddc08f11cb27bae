"""`bilevel reproduce certify` (issue 46): per learner family and data set, delta_lb (the largest budget a certificate
proves safe: bilevel.robust.certified_margin), delta_ub (the smallest budget at which the project's attack
destabilizes the true loop), their ratio and times, and the sampling check of soundness at delta_lb (random
poisonings on the budget sphere and the attacks' answers, judged by a numpy re-fit). One resumable sweep task per
data set; certify.md, certify.csv and a figure of the sorted brackets."""

from __future__ import annotations

import os
from dataclasses import dataclass
from typing import Any, Callable

import matplotlib

matplotlib.use("Agg")
import numpy as np  # noqa: E402
from matplotlib.figure import Figure  # noqa: E402

from ..files import atomic_open, atomic_path, write_rows_csv  # noqa: E402
from ..problems.identification_instance import attack_instance as ident_instance  # noqa: E402
from ..problems.vrft_instance import attack_instance as vrft_instance  # noqa: E402
from ..robust import as_target, certified_margin, sample_soundness  # noqa: E402
from .executor import open_executor  # noqa: E402
from .sweep import NUMBER, check_fields, run_sweep, sim_seeds, stderr_progress  # noqa: E402

ROW_SCHEMA = {"family": str, "size": int, "data_seed": int, "delta_lb": NUMBER, "delta_ub": NUMBER, "ratio": NUMBER,
              "certificate_seconds": NUMBER, "seconds_lb": NUMBER, "seconds_ub": NUMBER, "samples": int,
              "unstable": int, "worst_radius": NUMBER, "attack_radius": NUMBER}
"""A row's fields (delta_lb 0: nothing proven; ratio inf then; worst_radius: the largest true spectral radius among
the samples at delta_lb, attack_radius: the largest among the attacks' answers there)."""


@dataclass(frozen=True)
class Family:
    """A learner family of the reproduction: its data-set builder (size, seed) -> declaration, the sizes of the full
    and the quick run, the attack's starts, its label, and further sizes the full run also certifies."""

    build: Callable[[int, int], Any]
    size: int
    quick_size: int
    starts: int
    label: str
    more_sizes: tuple[int, ...] = ()


FAMILIES: dict[str, Family] = {
    "vrft": Family(lambda n, seed: vrft_instance("destabilize", "B", 0.0, 0.0, seed=seed, N=n), 512, 64, 8,
                   "VRFT, scenario B (N samples)", (64,)),
    "ident": Family(lambda n, seed: ident_instance("ss", n, 0.0, "ce-lqr", seed=seed), 100, 100, 1,
                    "identification + CE LQR (T samples)"),
}
"""The families certified, by name; a family module adds its own (e.g. De Persis–Tesi)."""


def certify_task(task: dict[str, Any]) -> dict[str, Any]:
    """One data set: certified_margin, then the sampling check at delta_lb."""
    family = FAMILIES[task["family"]]
    target = as_target(family.build(task["size"], task["seed"]), starts=family.starts)
    margin = certified_margin(target, seed=task["attack_seed"])
    cert = margin.certificate
    row = {"family": task["family"], "size": task["size"], "data_seed": task["seed"], "delta_lb": margin.delta_lb,
           "delta_ub": margin.delta_ub, "ratio": margin.ratio,
           "certificate_seconds": float("nan") if cert is None else cert.seconds, "seconds_lb": margin.seconds_lb,
           "seconds_ub": margin.seconds_ub, "samples": 0, "unstable": 0, "worst_radius": float("nan"),
           "attack_radius": float("nan")}
    if margin.delta_lb > 0:
        found = sample_soundness(target, margin.delta_lb, task["samples"], seed=task["attack_seed"])
        row.update(samples=found.samples, unstable=found.unstable, worst_radius=found.worst_radius,
                   attack_radius=max(found.attack_radius.values(), default=float("nan")))
    return row


def certify_tasks(sims: int, quick: bool, seed: int, samples: int, families: tuple[str, ...]) -> list[dict[str, Any]]:
    """One task per (family, size, data set): the quick size, or the full size and the family's more_sizes."""
    seeds = list(enumerate(zip(sim_seeds(seed, sims), sim_seeds(seed + 1, sims))))
    tasks = []
    for name in families:
        family = FAMILIES[name]
        for size in (family.quick_size,) if quick else (family.size, *family.more_sizes):
            tasks += [{"key": f"{name}|size={size}|sim={i}", "family": name, "size": size, "seed": data_seed,
                       "attack_seed": attack_seed, "samples": samples, "root_seed": seed}
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
                    "unstable": sum(r["unstable"] for r in rs) + sum(r["attack_radius"] >= 1 for r in rs)})
    return out


def summary_markdown(rows: list[dict[str, Any]]) -> str:
    lines = ["| family | size | data sets | 0 < lb <= ub | median ub/lb | worst ub/lb | median delta_lb | median "
             "delta_ub | s per certificate | samples at lb | unstable at lb |", "|" + "---|" * 11]
    for s in summarize(rows):
        lines.append(f"| {s['family']} | {s['size']} | {s['data_sets']} | {s['consistent']} | {s['median_ratio']:.3g} "
                     f"| {s['worst_ratio']:.3g} | {s['median_delta_lb']:.3g} | {s['median_delta_ub']:.3g} | "
                     f"{s['median_certificate_seconds']:.2g} | {s['samples']} | {s['unstable']} |")
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


def write_outputs(rows: list[dict[str, Any]], out_dir: str) -> str:
    """certify.csv, certify.md and fig_brackets.png; returns the path of certify.md."""
    os.makedirs(out_dir, exist_ok=True)
    write_rows_csv(os.path.join(out_dir, "certify.csv"), rows, ROW_SCHEMA)
    with atomic_path(os.path.join(out_dir, "fig_brackets.png")) as tmp:
        bracket_figure(rows).savefig(tmp, dpi=120)
    path = os.path.join(out_dir, "certify.md")
    with atomic_open(path) as fh:
        fh.write(summary_markdown(rows))
    return path


def run_certify(sims: int = 32, out_dir: str = "out/certify", quick: bool = False, seed: int = 0,
                workers: int | None = None, dask: str | None = None, families: tuple[str, ...] | None = None,
                progress: Callable[[str], None] | None = stderr_progress) -> str:
    """`bilevel reproduce certify`: every family's brackets (rows appended to certify.jsonl as they finish, so a rerun
    resumes), then the outputs; quick: 2 data sets, VRFT N = 64, 200 samples."""
    chosen = tuple(families or FAMILIES)
    samples = 200 if quick else 10_000
    tasks = certify_tasks(min(sims, 2) if quick else sims, quick, seed, samples, chosen)
    with open_executor(workers, dask) as executor:
        rows = run_sweep(certify_task, tasks, os.path.join(out_dir, "certify.jsonl"), executor, progress, "certify",
                         valid=lambda r: check_fields(r, ROW_SCHEMA))
    path = write_outputs([{k: r[k] for k in ROW_SCHEMA} for r in rows], out_dir)
    if progress:
        progress(f"wrote {path}")
    return path
