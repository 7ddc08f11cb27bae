"""Dask overhead: the Willems reproduction on 2 local worker processes vs a 2-worker Dask LocalCluster.

Runs `run_reproduction(sims=--sims, quick=not --paper, seed=0)` --rounds times on each executor (default: the
CI-sized plan, 3 budgets, N in {15, 50}, short DE, 75 attacks at 4 sims; `--paper`: the paper's plan, 10 budgets,
300-generation DE, 8 starts), alternating local/Dask so that load from other jobs hits
both alike, each run in a fresh output directory. Prints wall time per run (whole reproduction, Dask's
cluster start-up included; and the attacks alone, from timings.json), the median of each, the overhead of
Dask in % (baseline: the local pool, same process) and whether every table is identical. Asserts nothing.
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import sys
import tempfile
import time

from bilevel.experiments.willems import run_reproduction

sys.path.insert(0, os.path.join(os.path.dirname(__file__), ".."))
from tests.experiments.tables import tables  # noqa: E402

WORKERS = 2
EXECUTORS = {"local pool": None, "Dask LocalCluster": "local"}


def one_run(dask: str | None, out_dir: str, sims: int, quick: bool) -> tuple[float, float]:
    """(whole reproduction s, attacks only s) of one run into out_dir."""
    t0 = time.perf_counter()
    run_reproduction(sims=sims, out_dir=out_dir, quick=quick, seed=0, progress=None, workers=WORKERS, dask=dask)
    wall = time.perf_counter() - t0
    with open(os.path.join(out_dir, "timings.json"), encoding="utf-8") as fh:
        return wall, sum(seconds for _, seconds in json.load(fh).values())


def main() -> None:
    """Alternate the executors --rounds times; print each run, the medians and Dask's overhead."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--sims", type=int, default=4, help="simulations per cell (default 4)")
    parser.add_argument("--paper", action="store_true", help="the paper's plan instead of the CI-sized one")
    parser.add_argument("--rounds", type=int, default=2, help="runs per executor (default 2)")
    args = parser.parse_args()
    if args.sims < 1 or args.rounds < 1:
        parser.error("--sims and --rounds must be >= 1")
    print(f"plan: {'paper' if args.paper else 'CI-sized (quick)'}, sims={args.sims}, rounds={args.rounds}", flush=True)
    times: dict[str, list[tuple[float, float]]] = {name: [] for name in EXECUTORS}
    with tempfile.TemporaryDirectory() as tmp:
        for r in range(args.rounds):
            for name, dask in EXECUTORS.items():
                wall, attacks = one_run(dask, os.path.join(tmp, f"{r}-{dask}"), args.sims, not args.paper)
                times[name].append((wall, attacks))
                print(f"round {r + 1} {name:>18}: reproduction {wall:6.1f} s, attacks {attacks:6.1f} s", flush=True)
        same = all(tables(os.path.join(tmp, f"{r}-{d}")) == tables(os.path.join(tmp, f"0-{None}"))
                   for r in range(args.rounds) for d in EXECUTORS.values())
    med = {name: (statistics.median(w for w, _ in v), statistics.median(a for _, a in v)) for name, v in times.items()}
    base, dask = med["local pool"], med["Dask LocalCluster"]
    print(f"median over {args.rounds} runs: local pool {base[0]:.1f} s (attacks {base[1]:.1f} s), Dask LocalCluster "
          f"{dask[0]:.1f} s (attacks {dask[1]:.1f} s)")
    print(f"Dask overhead: {100 * (dask[0] / base[0] - 1):+.1f}% on the whole reproduction (cluster start-up "
          f"included), {100 * (dask[1] / base[1] - 1):+.1f}% on the attacks alone")
    print(f"every table identical across executors and rounds (wall-time columns aside): {'yes' if same else 'NO'}")


if __name__ == "__main__":
    main()
