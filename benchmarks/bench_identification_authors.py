"""The stealthy identification attack on Russo & Proutiere's terms: the engine against the authors' own SLSQP code
on their own data sets, side by side, every answer judged by the independent numpy check of their constraints.

Their code (rssalessio/data-poisoning-linear-systems, example_stealthy_attack: algorithm.py's ComputeAttack, SLSQP
with torch derivatives, 100 iterations, bounds [-0.5, 0.5], their start: 1e-5 normals from numpy seed 0) runs in their
own environment through benchmarks/authors_slsqp_runner.py, one process per data set, one torch/BLAS thread; its rows
are kept in a JSONL file (--results) and not rerun. The engine (bilevel.experiments.identification_paper.paper_attack:
stealth_kind "authors", objective ||d[A B]||_2, paper_method(T)) runs here with one BLAS thread on the same (T, data
set, delta), after one warm-up attack per T (declaration and compilation, once per process), a data set's deltas in
increasing order, each continued from the smaller delta's answer (paper_attack's `smaller`: warm start, cold run beside
it where needed); its rows are kept in --engine-results the same way. CPU times are time.process_time of each side's attack. Both answers are checked by
bilevel.ddc.stealth_check (tolerance 1e-6).

Run: python benchmarks/bench_identification_authors.py --authors DIR --python PY --data DIR [--horizons 100,500]
[--sims 10] [--sims-500 N] [--results FILE] [--engine-results FILE] [--recorded-only | --engine-only]; DIR: their
example_stealthy_attack folder, PY: a python with torch (CPU), numpy, scipy and momentchi2 (docs/identification.md:
`python3 -m venv V && V/bin/pip install torch numpy scipy momentchi2`), --data: their extracted datasets folder.
Output: benchmarks/results/bench_identification_authors.txt. The side-by-side table is over the (T, data set, delta)
both sides have; the second table is the engine's on every data set of the plan.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import subprocess
import sys
from datetime import datetime, timezone

import numpy as np

from bilevel.ddc.stealth_check import check_stealth
from bilevel.experiments.identification_paper import DELTAS, MONOTONE_FROM, PUBLISHED_MEDIANS, dataset_path, \
    load_dataset, PaperAttack, paper_attack, paper_method, true_parameters
from bilevel.threads import single_threaded

RUNNER = os.path.join(os.path.dirname(os.path.abspath(__file__)), "authors_slsqp_runner.py")
ONE_THREAD = {k: "1" for k in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS")}


def recorded(path: str) -> dict[tuple[int, int, float], dict]:
    """The rows a JSONL file holds, by (T, data set, delta) (none if there is no file)."""
    rows = {}
    if os.path.exists(path):
        for line in open(path):
            r = json.loads(line)
            rows[(r["T"], r["sim"], r["delta"])] = r
    return rows


def authors_rows(args: argparse.Namespace, plan: list[tuple[int, int]]) -> dict[tuple[int, int, float], dict]:
    """Their SLSQP's rows by (T, data set, delta), run where --results lacks them."""
    rows = recorded(args.results)
    for T, sim in plan:
        missing = [d for d in DELTAS if (T, sim, d) not in rows]
        if not missing or args.recorded_only or args.engine_only:
            continue
        out = subprocess.run([args.python, RUNNER, args.authors, args.data, str(T), str(sim),
                              ",".join(map(str, missing))], capture_output=True, text=True, check=True,
                             env={**os.environ, **ONE_THREAD})
        with open(args.results, "a") as fh:
            for line in out.stdout.splitlines():
                r = json.loads(line)
                rows[(r["T"], r["sim"], r["delta"])] = r
                fh.write(line + "\n")
    return rows


def engine_row(T: int, sim: int, delta: float, run: PaperAttack) -> dict:
    return {"T": T, "sim": sim, "delta": delta, "norm2": run.check["norm2"], "stealthy": run.check["stealthy"],
            "AB": run.check["AB"].tolist(), "cpu_time": run.cpu_time, "status": run.result.status.value,
            "iterations": run.result.nit, "start": run.start}


