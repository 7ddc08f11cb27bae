"""Method reduced's compiled NLP (option compiled) against its callback path and the authors' own SLSQP on the authors'
data sets at T = 100, all three in one run: issue 45's speed target (median CPU per attack <= 1/30 of SLSQP's).

Per data set (0..N-1, their example_stealthy_attack data): the engine's attacks (paper_attack, each delta continued
from the smaller delta's answer) through method reduced's callbacks (paper_method(T)), then through its compiled NLP
(paper_method(T, compiled=True): the problem declared with the authors' statistics as CasADi expressions), then the
authors' SLSQP (their code, benchmarks/authors_slsqp_runner.py, seed 0) on the same data set; each process one BLAS
thread, CPU seconds by time.process_time, the first attack of each engine path per process (declaration and
compilation) run before and not counted. Every answer is judged by the independent numpy check of the authors'
constraints (bilevel.ddc.stealth_check, tolerance 1e-6).

Run: python benchmarks/bench_identification_compiled.py --authors DIR --python PY --data DIR [--sims 10] [--rows FILE]
(DIR, PY: as bench_identification_authors.py; FILE: every attack's row as JSONL).
Output: benchmarks/results/bench_identification_compiled.txt.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import subprocess
import sys
import time
from datetime import datetime, timezone

import numpy as np

from bilevel.ddc.stealth_check import check_stealth
from bilevel.experiments.identification_paper import DELTAS, dataset_path, load_dataset, paper_attack, paper_method
from bilevel.threads import single_threaded

T = 100
RUNNER = os.path.join(os.path.dirname(os.path.abspath(__file__)), "authors_slsqp_runner.py")
ONE_THREAD = {k: "1" for k in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS")}
PATHS = ("callbacks", "compiled")
NORM, CPU, NIT = "norm2", "cpu", "nit"


def load() -> str:
    with open("/proc/loadavg") as fh:
        return " ".join(fh.read().split()[:3])


def engine(data_path: str, compiled: bool) -> dict[float, dict]:
    """The engine's attacks on one data set, every delta continued (paper_attack)."""
    data, rows, smaller = load_dataset(data_path), {}, None
    for delta in DELTAS:
        smaller = paper_attack(data, delta, smaller, compiled=compiled)
        rows[delta] = {"norm2": smaller.check["norm2"], "stealthy": smaller.check["stealthy"],
                       "cpu": smaller.cpu_time, "nit": smaller.result.nit, "start": smaller.start}
    return rows


def slsqp(args: argparse.Namespace, sim: int) -> dict[float, dict]:
    """The authors' SLSQP on one data set, every delta, judged by the independent check."""
    out = subprocess.run([args.python, RUNNER, args.authors, args.data, str(T), str(sim), ",".join(map(str, DELTAS))],
                         capture_output=True, text=True, check=True, env={**os.environ, **ONE_THREAD})
    data, rows = load_dataset(dataset_path(args.data, T, sim)), {}
    for line in out.stdout.splitlines():
        r = json.loads(line)
        x = np.asarray(r["x"])
        dX, dU = x[:data.X.size].reshape(data.X.shape), x[data.X.size:].reshape(data.U.shape)  # their row-major split
        check = check_stealth(data.X, data.U, dX, dU, r["delta"])
        rows[r["delta"]] = {"norm2": check["norm2"], "stealthy": check["stealthy"], "cpu": r["cpu_time"]}
    return rows


