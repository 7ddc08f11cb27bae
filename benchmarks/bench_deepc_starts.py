"""Does the default method's DeePC attack on one's own plant reach what 64 starts reach, and where it does not, does
its message say so? Ten instances (the docs/own_plant.md heater, recorded with seeds 0..9, l2 budget 5 %): the
default solve, then the same method with 64 starts; prints per instance both objectives, their ratio and whether the
default's message reports its starts' spread (issue 50: within 5 % of the 64-start run, or the message says so).

    python benchmarks/bench_deepc_starts.py [instances] [--default-only]

--default-only runs the default solves alone (their statuses and objectives; no 64-start comparison).
"""

from __future__ import annotations

import platform
import sys
import time

import control
import numpy as np

import bilevel as bl
from bilevel.ddc import simulate
from bilevel.problems.budget import Budget
from bilevel.problems.deepc import declare
from bilevel.problems.deepc_instance import DeePCAttack


def instance(seed: int) -> DeePCAttack:
    """The docs/own_plant.md heater recorded for 120 samples with white noise (seed), l2 budget 5 %, horizon 8."""
    heater = control.tf([0.2, 0.1], [1.0, -1.1, 0.3], 1.0)
    rng = np.random.default_rng(seed)
    u = rng.standard_normal(120)
    y = simulate(heater, u) + 0.01 * rng.standard_normal(120)
    return DeePCAttack(heater, u, y, np.zeros(8), np.zeros(8), Budget(0.05), horizon=8)


def main(count: int = 10, default_only: bool = False) -> None:
    print(f"# {time.strftime('%Y-%m-%d %H:%M UTC', time.gmtime())}, {platform.machine()}, {platform.processor()}, "
          f"python {platform.python_version()}, bilevel {bl.__version__ if hasattr(bl, '__version__') else ''}")
    print("seed | default method | default status | default F | 64-start F | default / 64 | spread reported | "
          "default s | 64-start s")
    ok = 0
    for seed in range(count):
        atk = instance(seed)
        t0 = time.perf_counter()
        default = bl.solve(declare(atk), seed=0)
        t1 = time.perf_counter()
        if default_only:
            print(f"{seed} | {default.method} | {default.status.value} | {default.upper_objective:.6g} | - | - | "
                  f"{'starts_spread' in default.stats} | {t1 - t0:.1f} | -", flush=True)
            continue
        many = bl.solve(declare(atk), method=default.method, starts=64, seed=0)
        t2 = time.perf_counter()
        ratio = default.upper_objective / many.upper_objective
        reported = "starts_spread" in default.stats
        ok += ratio >= 0.95 or reported
        print(f"{seed} | {default.method} | {default.status.value} | {default.upper_objective:.6g} | "
              f"{many.upper_objective:.6g} | {ratio:.3f} | {reported} | {t1 - t0:.1f} | {t2 - t1:.1f}", flush=True)
    if not default_only:
        print(f"within 5 % of 64 starts or spread reported: {ok} of {count}")


if __name__ == "__main__":
    args = [a for a in sys.argv[1:] if a != "--default-only"]
    main(int(args[0]) if args else 10, "--default-only" in sys.argv[1:])