def engine_rows(args: argparse.Namespace, plan: list[tuple[int, int]]) -> dict[tuple[int, int, float], dict]:
    """The engine's rows by (T, data set, delta), run (one BLAS thread) where --engine-results lacks them."""
    rows = recorded(args.engine_results)
    if args.recorded_only:  # the data sets whose every delta the file holds
        plan[:] = [(T, sim) for T, sim in plan if all((T, sim, d) in rows for d in DELTAS)]
        return rows
    with single_threaded(), open(args.engine_results, "a") as fh:
        for T, sim in plan:
            smaller = None  # each delta continued from the smaller delta's answer (paper_attack)
            for d in DELTAS:
                if (T, sim, d) not in rows:
                    smaller = paper_attack(load_dataset(dataset_path(args.data, T, sim)), d, smaller)
                    rows[(T, sim, d)] = engine_row(T, sim, d, smaller)
                    fh.write(json.dumps(rows[(T, sim, d)]) + "\n")
                    fh.flush()
    return rows


def authors_check(row: dict, folder: str) -> dict:
    data = load_dataset(dataset_path(folder, row["T"], row["sim"]))
    x = np.asarray(row["x"])
    dX, dU = x[:data.X.size].reshape(data.X.shape), x[data.X.size:].reshape(data.U.shape)  # their row-major split
    return check_stealth(data.X, data.U, dX, dU, row["delta"])


