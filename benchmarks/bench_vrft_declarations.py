"""The registered VRFT max-min problem declared with its filters as recursions (the default) and as LinearOperators
(bilevel.problems.vrft.FILTERS): the first structured attack (declaration, preparation, attack, finalize) and the
CPU time per attack on re-loaded data sets, with their objectives. Ratios recursions / operators, same process.

Run: python benchmarks/bench_vrft_declarations.py [N ...]   (default 512 8192)
"""

from __future__ import annotations

import os
import platform
import sys
import time

import numpy as np

from bilevel.attacks.vrft_methods import METHODS
from bilevel.problems.vrft import attack_problem, load_instance
from bilevel.problems.vrft_instance import attack_instance
from bilevel.solvers.registry import solve


def run(N: int, filters: str, seeds: int) -> tuple[float, float, list[float], list[str]]:
    """First call's wall seconds, CPU ms per re-loaded attack, objectives and statuses of every seed."""
    t0 = time.perf_counter()
    problem = attack_problem(attack_instance("maxmin", "B", 0.1, 0.057, 0, N), filters)
    first = solve(problem, method=METHODS["alternating"])
    wall = time.perf_counter() - t0
    values, statuses = [first.upper_objective], [first.status.value]
    c0 = time.process_time()
    for seed in range(1, seeds):
        load_instance(problem, attack_instance("maxmin", "B", 0.1, 0.057, seed, N))
        res = solve(problem, method=METHODS["alternating"])
        values.append(res.upper_objective)
        statuses.append(res.status.value)
    return wall, 1e3 * (time.process_time() - c0) / max(seeds - 1, 1), values, statuses


def main(sizes: list[int]) -> None:
    print(f"# bench_vrft_declarations.py, {time.strftime('%Y-%m-%d %H:%M:%S %Z')}; {platform.platform()}; nproc "
          f"{os.cpu_count()}; python {platform.python_version()}; load average {os.getloadavg()[0]:.2f}")
    for N in sizes:
        seeds = 21 if N <= 1024 else 3
        got = {f: run(N, f, seeds) for f in ("recursions", "operators")}
        (wr, cr, vr, sr), (wo, co, vo, so) = got["recursions"], got["operators"]
        diff = float(np.max(np.abs(np.array(vr) - np.array(vo)) / np.abs(vr)))
        print(f"N = {N:6d}: first call recursions {wr:.2f} s, operators {wo:.2f} s (ratio {wr / wo:.2f}x); "
              f"per attack ({seeds - 1} re-loaded data sets) recursions {cr:.1f} ms, operators {co:.1f} ms CPU "
              f"(ratio {cr / co:.2f}x); objectives' max relative difference {diff:.1e}; statuses equal "
              f"{sum(a == b for a, b in zip(sr, so))}/{seeds}", flush=True)


if __name__ == "__main__":
    main([int(n) for n in sys.argv[1:]] or [512, 8192])