def main() -> None:
    p = argparse.ArgumentParser()
    p.add_argument("--authors", required=True)
    p.add_argument("--python", required=True)
    p.add_argument("--data", required=True)
    p.add_argument("--sims", type=int, default=10)
    p.add_argument("--rows", default=None, help="also write every attack's row to this JSONL file")
    args = p.parse_args()
    start, t0 = load(), time.time()
    print(f"# bench_identification_compiled  {datetime.now(timezone.utc):%Y-%m-%d %H:%M} UTC  {platform.node()}  "
          f"{platform.processor() or platform.machine()}  cores={os.cpu_count()}  python {platform.python_version()}  "
          f"load at the start {start}")
    print(f"T = {T}, data sets 0-{args.sims - 1}, deltas {DELTAS}; callbacks: {paper_method(T)}; compiled: "
          f"{paper_method(T, True)}; SLSQP: the authors' code (100 iterations, seed 0); one thread each; CPU seconds "
          "per attack (time.process_time); stealthy: the independent numpy check, tol 1e-6\n", flush=True)
    rows: dict[tuple[str, int, float], dict] = {}
    with single_threaded():
        for sim in range(args.sims):
            path = dataset_path(args.data, T, sim)
            for name in PATHS:
                for delta, r in engine(path, name == "compiled").items():
                    rows[(name, sim, delta)] = r
            for delta, r in slsqp(args, sim).items():
                rows[("slsqp", sim, delta)] = r
            print(f"# data set {sim} done, load {load()}", flush=True)
    if args.rows:
        with open(args.rows, "w") as fh:
            for (name, sim, delta), r in rows.items():
                fh.write(json.dumps({"path": name, "sim": sim, "delta": delta, **r}) + "\n")
    print("\n| delta | stealthy callbacks / compiled / SLSQP | >= SLSQP callbacks / compiled | >= SLSQP or SLSQP not "
          "stealthy callbacks / compiled | compiled >= callbacks | median ||d[A B]||_2 "
          "callbacks / compiled / SLSQP | median CPU s callbacks / compiled / SLSQP | median IPOPT iterations "
          "callbacks / compiled | median SLSQP/engine CPU callbacks / compiled | median callbacks/compiled CPU |")
    print("|---|---|---|---|---|---|---|---|---|---|")
    ratio = {name: [] for name in PATHS}
    speed = []
    wins = {name: 0 for name in PATHS}
    fairs = {name: 0 for name in PATHS}
    for delta in DELTAS:
        cell = {name: [rows[(name, s, delta)] for s in range(args.sims)] for name in (*PATHS, "slsqp")}
        a = cell["slsqp"]
        r = {name: [y["cpu"] / x["cpu"] for x, y in zip(cell[name], a)] for name in PATHS}
        w = {name: sum(x["norm2"] >= y["norm2"] * (1 - 1e-6) for x, y in zip(cell[name], a)) for name in PATHS}
        fair = {name: sum(x["norm2"] >= y["norm2"] * (1 - 1e-6) or not y["stealthy"] for x, y in zip(cell[name], a))
                for name in PATHS}
        same = sum(x["norm2"] >= y["norm2"] * (1 - 1e-6) for x, y in zip(cell["compiled"], cell["callbacks"]))
        s = [x["cpu"] / y["cpu"] for x, y in zip(cell["callbacks"], cell["compiled"])]
        for name in PATHS:
            ratio[name] += r[name]
            wins[name] += w[name]
            fairs[name] += fair[name]
        speed += s
        med = lambda name, key: np.median([x[key] for x in cell[name]])  # noqa: E731
        print(f"| {delta} | {' / '.join(str(sum(x['stealthy'] for x in cell[n])) for n in (*PATHS, 'slsqp'))} | "
              f"{w['callbacks']} / {w['compiled']} | {fair['callbacks']} / {fair['compiled']} | {same} | "
              f"{' / '.join(f'{med(n, NORM):.3f}' for n in (*PATHS, 'slsqp'))} | "
              f"{' / '.join(f'{med(n, CPU):.3f}' for n in (*PATHS, 'slsqp'))} | "
              f"{' / '.join(f'{med(n, NIT):.0f}' for n in PATHS)} | "
              f"{np.median(r['callbacks']):.1f}x / {np.median(r['compiled']):.1f}x | {np.median(s):.2f}x |")
    n = args.sims * len(DELTAS)
    for name in PATHS:
        v = np.array(ratio[name])
        stealthy = sum(rows[(name, s, d)]["stealthy"] for s in range(args.sims) for d in DELTAS)
        print(f"\n{name}: median SLSQP/engine CPU per attack {np.median(v):.1f}x (min {v.min():.1f}x, max "
              f"{v.max():.1f}x) over {n} attacks; stealthy {stealthy}/{n}; >= SLSQP on {wins[name]}/{n}, >= SLSQP "
              f"or SLSQP not stealthy on {fairs[name]}/{n}; total CPU "
              f"{sum(rows[(name, s, d)]['cpu'] for s in range(args.sims) for d in DELTAS):.1f} s")
    print(f"\nSLSQP total CPU {sum(rows[('slsqp', s, d)]['cpu'] for s in range(args.sims) for d in DELTAS):.1f} s; "
          f"median callbacks/compiled CPU per attack {np.median(speed):.2f}x")
    print(f"\n# load at the end {load()}; {time.time() - t0:.0f} s wall")


if __name__ == "__main__":
    sys.exit(main())
