"""method="global" on every registered textbook problem: the proof (bounds, nodes) and its time, with SCIP taking
the nonconvex leaders (algorithm "auto"), next to ipopt (8 starts, the baseline, run in the same process).

One line per problem: known F*, the proven bounds in the declared sense, relative gap, nodes, the algorithm "auto"
picks, the median wall time of REPEATS solves, ipopt's median time and the ratio, and the time with
algorithm="scip" forced (SCIP on the convex problems too, against HiGHS / our branch-and-bound there). Then the
median time over the problems the method proves (the issue asks <= 5 s) and the problems it refuses, with the
class its ModelError names.
Part 2: random instances with a bilinear leader over an LP lower level (bilevel/problems/random_bilinear.py;
n_x = n_y / 2, m = n_y / 2 general rows plus the box 0 <= y <= 1), SEEDS seeds per size, TIME_LIMIT each, growing
until a size has a seed that is not proven. Asserts nothing.
Usage: python benchmarks/bench_global_scip.py > benchmarks/results/bench_global_scip.txt
"""

from __future__ import annotations

import os
import platform
import statistics
import subprocess
import sys
import time
from datetime import datetime, timezone

import numpy as np
import pyscipopt
import scipy

import bilevel as bl
from bilevel.problems import registry
from bench_global import REPEATS, timed  # the same timing of a registered problem (run from benchmarks/)
from bilevel.problems.random_bilinear import (
    build_bilinear_bilevel,
    random_bilinear_data,
)

SEEDS = 3
TIME_LIMIT = 60.0
SIZES = (4, 8, 12, 16, 20, 24, 32)


def header(script: str = "bench_global_scip.py") -> None:
    """Machine, date, load and versions, so the numbers can be read in context."""
    uname = subprocess.run(["uname", "-a"], capture_output=True, text=True).stdout.strip()
    print(f"# {script} — {datetime.now(timezone.utc):%Y-%m-%d %H:%M:%S} UTC")
    print(f"# uname -a: {uname}")
    print(f"# nproc: {os.cpu_count()}; load average at start: {', '.join(f'{v:.2f}' for v in os.getloadavg())}")
    print("# NOTE: the machine may be shared with other jobs; compare the ratio column, not absolute times")
    print(f"# python {platform.python_version()}, numpy {np.__version__}, scipy {scipy.__version__}, pyscipopt "
          f"{pyscipopt.__version__} (SCIP {pyscipopt.Model().version()}), bilevel {sys.modules['bilevel'].__file__}")


def random_table() -> None:
    """Grow the random bilinear size until some seed is not proven within TIME_LIMIT."""
    print(f"\n## Random bilinear leader over an LP lower level, {SEEDS} seeds per size, time limit {TIME_LIMIT:.0f} s")
    print(f"{'n_x':>4} {'n_y':>4} {'m':>4} {'pairs':>6} {'proven':>7} {'median [s]':>11} {'worst [s]':>10} "
          f"{'max nodes':>10} {'worst gap':>10}")
    for n_y in SIZES:
        n_x = m = max(1, n_y // 2)
        times, nodes, gaps, proven = [], [], [], 0
        for seed in range(SEEDS):
            data = random_bilinear_data(np.random.default_rng(seed), n_x, n_y, m)
            t0 = time.perf_counter()
            res = bl.solve(build_bilinear_bilevel(data), method="global", time_limit=TIME_LIMIT)
            times.append(time.perf_counter() - t0)
            nodes.append(res.stats.get("nodes", 0))
            gaps.append(res.stats.get("gap", np.inf))
            proven += res.status is bl.Status.SOLVED
        print(f"{n_x:>4} {n_y:>4} {m:>4} {m + 2 * n_y:>6} {proven:>4}/{SEEDS} {statistics.median(times):>11.2f} "
              f"{max(times):>10.2f} {max(nodes):>10} {max(gaps):>10.1e}", flush=True)
        if proven < SEEDS:
            break


def main() -> None:
    header()
    print(f"\n## Textbook problems, method='global' (median of {REPEATS} runs) vs ipopt (8 starts)")
    print(f"{'problem':<28} {'F*':>12} {'lower bound':>14} {'upper bound':>14} {'gap':>8} {'nodes':>6} "
          f"{'status':<8} {'algorithm':<16} {'global [s]':>10} {'ipopt [s]':>10} {'g/i':>6} {'scip [s]':>9} {'scip F':>12}")
    times, ratios, refused, forced = [], [], [], []
    for name in registry.names("textbook"):
        known = registry.spec(name).optimum
        try:
            tg, res = timed(name, "global")
        except bl.ModelError as exc:
            refused.append(f"{name}: {exc}")
            continue
        ti, _ = timed(name, "ipopt", starts=8, seed=0)
        ts, rs = timed(name, "global", algorithm="scip")
        scip_proven = rs.status is bl.Status.SOLVED and rs.certificate.global_bound.proven
        forced.append((ts, tg, scip_proven))
        gb = res.certificate.global_bound if res.certificate else None
        low, high = (gb.lower_bound, gb.upper_bound) if gb else (res.stats["lower_bound"], res.stats["upper_bound"])
        proven = bool(gb and gb.proven) and res.status is bl.Status.SOLVED
        if proven:
            times.append(tg)
            ratios.append(tg / ti)
        status = "proven" if proven else res.status.value
        print(f"{name:<28} {known:>12.8g} {low:>14.10g} {high:>14.10g} {res.stats['gap']:>8.1e} "
              f"{res.stats['nodes']:>6} {status:<8} {res.stats['algorithm'].split(' ')[0]:<16} {tg:>10.3f} "
              f"{ti:>10.3f} {tg / ti:>6.2f} {ts:>9.3f} {rs.upper_objective:>12.8g}"
              f"{'' if scip_proven else ' (scip: ' + rs.status.value + ')'}", flush=True)
    print(f"\nproven: {len(times)} problems; median time {statistics.median(times):.3f} s, worst {max(times):.3f} s; "
          f"median ratio global / ipopt {statistics.median(ratios):.2f}")
    print(f"algorithm='scip' forced: proven on {sum(p for *_, p in forced)}/{len(forced)}; median time "
          f"{statistics.median(t for t, *_ in forced):.3f} s; median ratio scip / auto "
          f"{statistics.median(t / a for t, a, _ in forced):.2f}")
    print("refused by method 'global' (ModelError):")
    for line in refused:
        print(f"  {line}")
    random_table()
    print(f"# load average at end: {', '.join(f'{v:.2f}' for v in os.getloadavg())}")


if __name__ == "__main__":
    main()
