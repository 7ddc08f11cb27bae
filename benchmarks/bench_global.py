"""Time method="global" against ipopt on the textbook problems in its scope, and find the largest random LP-LP
size it solves to a proven gap (1e-6 relative) within 60 s.

Part 1: every registered textbook problem the method accepts, global (median of 3 runs) next to ipopt (8 starts,
median of 3 runs; the baseline, run in the same process); value reached, time ratio, median and worst times.
Part 2: random LP-LP instances (bilevel/problems/random_linear.py; n_x = n_y / 2, m = n_y lower constraints plus
the box 0 <= y <= 10, so 2 n_y + m complementarity pairs), 3 seeds per size, growing until a size has a seed that
is not proven within the limit. Asserts nothing. Usage: python benchmarks/bench_global.py > benchmarks/results/...
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
import scipy

import bilevel as bl
from bilevel.experiments.compare import relative_gap
from bilevel.problems import registry
from bilevel.problems.random_linear import build_linear_bilevel, random_linear_data

REPEATS = 3
TIME_LIMIT = 60.0
SEEDS = 3
SIZES = (4, 8, 12, 16, 20, 24, 28, 32, 40)


def header() -> None:
    """Machine, date and load, so the numbers can be read in context."""
    uname = subprocess.run(["uname", "-a"], capture_output=True, text=True).stdout.strip()
    print(f"# bench_global.py — {datetime.now(timezone.utc):%Y-%m-%d %H:%M:%S} UTC")
    print(f"# uname -a: {uname}")
    print(f"# nproc: {os.cpu_count()}; load average at start: {', '.join(f'{v:.2f}' for v in os.getloadavg())}")
    print("# NOTE: the machine was shared with other engineers' test and benchmark jobs during this run; times are "
          "upper bounds of what an idle machine gives")
    print(f"# python: {platform.python_version()}, numpy {np.__version__}, scipy {scipy.__version__} (HiGHS), "
          f"bilevel {sys.modules['bilevel'].__file__}")


def timed(name: str, method: str, **options: object) -> tuple[float, bl.BilevelResult]:
    """Median wall time over REPEATS solves, and the last result."""
    times, res = [], None
    for _ in range(REPEATS):
        t0 = time.perf_counter()
        res = bl.solve(registry.get(name), method=method, **options)
        times.append(time.perf_counter() - t0)
    return statistics.median(times), res


def textbook_table() -> None:
    """One line per in-scope textbook problem, then median and worst times of both methods."""
    print("\n## Textbook problems in scope of method='global' (median of 3 runs each)")
    print(f"{'problem':<28} {'global [s]':>10} {'ipopt [s]':>10} {'g/i':>6} {'global F':>14} {'ipopt F':>14} "
          f"{'known F*':>14} {'proven':>6} {'algorithm':<12}")
    t_global, t_ipopt, outside = [], [], []
    for name in registry.names("textbook"):
        try:
            tg, rg = timed(name, "global")
        except bl.ModelError as exc:
            outside.append(f"{name}: {str(exc).split(';')[0]}")
            continue
        ti, ri = timed(name, "ipopt", starts=8, seed=0)
        known = registry.spec(name).optimum
        gb = rg.certificate.global_bound if rg.certificate else None
        t_global.append(tg)
        t_ipopt.append(ti)
        print(f"{name:<28} {tg:>10.3f} {ti:>10.3f} {tg / ti:>6.2f} {rg.upper_objective:>14.8g} "
              f"{ri.upper_objective:>14.8g} {known:>14.8g} {str(bool(gb and gb.proven)):>6} "
              f"{rg.stats['algorithm'].split(' ')[0]:<12}"
              f"{'' if relative_gap(ri.upper_objective, known) <= 1e-4 else '  <- ipopt misses F*'}")
    for label, ts in (("global", t_global), ("ipopt (8 starts)", t_ipopt)):
        print(f"{label}: median {statistics.median(ts):.3f} s, worst {max(ts):.3f} s over {len(ts)} problems")
    print(f"ratio of medians global / ipopt: {statistics.median(t_global) / statistics.median(t_ipopt):.2f}")
    print("outside the scope of 'global' (ModelError):")
    for line in outside:
        print(f"  {line}")


def random_table() -> None:
    """Grow the random LP-LP size until some seed is not proven within TIME_LIMIT."""
    print(f"\n## Random LP-LP instances, {SEEDS} seeds per size, time limit {TIME_LIMIT:.0f} s, gap 1e-6")
    print(f"{'n_x':>4} {'n_y':>4} {'m':>4} {'pairs':>6} {'proven':>7} {'median [s]':>11} {'worst [s]':>10} "
          f"{'max nodes':>10} {'algorithm':<12}")
    largest = None
    for n_y in SIZES:
        n_x, m = max(1, n_y // 2), n_y
        times, nodes, proven, algo = [], [], 0, ""
        for seed in range(SEEDS):
            data = random_linear_data(np.random.default_rng(seed), n_x, n_y, m)
            t0 = time.perf_counter()
            res = bl.solve(build_linear_bilevel(data), method="global", time_limit=TIME_LIMIT)
            times.append(time.perf_counter() - t0)
            nodes.append(res.stats.get("nodes", 0))
            algo = res.stats.get("algorithm", "").split(" ")[0]
            proven += res.status is bl.Status.SOLVED
        print(f"{n_x:>4} {n_y:>4} {m:>4} {2 * n_y + m:>6} {proven:>4}/{SEEDS} {statistics.median(times):>11.2f} "
              f"{max(times):>10.2f} {max(nodes):>10} {algo:<12}", flush=True)
        if proven < SEEDS:
            break
        largest = (n_x, n_y, m)
    if largest is None:
        print("no size was solved to a proven gap on every seed within the limit")
    else:
        n_x, n_y, m = largest
        print(f"largest size proven on all {SEEDS} seeds within {TIME_LIMIT:.0f} s: {n_y} lower variables x "
              f"{m + 2 * n_y} lower constraints ({m} general + {2 * n_y} box rows), {n_x} upper variables")


if __name__ == "__main__":
    header()
    textbook_table()
    random_table()
    print(f"# load average at end: {', '.join(f'{v:.2f}' for v in os.getloadavg())}")
