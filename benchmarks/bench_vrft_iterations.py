"""Does the structured VRFT attack stop too early? attack_alternating at its default max_iter = 60 against max_iter = 500
on the compare/bench_generic instances (scenario B, eps = (0.1, 0.057), N = 512, seeds 0..S-1), max-min and targeted:
how often the default ends at its iteration limit (status not `solved`), and the objective ratio 500 / 60 (max-min is
maximized, targeted minimized). Run: python benchmarks/bench_vrft_iterations.py [seeds]
"""

from __future__ import annotations

import os
import platform
import sys
import time
from datetime import datetime, timezone

import numpy as np

from bilevel.problems.vrft_instance import attack_instance
from bilevel.attacks.vrft_methods import attack_alternating


def main(seeds: int = 40) -> None:
    print(f"# bench_vrft_iterations  {datetime.now(timezone.utc):%Y-%m-%d %H:%M} UTC  {platform.node()}  "
          f"cores={os.cpu_count()}  python {platform.python_version()}")
    for objective in ("maxmin", "targeted"):
        limited, ratios, times = 0, [], {60: 0.0, 500: 0.0}
        for seed in range(seeds):
            atk = attack_instance(objective, "B", 0.1, 0.057, seed=seed, N=512)
            res = {}
            for max_iter in (60, 500):
                t = time.perf_counter()
                res[max_iter] = attack_alternating(atk, max_iter=max_iter)
                times[max_iter] += time.perf_counter() - t
            limited += res[60].status.value != "solved"
            ratios.append(res[500].upper_objective / res[60].upper_objective)
        r = np.array(ratios)
        print(f"{objective}: default (60) not solved on {limited}/{seeds}; objective 500/60 median {np.median(r):.4f}, "
              f"min {r.min():.4f}, max {r.max():.4f}; total time {times[60]:.2f} s vs {times[500]:.2f} s", flush=True)


if __name__ == "__main__":
    main(int(sys.argv[1]) if len(sys.argv) > 1 else 40)
