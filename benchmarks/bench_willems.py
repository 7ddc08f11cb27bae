"""Time the attacks on the De Persis–Tesi learner (paper setting) at N = 15 and N = 50, ours against DE.

Same instances for both methods (the reproduction's first sims, delta_u = 0.6, eigenvalue criterion,
input poisoning of the appendix SDP). Prints median wall time per attack, the ratio DE / ours (baseline:
our attack, run in the same process), mean criterion and unstable counts; then the generic KKT route
(bilevel.solve, IPOPT and the relaxation sequence) at N = 15; then the paper-setting sweep on a measured
fraction of its simulations, extrapolated to 256 (labelled as such). Asserts nothing.
"""

from __future__ import annotations

import os
import statistics
import tempfile
import time
from collections.abc import Callable

import numpy as np

from bilevel.attacks.outcome import unstable
from bilevel.attacks.willems import de_attack, hypergradient_attack, kkt_attack
from bilevel.result import BilevelResult
from bilevel.experiments.executor import LocalExecutor
from bilevel.experiments.sweep import run_sweep
from bilevel.experiments.willems import attack_task, make_plan, paper_tasks, sim_seeds
from bilevel.problems.willems import build_attack

INSTANCES = 5
DELTA_U = 0.6
SWEEP_SIMS = 4
PAPER_SIMS = 256
WORKERS = 2


def time_attacks(horizon: int, stop: bool) -> dict[str, list[BilevelResult]]:
    """Our attack and DE (sweep settings) on the same INSTANCES instances of length `horizon`."""
    methods: dict[str, Callable[..., BilevelResult]] = {"ours": hypergradient_attack, "de": de_attack}
    out: dict[str, list[BilevelResult]] = {name: [] for name in methods}
    for data_seed, attack_seed in sim_seeds(0, INSTANCES):
        attack = build_attack(horizon=horizon, seed=data_seed, delta_u=DELTA_U)
        for name, fn in methods.items():
            out[name].append(fn(attack, seed=attack_seed, stop_when_unstable=stop))
    return out


def attack_table() -> None:
    """One line per (N, stop rule): median times, ratio, mean criterion, unstable counts."""
    print(f"Per attack, {INSTANCES} instances, delta_u = {DELTA_U}, eigenvalue criterion, design lqr, U poisoned")
    print(f"{'N':>3} {'stop at instability':>19} {'ours [s]':>9} {'DE [s]':>8} {'DE/ours':>8} {'ours crit':>10}"
          f" {'DE crit':>9} {'ours unst':>9} {'DE unst':>8}")
    for horizon in (15, 50):
        for stop in (False, True):
            res = time_attacks(horizon, stop)
            t = {k: statistics.median(r.wall_time for r in v) for k, v in res.items()}
            crit = {k: float(np.mean([r.upper_objective for r in v])) for k, v in res.items()}
            unst = {k: sum(unstable(r) for r in v) for k, v in res.items()}
            print(f"{horizon:>3} {str(stop):>19} {t['ours']:>9.3f} {t['de']:>8.3f} {t['de'] / t['ours']:>8.1f}"
                  f" {crit['ours']:>10.4f} {crit['de']:>9.4f} {unst['ours']:>9} {unst['de']:>8}")


def kkt_table() -> None:
    """The generic route at N = 15 on the first instance (one start), next to our attack to convergence."""
    data_seed, attack_seed = sim_seeds(0, 1)[0]
    attack = build_attack(horizon=15, seed=data_seed, delta_u=DELTA_U)
    ours = hypergradient_attack(attack, seed=attack_seed, stop_when_unstable=False)
    print(f"\nGeneric KKT route at N = 15 (one start) vs ours to convergence ({ours.wall_time:.3f} s, "
          f"criterion {ours.upper_objective:.6f})")
    for method in ("ipopt", "relaxation"):
        res = kkt_attack(attack, method=method, starts=1, seed=attack_seed)
        print(f"  {method:>10}: {res.wall_time:7.2f} s ({res.wall_time / ours.wall_time:6.1f} x ours), status "
              f"{res.stats['details']['status']}, certificate "
              f"{'passed' if res.stats['details']['certificate_passed'] else 'failed'},"
              f" criterion {res.upper_objective:.6f}")


def sweep_fraction() -> None:
    """The paper-setting sweep (every N, delta_u and method) on SWEEP_SIMS sims with 2 workers, extrapolated."""
    plan = make_plan(PAPER_SIMS, quick=False)
    fraction = make_plan(SWEEP_SIMS, quick=False)
    tasks = paper_tasks(fraction, 0)
    with tempfile.TemporaryDirectory() as tmp:
        t0 = time.perf_counter()
        with LocalExecutor(WORKERS) as executor:
            run_sweep(attack_task, tasks, os.path.join(tmp, "paper.jsonl"), executor, None, "bench")
        wall = time.perf_counter() - t0
    total = len(paper_tasks(plan, 0))
    print(f"\nPaper-setting sweep: measured {len(tasks)} of its {total} attacks ({SWEEP_SIMS} of {PAPER_SIMS} sims, "
          f"all N, delta_u, methods) in {wall:.1f} s on {WORKERS} workers")
    print(f"  EXTRAPOLATED (x {total / len(tasks):.0f}, not measured): full paper-setting sweep "
          f"~ {wall * total / len(tasks) / 60:.0f} min")


def main() -> None:
    """Run all three parts."""
    build_attack(horizon=15)  # warm-up (imports, CasADi)
    attack_table()
    kkt_table()
    sweep_fraction()


if __name__ == "__main__":
    main()
