"""VRFT max-min attack: our attack vs the paper-style baseline on the same instances, and scaling in N.

Prints, for scenario B at (eps_u, eps_y) = (0.1, 0.057), N = 512: median time per attack of each method,
the speed ratio (baseline / ours, same process), the fraction of instances where our attacker objective
is >= the baseline's, and instability counts; the budget path of the maxmin-paper-path sweep (the eps_y grid with
warm starts, time per cell); then our attack at N = 65,536 with its peak traced memory.
Run: python benchmarks/bench_vrft_attack.py [instances]
"""

from __future__ import annotations

import os
import platform
import sys
import time
import tracemalloc
from datetime import datetime, timezone

import numpy as np
from threadpoolctl import threadpool_limits

sys.path.insert(0, os.path.dirname(__file__))
from vrft_baseline import paper_baseline  # noqa: E402

from bilevel.problems.vrft_instance import attack_instance  # noqa: E402
from bilevel.attacks.vrft_methods import (attack_alternating, attack_budget_path, attack_value,  # noqa: E402
                                          attack_white_noise, unstable)
from bilevel.experiments.vrft import EPS_Y  # noqa: E402


def main(instances: int = 20) -> None:
    print(f"# bench_vrft_attack  {datetime.now(timezone.utc):%Y-%m-%d %H:%M} UTC  {platform.node()}  "
          f"{platform.processor() or platform.machine()}  cores={os.cpu_count()}  python {platform.python_version()}")
    rows = []
    with threadpool_limits(1):
        for seed in range(instances):
            atk = attack_instance("maxmin", "B", 0.1, 0.057, seed=seed, N=512)
            ours = attack_alternating(atk, seed=seed)
            base = paper_baseline(atk, seed=seed)
            wn = attack_white_noise(atk, seed=seed)
            rows.append((ours.wall_time, base.wall_time, attack_value(ours), attack_value(base), attack_value(wn),
                         unstable(ours), unstable(base)))
            print(f"seed {seed:3d}: ours {1000 * ours.wall_time:7.1f} ms J = {attack_value(ours):.5f} "
                  f"(rho {ours.stats['spectral_radius']:.4f}) | baseline {1000 * base.wall_time:8.1f} ms "
                  f"J = {attack_value(base):.5f} "
                  f"(rho {base.stats['spectral_radius']:.4f}) | white noise J = {attack_value(wn):.5f}", flush=True)
        r = np.array(rows, dtype=float)
        t_ours, t_base = np.median(r[:, 0]), np.median(r[:, 1])
        stronger = np.mean(r[:, 2] >= r[:, 3] * (1 - 1e-9))
        print(f"\nN = 512, {instances} instances, scenario B, eps = (0.1, 0.057), one core:")
        print(f"  median time per attack: ours {1000 * t_ours:.1f} ms, paper-style baseline {1000 * t_base:.1f} ms, "
              f"ratio {t_base / t_ours:.0f}x")
        print(f"  ours >= baseline objective on {100 * stronger:.0f}% of instances; median J ours "
              f"{np.median(r[:, 2]):.4f}, baseline {np.median(r[:, 3]):.4f}, white noise {np.median(r[:, 4]):.4f}")
        print(f"  unstable: ours {int(r[:, 5].sum())}/{instances}, baseline {int(r[:, 6].sum())}/{instances}")
        path_times, path_stronger = [], []
        for seed in range(instances):
            atk = attack_instance("maxmin", "B", 0.1, EPS_Y[0], seed=seed, N=512)
            t = time.perf_counter()
            path = attack_budget_path(atk, EPS_Y, seed=seed)
            path_times.append((time.perf_counter() - t) / len(EPS_Y))
            path_stronger.append(attack_value(path[-1]) >= r[seed, 3] * (1 - 1e-9))
        print(f"  budget path over eps_y = {EPS_Y} (the maxmin-paper-path sweep): median {1000 * np.median(path_times):.1f}"
              f" ms per cell; at 0.057 >= baseline on {100 * np.mean(path_stronger):.0f}% of instances")
        for n in (4096, 65_536):
            atk = attack_instance("maxmin", "B", 0.1, 0.057, seed=0, N=n)
            tracemalloc.start()
            t = time.perf_counter()
            res = attack_alternating(atk)
            dt = time.perf_counter() - t
            peak = tracemalloc.get_traced_memory()[1]
            tracemalloc.stop()
            print(f"N = {n}: {dt:.2f} s, {res.nit} iterations, peak traced memory {peak / 2**20:.1f} MiB "
                  f"({peak / (8 * n):.0f} doubles per sample; a dense N x N matrix would be {8 * n * n / 2**30:.1f} GiB)")


if __name__ == "__main__":
    main(int(sys.argv[1]) if len(sys.argv) > 1 else 20)
