"""willems-destabilize against an independent baseline: a 64-start numpy projected ascent on the true rho(A + B K).

Setting of issue 32: batch reactor, design lqr, the min-norm learner, input poisoning in an linf box of radius
delta_u in {0.1, 0.2, 0.3, 0.5}; 48 data sets at N = 15 and 16 at N = 50 (the Willems reproduction's seeds).
Ours: bilevel.attacks.willems.destabilize_attack with its defaults, timed whole, cold (a new attack: the engine's
preparation, the learner's solve, the ascent, finalize's certificate re-solve and probe) and warm (a second call on
the same attack, whose prepared problem and learner solutions it keeps: ascent, certificate and probe).
Baseline (shares nothing with the attack code but the data and the learner's Q): K(dU) = K0 + dU G with G = Q S^-1 by hand, the true plant's (A, B), 64 starts (clean data + uniform
in the box, its own rng), per start projected gradient ascent on rho with d rho / dK = B' Re(conj(l)/|l| u' v')
(u, v the top eigenvalue's left/right vectors, here from scipy.linalg.eig), Armijo backtracking, 100 iterations.
Its time excludes the learner solve. Times are CPU seconds (time.process_time, one BLAS thread), so the ratios
base/cold hold on a loaded machine. Asserts nothing. Usage: bench_willems_destabilize.py [SETS_N15] [SETS_N50].
"""

from __future__ import annotations

import os
import platform
import sys
import time

import numpy as np
import scipy.linalg

from bilevel.attacks.willems import destabilize_attack
from bilevel.ddc.plants import batch_reactor
from bilevel.experiments.willems import sim_seeds
from bilevel.problems.willems import build_attack
from bilevel.threads import single_threaded

SETS = {15: int(sys.argv[1]) if len(sys.argv) > 1 else 48, 50: int(sys.argv[2]) if len(sys.argv) > 2 else 16}
DELTAS = (0.1, 0.2, 0.3, 0.5)
BASE_STARTS, BASE_ITER = 64, 100
PLANT = batch_reactor()


def rho_and_grad(k: np.ndarray) -> tuple[float, np.ndarray]:
    """rho(A + B K) and d rho / dK (top eigenvalue; a conjugate pair gives the same gradient from either member)."""
    lam, left, right = scipy.linalg.eig(PLANT.A + PLANT.B @ k, left=True, right=True)
    i = int(np.argmax(np.abs(lam)))
    u, v = np.conj(left[:, i]), right[:, i]
    dm = np.real(np.conj(lam[i]) / abs(lam[i]) * np.outer(u, v) / (u @ v))
    return float(abs(lam[i])), PLANT.B.T @ dm


def baseline(k0: np.ndarray, g: np.ndarray, delta: float, seed: int) -> float:
    """Largest true rho reached by 64 projected ascents on rho(A + B (K0 + dU G)) over |dU| <= delta."""
    rng = np.random.default_rng(seed)
    m, t = PLANT.B.shape[1], g.shape[0]
    best = 0.0
    for s in range(BASE_STARTS):
        du = np.zeros((m, t)) if s == 0 else rng.uniform(-delta, delta, (m, t))
        rho, dk = rho_and_grad(k0 + du @ g)
        step = delta
        for _ in range(BASE_ITER):
            grad = dk @ g.T
            scale = np.abs(grad).max()
            if scale == 0:
                break
            while step > 1e-8 * delta:
                trial = np.clip(du + step * grad / scale, -delta, delta)
                rho_t, dk_t = rho_and_grad(k0 + trial @ g)
                if rho_t >= rho + 1e-4 * float(np.sum(grad * (trial - du))) and rho_t > rho:
                    du, rho, dk = trial, rho_t, dk_t
                    step = min(2 * step, 2 * delta)
                    break
                step /= 2
            else:
                break
        best = max(best, rho)
    return best


def main() -> None:
    print(f"# {' '.join(sys.argv)} -- {time.strftime('%Y-%m-%d %H:%M:%S UTC', time.gmtime())}, "
          f"{platform.node()} {platform.machine()}, nproc {os.cpu_count()}, load average "
          f"{' '.join(f'{v:.2f}' for v in os.getloadavg())} at start")
    print("design lqr, min-norm learner, U poisoned (linf); ours: destabilize_attack defaults; baseline: 64-start "
          "numpy projected ascent on the true rho (time without the learner solve); CPU seconds, OPENBLAS_NUM_THREADS="
          f"{os.environ.get('OPENBLAS_NUM_THREADS', 'unset')}")
    print(f"{'N':>3} {'delta_u':>7} {'sets':>4} {'ours unst':>9} {'base unst':>9} {'ours mean rho':>13} "
          f"{'base mean rho':>13} {'ours>=base':>10} {'cold med [s]':>12} {'warm med [s]':>12} "
          f"{'base med [s]':>12} {'base/cold':>10}")
    for n, sets in SETS.items():
        for delta in DELTAS:
            ours, base, t_ours, t_ascent, t_base = [], [], [], [], []
            for data_seed, attack_seed in sim_seeds(0, sets):
                attack = build_attack(objective="destabilize", horizon=n, seed=data_seed, delta_u=delta)
                t0 = time.process_time()
                res = destabilize_attack(attack, seed=attack_seed)
                t_ours.append(time.process_time() - t0)
                ours.append(res.stats["spectral_radius"])
                t0 = time.process_time()
                destabilize_attack(attack, seed=attack_seed)  # the attack's prepared problem and learner kept
                t_ascent.append(time.process_time() - t0)
                with single_threaded():  # the learner's Q, for the baseline
                    q = attack.oracle(True).evaluate(np.zeros(attack.budget().size)).lower.y.reshape(
                        n, -1, order="F")
                    s_mat = attack.x[:, :n] @ q  # S = X0 Q, symmetric at the learner's solution
                    g = q @ np.linalg.inv(0.5 * (s_mat + s_mat.T))
                    k0 = attack.u @ g
                    t0 = time.process_time()
                    base.append(baseline(k0, g, delta, attack_seed + 1))
                    t_base.append(time.process_time() - t0)
            o, b = np.array(ours), np.array(base)
            print(f"{n:>3} {delta:>7} {sets:>4} {int((o >= 1).sum()):>9} {int((b >= 1).sum()):>9} {o.mean():>13.4f} "
                  f"{b.mean():>13.4f} {int((o >= b - 1e-9).sum()):>6} / {sets:<3}{np.median(t_ours):>12.3f} "
                  f"{np.median(t_ascent):>12.3f} {np.median(t_base):>12.3f} "
                  f"{np.median(t_base) / np.median(t_ours):>10.1f}", flush=True)


if __name__ == "__main__":
    main()
