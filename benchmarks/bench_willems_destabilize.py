"""willems-destabilize against the issue's baseline: a 16-start projected ascent directly on the true rho(A + B K).

Setting of issue 12: batch reactor, N = 15, the appendix SDP (design lqr), input poisoning in an linf box of
radius delta_u in {0.2, 0.3, 0.5}, DATASETS data sets (the Willems reproduction's data seeds), for each learner
selection (min-norm, clarabel, scs): our attack (bilevel.attacks.willems.destabilize_attack, 16 starts) and the
baseline, both white box against that selection, run in this process on the same instances and starts. Baseline:
the engine's projected ascent (bilevel.solvers.ascent) on log rho of the TRUE plant's closed loop, through the same
learner (SDPHypergradient.gain_gradient), from the clean data and 15 uniform points of the box (the same starts as
ours), max_iter as ours per path; its reported point is the evaluated one with the largest true rho (as ours).
Our attack's direct path is this ascent on the identified plant (= the true one to ~1e-12 on noise-free data), so
ours >= baseline is by construction; the columns "smooth" show what the Gelfand path alone reaches.
Then the transfer: our poisoning computed against one selection, handed to each learner. Asserts nothing.
Usage: bench_willems_destabilize.py [DATASETS] [SELECTIONS comma-separated].
"""

from __future__ import annotations

import os
import platform
import sys
import time

import numpy as np

from bilevel.attacks.willems import SDPHypergradient, destabilize_attack, log_radius_gradient
from bilevel.ddc.plants import batch_reactor
from bilevel.experiments.willems import sim_seeds
from bilevel.problems.willems import build_attack
from bilevel.sampling import sample_in_bounds
from bilevel.solvers.ascent import budget_direction, projected_ascent
from bilevel.solvers.projections import Box

DATASETS = int(sys.argv[1]) if len(sys.argv) > 1 else 48
DELTAS = (0.2, 0.3, 0.5)
SELECTIONS = tuple(sys.argv[2].split(",")) if len(sys.argv) > 2 else ("min-norm", "clarabel", "scs")
STARTS = 16
MAX_ITER = 100
PLANT = batch_reactor()


def true_radius(gain: np.ndarray) -> float:
    return float(np.max(np.abs(np.linalg.eigvals(PLANT.A + PLANT.B @ gain))))


def baseline(attack, seed: int) -> float:
    """Largest true rho over every point a 16-start projected ascent on log rho(A + B K) evaluates."""
    oracle = SDPHypergradient(attack)
    bound = attack.budget()
    rng = np.random.default_rng(seed)
    best = [0.0]

    def value(x):
        ev = oracle.evaluate(x)
        rho = true_radius(ev.gain)
        best[0] = max(best[0], rho)
        return float(np.log(rho)), ev

    def direction(ev):
        g = oracle.gain_gradient(ev, log_radius_gradient(PLANT.A + PLANT.B @ ev.gain, PLANT.B)[1])
        return g, bound * budget_direction(bound * g, 1.0, np.inf)

    for k in range(STARTS):
        x0 = np.zeros(bound.size) if k == 0 else sample_in_bounds(-bound, bound, rng)
        projected_ascent(value, direction, Box(-bound, bound), x0, bound, MAX_ITER, 1e-9, [])
    return best[0]


def transferred(attack, x: np.ndarray, selection: str) -> float:
    """True rho when the learner with `selection` learns from the poisoning x (computed against another one)."""
    target = build_attack(objective="destabilize", horizon=attack.setting.horizon, seed=attack.setting.seed,
                          delta_u=attack.setting.delta_u, selection=selection)
    return true_radius(SDPHypergradient(target).evaluate(x).gain)


def main() -> None:
    seeds = sim_seeds(0, DATASETS)
    print(f"# {' '.join(sys.argv)} -- {time.strftime('%Y-%m-%d %H:%M:%S UTC', time.gmtime())}, "
          f"{platform.node()} {platform.machine()}, nproc {os.cpu_count()}, load average "
          f"{' '.join(f'{v:.2f}' for v in os.getloadavg())} at start")
    print(f"N = 15, design lqr, U poisoned (linf), {DATASETS} data sets (sim_seeds(0, {DATASETS})), {STARTS} starts")
    print(f"{'selection':>9} {'delta_u':>7} {'ours unst':>9} {'base unst':>9} {'smooth unst':>11} "
          f"{'ours mean rho':>13} {'base mean rho':>13} {'smooth mean':>11} {'smooth > base':>13} "
          f"{'ours [s]':>8} {'base [s]':>8}")
    xs: dict[tuple[str, float], list[tuple[object, np.ndarray]]] = {}
    for selection in SELECTIONS:
        for delta in DELTAS:
            ours, base, smooth, t_ours, t_base, kept = [], [], [], 0.0, 0.0, []
            for data_seed, attack_seed in seeds:
                attack = build_attack(objective="destabilize", horizon=15, seed=data_seed, delta_u=delta,
                                      selection=selection)
                t0 = time.perf_counter()
                res = destabilize_attack(attack, starts=STARTS, seed=attack_seed, max_iter=MAX_ITER)
                t1 = time.perf_counter()
                base.append(baseline(attack, attack_seed))
                t_base += time.perf_counter() - t1
                t_ours += t1 - t0
                ours.append(res.stats["spectral_radius"])
                smooth.append(max(r["smooth_radius"] or 0.0 for r in res.stats["details"]["starts"]))
                kept.append((attack, res.stats["x"]))
            xs[selection, delta] = kept
            o, b, sm = np.array(ours), np.array(base), np.array(smooth)
            print(f"{selection:>9} {delta:>7} {int((o >= 1).sum()):>9} {int((b >= 1).sum()):>9} "
                  f"{int((sm >= 1).sum()):>11} {o.mean():>13.4f} {b.mean():>13.4f} {sm.mean():>11.4f} "
                  f"{int((sm > b * (1 + 1e-6)).sum()):>8} / "
                  f"{len(o):<3} {t_ours:>8.1f} {t_base:>8.1f}", flush=True)
    print("\nTransfer (unstable loops of the target learner under our poisoning computed against the source):")
    print(f"{'source':>9} {'delta_u':>7} " + " ".join(f"{'-> ' + s:>12}" for s in SELECTIONS))
    for (source, delta), kept in xs.items():
        counts = [sum(transferred(a, x, target) >= 1 for a, x in kept) for target in SELECTIONS]
        print(f"{source:>9} {delta:>7} " + " ".join(f"{c:>12}" for c in counts), flush=True)


if __name__ == "__main__":
    main()