def main() -> None:
    p = argparse.ArgumentParser()
    p.add_argument("--authors", required=True)
    p.add_argument("--python", required=True)
    p.add_argument("--data", required=True)
    p.add_argument("--horizons", default="100,500")
    p.add_argument("--sims", type=int, default=10)
    p.add_argument("--sims-500", type=int, default=None, help="data sets at T = 500 (default --sims)")
    p.add_argument("--results", default="authors_slsqp.jsonl")
    p.add_argument("--engine-results", default="engine_authors_terms.jsonl")
    p.add_argument("--recorded-only", action="store_true", help="compare on the rows --results and --engine-results "
                   "hold (the engine's data sets with every delta), run none")
    p.add_argument("--engine-only", action="store_true", help="run the engine where --engine-results lacks rows, "
                   "not the authors' SLSQP (compare on the rows --results holds)")
    args = p.parse_args()
    horizons = [int(t) for t in args.horizons.split(",")]
    plan = [(T, s) for T in horizons for s in range(args.sims if T != 500 or args.sims_500 is None else args.sims_500)]
    print(f"# bench_identification_authors  {datetime.now(timezone.utc):%Y-%m-%d %H:%M} UTC  {platform.node()}  "
          f"{platform.processor() or platform.machine()}  cores={os.cpu_count()}  python {platform.python_version()}  "
          f"load {os.getloadavg()[0]:.1f}")
    print(f"engine {paper_method(100)} (from T = {MONOTONE_FROM}: {paper_method(MONOTONE_FROM)}), stealth_kind "
          "'authors'; the authors' SLSQP (their code, 100 iterations); one thread each; CPU seconds per attack; "
          "stealthy: the independent numpy check of their constraints, tol 1e-6\n")
    ours = engine_rows(args, plan)
    theirs = authors_rows(args, plan)
    print("| T | delta | data sets | engine stealthy | SLSQP stealthy | engine >= SLSQP | engine >= SLSQP or SLSQP not "
          "stealthy | median ||d[A B]||_2 engine | SLSQP | authors' published median* | median CPU s engine | SLSQP | "
          "median SLSQP/engine CPU |")
    print("|---|---|---|---|---|---|---|---|---|---|---|---|---|")
    ratios, counts, per_T = [], np.zeros(3, dtype=int), {}
    for T in horizons:
        for d in DELTAS:
            keys = [(t, s, dd) for (t, s, dd) in ours if t == T and dd == d and (t, s, dd) in theirs and (t, s) in plan]
            if not keys:
                continue
            e = [ours[k] for k in keys]
            a = [authors_check(theirs[k], args.data) for k in keys]
            ac = [theirs[k]["cpu_time"] for k in keys]
            r = [x / y["cpu_time"] for x, y in zip(ac, e)]
            ratios += r
            per_T.setdefault(T, []).extend(zip(r, ac, [x["cpu_time"] for x in e]))
            wins = sum(x["norm2"] >= y["norm2"] * (1 - 1e-6) for x, y in zip(e, a))
            fair = sum(x["norm2"] >= y["norm2"] * (1 - 1e-6) or not y["stealthy"] for x, y in zip(e, a))
            counts += (len(keys), wins, fair)
            pub = PUBLISHED_MEDIANS.get(T, {}).get(d)
            print(f"| {T} | {d} | {len(keys)} | {sum(x['stealthy'] for x in e)} | {sum(y['stealthy'] for y in a)} | "
                  f"{wins} | {fair} | {np.median([x['norm2'] for x in e]):.3f} | "
                  f"{np.median([y['norm2'] for y in a]):.3f} | "
                  f"{'-' if pub is None else pub} | {np.median([x['cpu_time'] for x in e]):.3f} | "
                  f"{np.median(ac):.2f} | {np.median(r):.1f}x |")
    print(f"\nall cells: median SLSQP/engine CPU per data set {np.median(ratios):.1f}x (min {min(ratios):.1f}x, "
          f"max {max(ratios):.1f}x) over {len(ratios)} attacks; engine >= SLSQP on {counts[1]}/{counts[0]}, >= SLSQP "
          f"or SLSQP not stealthy on {counts[2]}/{counts[0]}")
    for T, v in per_T.items():
        r, a, e = np.array(v).T
        print(f"T = {T}: median SLSQP/engine CPU {np.median(r):.1f}x over {len(r)} attacks (min {r.min():.1f}x, max "
              f"{r.max():.1f}x); total CPU SLSQP {a.sum():.1f} s, engine {e.sum():.1f} s ({a.sum() / e.sum():.1f}x)")
    print("* of ||[A B]' - [A B]_true||_2 for their best of 10 starts, read off their figure (T = 500); the columns "
          "beside are ||[A B]' - [A B]_clean||_2 of one start (theirs: seed 0)")
    print("\nThe engine on every data set it ran (with or without an SLSQP row):\n")
    print("| T | delta | data sets | stealthy | solved | kept start (warm/cold/kept) | median ||d[A B]||_2 | "
          "median ||[A B]' - [A B]_true||_2 | authors' published median | median CPU s | total CPU s |")
    print("|---|---|---|---|---|---|---|---|---|---|---|")
    truth = true_parameters()
    for T in horizons:
        for d in DELTAS:
            e = [v for (t, s, dd), v in ours.items() if t == T and dd == d and (t, s) in plan]
            pub = PUBLISHED_MEDIANS.get(T, {}).get(d)
            print(f"| {T} | {d} | {len(e)} | {sum(x['stealthy'] for x in e)} | "
                  f"{sum(x['status'] == 'solved' for x in e)} | "
                  f"{'/'.join(str(sum(x.get('start') == k for x in e)) for k in ('warm', 'cold', 'kept'))} | "
                  f"{np.median([x['norm2'] for x in e]):.3f} | "
                  f"{np.median([np.linalg.norm(np.array(x['AB']) - truth, 2) for x in e]):.3f} | "
                  f"{'-' if pub is None else pub} | "
                  f"{np.median([x['cpu_time'] for x in e]):.3f} | {sum(x['cpu_time'] for x in e):.1f} |")
    print(f"\n# load at the end {os.getloadavg()[0]:.1f}")


if __name__ == "__main__":
    sys.exit(main())
