"""The structured VRFT attacks against the generic route on the registered problems: alternating (exact input step),
joint, and the generic hypergradient (default options, one start) on vrft-maxmin, vrft-targeted and vrft-destabilize;
N = 512, scenario B, eps = (0.1, 0.057), SEEDS data sets. Per method: the declared objective's median ratio to the
structured attack's, the true closed loop's unstable count, and the median wall time per attack (after one warm-up
attack each, same process). On vrft-destabilize also joint on the exact spectral radius of the modelled loop (its
log-sum-exp with beta = 1e6: the declared objective) in place of the log-sum-exp with beta = 50 it ascends by default.
Which attack each problem's registry entry runs: bilevel.attacks.registry.

Run: python benchmarks/bench_vrft_methods.py [SEEDS]   (default 10)
"""

from __future__ import annotations

import dataclasses
import os
import platform
import statistics
import sys
import time

from bilevel.attacks.vrft_methods import attack_alternating, attack_joint
from bilevel.problems.vrft import problem_for
from bilevel.problems.vrft_instance import attack_instance
from bilevel.solvers.registry import solve

RUNS = {"alternating": lambda atk: attack_alternating(atk), "joint": lambda atk: attack_joint(atk),
        "joint-exact": lambda atk: attack_joint(dataclasses.replace(atk, surrogate_beta=1e6)),
        "hypergradient": lambda atk: solve(problem_for(atk), method="hypergradient", starts=1)}


def main(seeds: int = 10) -> None:
    print(f"# bench_vrft_methods.py, {time.strftime('%Y-%m-%d %H:%M:%S %Z')}; {platform.platform()}; nproc "
          f"{os.cpu_count()}; python {platform.python_version()}; load average {os.getloadavg()[0]:.2f}")
    for objective in ("maxmin", "targeted", "destabilize"):
        structured = "joint" if objective == "destabilize" else "alternating"
        methods = [m for m in RUNS if m != ("alternating" if objective == "destabilize" else "joint-exact")]
        for m in methods:
            RUNS[m](attack_instance(objective, "B", 0.1, 0.057, 0, 512))  # warm-up: declarations, compilations
        rows = {m: [] for m in methods}
        for seed in range(seeds):
            atk = attack_instance(objective, "B", 0.1, 0.057, seed, 512)
            for m in methods:
                t0 = time.perf_counter()
                res = RUNS[m](atk)
                rows[m].append((res.upper_objective, time.perf_counter() - t0,
                                atk.setting.loop.spectral_radius(res.y["theta"]) >= 1.0))
        ref = [r[0] for r in rows[structured]]
        sense = -1.0 if objective == "targeted" else 1.0  # targeted's declared objective is a distance (minimized)
        for m in methods:
            ratio = statistics.median((r[0] / b) ** sense for r, b in zip(rows[m], ref))
            better = sum(sense * (r[0] - b) >= -1e-9 * abs(b) for r, b in zip(rows[m], ref))
            print(f"vrft-{objective:11s} {m:13s}: objective median {ratio:.4f}x {structured}'s (at least as good on "
                  f"{better}/{seeds}), unstable {sum(r[2] for r in rows[m])}/{seeds}, median "
                  f"{1e3 * statistics.median(r[1] for r in rows[m]):.1f} ms per attack", flush=True)


if __name__ == "__main__":
    main(*map(int, sys.argv[1:2]))
