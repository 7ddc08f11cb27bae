"""IPOPT option variants of the stealthy identification attack on the authors' terms, side by side in one process:
each data set's deltas run under every variant in turn (interleaved, so load drifts hit all alike), each variant
continued over the deltas as paper_attack does, against the authors' SLSQP rows recorded on the same machine.

A variant is paper_method(T) with top-level options (nlp_tol, max_iter) and IPOPT options (the rest) replaced. Per
variant: total CPU seconds and IPOPT iterations, median CPU per delta, the median SLSQP/engine CPU ratio per attack,
stealthy answers (bilevel.ddc.stealth_check, tolerance 1e-6), how many answers reach SLSQP's value (to 1e-6
relative; "fair": or SLSQP's answer breaks a bound), the criterion of issue 45 (>= 95 %), and how many fall below the
first variant's answer on the same (data set, delta) by more than 1e-4 relative.

Run: python benchmarks/bench_identification_options.py --data DIR --slsqp FILE [--T 100] [--sims 10] [--variants JSON];
DIR: the authors' extracted data sets; FILE: their SLSQP rows (bench_identification_authors.py's --results JSONL).
Output: benchmarks/results/bench_identification_options.txt.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import sys
from datetime import datetime, timezone
from typing import Any, Callable

import numpy as np

import bilevel.experiments.identification_paper as paper
from bilevel.ddc.stealth_check import check_stealth
from bilevel.threads import single_threaded

VARIANTS = {
    "main": {},
    "tol 1e-4, constr_viol_tol 1e-8": {"nlp_tol": 1e-4, "constr_viol_tol": 1e-8},
    "L-BFGS memory 3": {"limited_memory_max_history": 3},
    "mu_oracle probing": {"mu_oracle": "probing"},
    "extended low-rank solver": {"limited_memory_aug_solver": "extended"},
}
TOP = ("nlp_tol", "max_iter")


def method_of(variant: dict[str, Any], base: Callable[[int], dict[str, Any]]) -> Callable[[int], dict[str, Any]]:
    """paper_method with the variant's options in place."""
    top = {k: v for k, v in variant.items() if k in TOP}
    ipopt = {k: v for k, v in variant.items() if k not in TOP}
    return lambda T: {**base(T), **top, "ipopt": {**base(T).get("ipopt", {}), **ipopt}}


def slsqp_rows(path: str, T: int, folder: str) -> dict[tuple[int, float], dict[str, Any]]:
    """SLSQP's CPU time, value and verdict by (data set, delta), judged by the same check as the engine's."""
    rows = {}
    for line in open(path):
        r = json.loads(line)
        if r["T"] != T:
            continue
        data = paper.load_dataset(paper.dataset_path(folder, T, r["sim"]))
        x = np.asarray(r["x"])
        dX, dU = x[:data.X.size].reshape(data.X.shape), x[data.X.size:].reshape(data.U.shape)  # their row-major split
        check = check_stealth(data.X, data.U, dX, dU, r["delta"])
        rows[(r["sim"], r["delta"])] = {"cpu": r["cpu_time"], "norm2": check["norm2"], "stealthy": check["stealthy"]}
    return rows


def main() -> None:
    p = argparse.ArgumentParser()
    p.add_argument("--data", required=True)
    p.add_argument("--slsqp", required=True)
    p.add_argument("--T", type=int, default=100)
    p.add_argument("--sims", type=int, default=10)
    p.add_argument("--variants", default=None, help="JSON {name: options}; default VARIANTS")
    args = p.parse_args()
    variants = json.loads(args.variants) if args.variants else VARIANTS
    print(f"# bench_identification_options  {datetime.now(timezone.utc):%Y-%m-%d %H:%M} UTC  {platform.node()}  "
          f"{platform.processor() or platform.machine()}  cores={os.cpu_count()}  python {platform.python_version()}  "
          f"load {os.getloadavg()[0]:.1f}")
    base = paper.paper_method
    print(f"T = {args.T}, data sets 0-{args.sims - 1}, deltas {paper.DELTAS}; base {base(args.T)}; one BLAS thread; "
          "CPU seconds (time.process_time)\n")
    theirs = slsqp_rows(args.slsqp, args.T, args.data)
    rows: dict[str, list[dict[str, Any]]] = {name: [] for name in variants}
    try:
        with single_threaded():
            for name, variant in variants.items():  # declaration and compilation, once per variant's options
                paper.paper_method = method_of(variant, base)
                paper._WARMED.clear()
                paper.paper_attack(paper.load_dataset(paper.dataset_path(args.data, args.T, 0)), paper.DELTAS[0])
            for sim in range(args.sims):
                data = paper.load_dataset(paper.dataset_path(args.data, args.T, sim))
                for name, variant in variants.items():
                    paper.paper_method = method_of(variant, base)
                    smaller = None
                    for delta in paper.DELTAS:
                        smaller = paper.paper_attack(data, delta, smaller)
                        rows[name].append({"sim": sim, "delta": delta, "cpu": smaller.cpu_time,
                                           "nit": smaller.result.nit, "norm2": smaller.check["norm2"],
                                           "stealthy": bool(smaller.check["stealthy"])})
    finally:
        paper.paper_method = base
    print("| variant | total CPU s | IPOPT iterations | median CPU ms per delta | median SLSQP/engine CPU | stealthy | "
          ">= SLSQP | >= SLSQP or SLSQP not stealthy | below the first variant |")
    print("|---|---|---|---|---|---|---|---|---|")
    first = next(iter(rows.values()))
    for name, rs in rows.items():
        pairs = [(r, theirs[(r["sim"], r["delta"])]) for r in rs if (r["sim"], r["delta"]) in theirs]
        ratio = np.median([a["cpu"] / r["cpu"] for r, a in pairs])
        wins = sum(r["norm2"] >= a["norm2"] * (1 - 1e-6) for r, a in pairs)
        fair = sum(r["norm2"] >= a["norm2"] * (1 - 1e-6) or not a["stealthy"] for r, a in pairs)
        per_delta = " / ".join(f"{1e3 * np.median([r['cpu'] for r in rs if r['delta'] == d]):.0f}"
                               for d in paper.DELTAS)
        print(f"| {name} | {sum(r['cpu'] for r in rs):.2f} | {sum(r['nit'] for r in rs)} | {per_delta} | {ratio:.2f}x |"
              f" {sum(r['stealthy'] for r in rs)}/{len(rs)} | {wins}/{len(pairs)} | {fair}/{len(pairs)} | "
              f"{sum(r['norm2'] < b['norm2'] * (1 - 1e-4) for r, b in zip(rs, first))} |")
    print(f"\n# load at the end {os.getloadavg()[0]:.1f}")


if __name__ == "__main__":
    sys.exit(main())
