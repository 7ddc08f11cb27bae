"""The DeePC certificate with kappa = max(1 - beta, 1 - gamma / 2) and the S-lemma's block norms (issue 46) on the
reproduction's 32 data sets (T = 100): delta_lb by certified_margin below the committed delta_ub
(docs/results/certify/certify.csv, the same attack), the sampling check at the new delta_lb (10,000 sphere poisonings
and the engine's attack, 1 start), and delta_lb with M >= (1 - beta)^2 M0 alone (gamma = inf) on the same bisection.
CPU seconds by time.process_time. Writes docs/results/certify/deepc_kappa.{csv,md}.
Usage: python benchmarks/certify_deepc_kappa.py [workers [data sets]]"""

from __future__ import annotations

import csv
import dataclasses
import os
import platform
import sys
import time
from multiprocessing import Pool

import numpy as np

from bilevel.experiments.certify import FAMILIES, certify_tasks
from bilevel.robust import as_target, certified_margin, sample_soundness
from bilevel.robust.deepc import gram_maps, kkt_maps

OUT = os.path.join(os.path.dirname(__file__), "..", "docs", "results", "certify")


def one(task: dict, delta_ub: float) -> dict:
    """One data set: delta_lb with kappa and with beta alone, then the sampling check at the new delta_lb."""
    family = FAMILIES["deepc"]
    target = as_target(family.build(task["size"], task["seed"]), starts=family.starts)
    c0 = time.process_time()
    margin = certified_margin(target, seed=task["attack_seed"], delta_ub=delta_ub, rel_tol=family.rel_tol)
    cpu_margin = time.process_time() - c0
    cost = target.declaration
    maps = gram_maps(cost)
    cost.cache["gram"] = dataclasses.replace(maps, gamma=float("inf"))
    cost.cache["kkt"] = dataclasses.replace(kkt_maps(cost), gamma=float("inf"))
    old = certified_margin(target, seed=task["attack_seed"], delta_ub=delta_ub, rel_tol=family.rel_tol)
    cost.cache.clear()
    found = sample_soundness(target, margin.delta_lb, task["samples"], seed=task["attack_seed"])
    return {"data_seed": task["seed"], "delta_lb": margin.delta_lb, "delta_lb_beta_alone": old.delta_lb,
            "delta_ub": delta_ub, "ratio": delta_ub / margin.delta_lb, "gain": margin.delta_lb / old.delta_lb,
            "cpu_margin": cpu_margin, "certificate_seconds": margin.certificate.seconds, "samples": found.samples,
            "unstable": found.unstable, "worst_radius": found.worst_radius,
            "attack_radius": max(found.attack_radius.values())}


def main(workers: int, count: int) -> None:
    start = time.strftime("%Y-%m-%d %H:%M UTC", time.gmtime())
    load0 = os.getloadavg()[0]
    with open(os.path.join(OUT, "certify.csv")) as f:
        ub = {int(r["data_seed"]): float(r["delta_ub"]) for r in csv.DictReader(f) if r["family"] == "deepc"}
    tasks = certify_tasks(32, False, 0, 10_000, ("deepc",))[:count]
    with Pool(workers) as pool:
        rows = pool.starmap(one, [(t, ub[t["seed"]]) for t in tasks])
    keys = list(rows[0])
    with open(os.path.join(OUT, "deepc_kappa.csv"), "w", newline="") as f:
        w = csv.DictWriter(f, keys)
        w.writeheader()
        w.writerows(rows)
    ratio = np.array([r["ratio"] for r in rows])
    old = np.array([r["delta_ub"] / r["delta_lb_beta_alone"] for r in rows])
    gain = np.array([r["gain"] for r in rows])
    ok = sum(0 < r["delta_lb"] <= r["delta_ub"] for r in rows)
    with open(os.path.join(OUT, "deepc_kappa.md"), "w") as f:
        f.write(f"`python benchmarks/certify_deepc_kappa.py {workers} {count}`, {start} to "
                f"{time.strftime('%H:%M UTC', time.gmtime())}, {platform.machine()}, {os.cpu_count()} cores shared "
                f"with other jobs (load {load0:.1f} at the start, {os.getloadavg()[0]:.1f} at the end). DeePC tracking "
                f"cost (level 2 J0), T = 100, the reproduction's 32 data sets; delta_ub from certify.csv (same "
                f"attack, 1 start); delta_lb by certified_margin with kappa = max(1 - beta, 1 - gamma / 2), and "
                f"with beta alone (gamma = inf) on the same bisection; every norm of a linear map of the poisoning "
                f"by the S-lemma (bilevel/robust/deepc.py, _block_norm).\n\n")
        f.write("| data sets | 0 < lb <= ub | median ub/lb | worst ub/lb | best ub/lb | median ub/lb, beta alone | "
                "worst, beta alone | delta_lb gain (median, min, max) | samples at lb | failing at lb | largest "
                "J / level (samples, attack) | median CPU s per margin |\n"
                "|---|---|---|---|---|---|---|---|---|---|---|---|\n")
        f.write(f"| {len(rows)} | {ok} | {np.median(ratio):.3g} | {ratio.max():.3g} | {ratio.min():.3g} | "
                f"{np.median(old):.3g} | {old.max():.3g} | {np.median(gain):.3f}, {gain.min():.3f}, {gain.max():.3f} "
                f"| {sum(r['samples'] for r in rows)} | {sum(r['unstable'] for r in rows)} | "
                f"{max(r['worst_radius'] for r in rows):.4f}, {max(r['attack_radius'] for r in rows):.4f} | "
                f"{np.median([r['cpu_margin'] for r in rows]):.2f} |\n")
    print(open(os.path.join(OUT, "deepc_kappa.md")).read())


if __name__ == "__main__":
    main(int(sys.argv[1]) if len(sys.argv) > 1 else 2, int(sys.argv[2]) if len(sys.argv) > 2 else 32)
