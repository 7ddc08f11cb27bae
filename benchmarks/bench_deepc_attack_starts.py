"""The DeePC attack's delta_ub (issue 46) with 1 start (the reproduction's) against 4 starts, on the reproduction's data
sets (T = 100, level 2 J0): the budget search of attack_bound with each, its CPU seconds (time.process_time), the load.
Usage: python benchmarks/bench_deepc_attack_starts.py [first [last]] (data-set indices, default 3 5)"""

from __future__ import annotations

import os
import platform
import sys
import time

from bilevel.experiments.certify import FAMILIES, certify_tasks
from bilevel.robust import as_target
from bilevel.robust.chain import attack_bound


def main(first: int, last: int) -> None:
    print(f"# bench_deepc_attack_starts.py {first} {last}, {time.strftime('%Y-%m-%d %H:%M UTC', time.gmtime())}, "
          f"{platform.machine()}, {os.cpu_count()} cores shared with other jobs, load {os.getloadavg()[0]:.1f}",
          flush=True)
    family = FAMILIES["deepc"]
    for i, task in enumerate(certify_tasks(32, False, 0, 10_000, ("deepc",))[first:last + 1], first):
        found = {}
        for starts in (1, 4):
            target = as_target(family.build(task["size"], task["seed"]), starts=starts)
            c0 = time.process_time()
            delta_ub, _, _ = attack_bound(target, task["attack_seed"], family.rel_tol)
            found[starts] = (delta_ub, time.process_time() - c0)
        print(f"data set {i} (seed {task['seed']}): delta_ub 1 start {found[1][0]:.5g} ({found[1][1]:.1f} CPU s), "
              f"4 starts {found[4][0]:.5g} ({found[4][1]:.1f} CPU s), ratio {found[4][0] / found[1][0]:.3f}; "
              f"load {os.getloadavg()[0]:.1f}", flush=True)


if __name__ == "__main__":
    main(*(int(a) for a in sys.argv[1:3])) if len(sys.argv) > 2 else main(3, 5)
