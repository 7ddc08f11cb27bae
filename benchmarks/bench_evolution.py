"""Method `differential-evolution` against its baselines in the same run.

1. Willems (appendix B, N = 15, input poisoning, lqr design, eigenvalue criterion, delta_u = 0.6): the Willems DE
   baseline (bilevel.attacks.willems.de_attack: the same scipy call, batched over the population because the
   learner ignores the poisoning, no stop at instability) against `bilevel.solve(problem, method=
   "differential-evolution", popsize=5, max_iter=300)` on the registered problem, without and with the descent
   (polish). Prints time ratios (baseline: de_attack) and criteria.
2. The textbook problems whose upper variables are all boxed: `differential-evolution` (defaults) against
   `hypergradient` with 8 starts (baseline), time ratio, objective against the known optimum.
Run: python benchmarks/bench_evolution.py [willems seeds, default 5]
"""

from __future__ import annotations

import os
import platform
import sys
from datetime import datetime, timezone

import numpy as np

import bilevel as bl
from bilevel.attacks.willems import de_attack
from bilevel.errors import ModelError
from bilevel.problems import registry
from bilevel.problems.willems import build_attack


def willems(seeds: int) -> None:
    """Generic DE (without and with polish) against the Willems DE baseline, same popsize and generations."""
    print(f"willems-eigen N = 15, delta_u = 0.6, {seeds} seeds, popsize 5, 300 generations:")
    ratios: dict[str, list[float]] = {"generic": [], "generic+polish": []}
    for seed in range(seeds):
        attack = build_attack(objective="eigen", horizon=15, seed=seed, delta_u=0.6)
        base = de_attack(attack, seed=seed, stop_when_unstable=False)
        line = f"  seed {seed}: de_attack {base.wall_time:6.2f} s crit {base.upper_objective:.6f}"
        for label, polish in (("generic", False), ("generic+polish", True)):
            res = bl.solve(attack.problem, method="differential-evolution", seed=seed, popsize=5, max_iter=300,
                           polish=polish)
            ratios[label].append(res.wall_time / base.wall_time)
            line += (f" | {label} {res.wall_time:6.2f} s ({res.wall_time / base.wall_time:5.1f}x) crit "
                     f"{res.upper_objective:.6f} {res.status.value}")
        print(line, flush=True)
    for label, r in ratios.items():
        print(f"  {label}: median time {np.median(r):.1f}x de_attack (max {np.max(r):.1f}x)")


def textbook() -> None:
    """Every boxed textbook problem: evolution vs hypergradient (8 starts)."""
    print("\nBoxed textbook problems: differential-evolution (defaults) vs hypergradient (8 starts, baseline)")
    reached = total = 0
    for name in registry.names("textbook"):
        problem, optimum = registry.get(name), registry.spec(name).optimum
        try:
            res = bl.solve(problem, method="differential-evolution")
        except ModelError:
            continue
        base = bl.solve(registry.get(name), method="hypergradient", starts=8)
        total += 1
        gap = abs(res.upper_objective - optimum) / max(1.0, abs(optimum))
        reached += gap <= 1e-5
        print(f"  {name:28s} DE {res.wall_time:6.2f} s F = {res.upper_objective:<14.8g} gap {gap:.1e} "
              f"{res.status.value:12s} | hypergradient {base.wall_time:6.2f} s F = {base.upper_objective:<14.8g} "
              f"{base.status.value} | time ratio {res.wall_time / base.wall_time:5.1f}x", flush=True)
    print(f"  F* reached (1e-5 relative) by differential-evolution on {reached} of {total} boxed problems")


if __name__ == "__main__":
    print(f"# bench_evolution  {datetime.now(timezone.utc):%Y-%m-%d %H:%M} UTC  {platform.node()}  "
          f"{platform.processor() or platform.machine()}  cores={os.cpu_count()}  python {platform.python_version()}")
    willems(int(sys.argv[1]) if len(sys.argv) > 1 else 5)
    textbook()
