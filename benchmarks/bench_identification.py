"""Stealthy poisoning of state-space identification: the engine's attack of `bilevel reproduce identification` against
the SLSQP baseline (bilevel.experiments.identification_baseline: exact gradients, 100 iterations) on the same data sets.

Problem (bilevel.problems.identification, learner "ss"): the flexible transmission in controllable canonical form,
T samples, input std 1, process-noise std 0.1; ||dX||_F <= delta ||X||_F, ||dU||_F <= delta ||U||_F; maximize
||[A B]' - [A B]_clean||_F^2 subject to |1 - stat'/stat| <= delta for the variance, whiteness and input statistics.
Engine: bilevel.experiments.identification.METHOD on the problem declared once and re-targeted to each data set
(problem_for), as the sweep runs it; its time includes re-targeting (with the stealth start) and the certificate.
Both points are judged by the defender's tests on a numpy refit of the returned data. Both run with one BLAS thread
(as the sweep's workers do); the ratios are of CPU time (time.process_time) and of wall time, in one process.
Run: python benchmarks/bench_identification.py [data_sets] [T] [delta]; outputs in benchmarks/results/
bench_identification.txt (10 100 0.05), bench_identification_delta_0.1.txt (10 100 0.1),
bench_identification_delta_0.025.txt (10 100 0.025), bench_identification_T500.txt (5 500 0.05) and
bench_identification_T500_delta_0.1.txt (3 500 0.1).
"""

from __future__ import annotations

import os
import platform
import sys
import time
from datetime import datetime, timezone
from typing import Any, Callable

import numpy as np

from bilevel.experiments.identification import METHOD
from bilevel.experiments.identification_baseline import START_SCALE, judge, slsqp_attack
from bilevel.problems.identification import problem_for
from bilevel.problems.identification_instance import IdentificationAttack, attack_instance
from bilevel.threads import single_threaded


def timed(fn: Callable[[], Any]) -> tuple[Any, float, float]:
    """(fn(), CPU seconds, wall seconds)."""
    c0, w0 = time.process_time(), time.perf_counter()
    out = fn()
    return out, time.process_time() - c0, time.perf_counter() - w0


def engine(atk: IdentificationAttack) -> tuple[dict[str, np.ndarray], str]:
    """The engine's poisoned signals, and its status ("solved" only where also certified)."""
    result = problem_for(atk).solve(**METHOD, seed=0)
    signals = {k: atk.signals[k] + np.reshape(result.x[f"d{k}"], atk.signals[k].shape) for k in atk.signals}
    return signals, result.status.value


def main(data_sets: int = 10, T: int = 100, delta: float = 0.05) -> None:
    print(f"# bench_identification  {datetime.now(timezone.utc):%Y-%m-%d %H:%M} UTC  {platform.node()}  "
          f"{platform.processor() or platform.machine()}  cores={os.cpu_count()}  python {platform.python_version()}  "
          f"load {os.getloadavg()[0]:.1f}")
    print(f"ident-ss, T = {T}, budgets and stealth delta = {delta}; engine {METHOD}; baseline SLSQP, 100 iterations, "
          f"exact gradients, start at {START_SCALE} x the budget radii; one BLAS thread each\n")
    rows = []
    with single_threaded():
        _, first_cpu, first_wall = timed(lambda: engine(attack_instance("ss", T=T, eps=delta, stealth=delta, seed=0)))
        print(f"engine's first solve (declaration, preparation, compilation): cpu {first_cpu:.2f} s, wall "
              f"{first_wall:.2f} s, once per process\n")
        print(f"{'seed':>4} | {'engine |dAB|_2':>14} {'cpu s':>6} {'ok':>3} {'status':<19} | {'SLSQP |dAB|_2':>14} "
              f"{'cpu s':>6} {'ok':>3}   (ok: stealthy by the defender's tests; status: the engine's, solved = "
              "converged and certified)")
        statuses = []
        for seed in range(data_sets):
            atk = attack_instance("ss", T=T, eps=delta, stealth=delta, seed=seed)
            (signals, status), ce, we = timed(lambda: engine(atk))
            e = judge(atk, signals)
            (signals, _, _), cb, wb = timed(lambda: slsqp_attack(atk, seed))
            b = judge(atk, signals)
            rows.append((e["norm2"], e["stealthy"], ce, we, b["norm2"], b["stealthy"], cb, wb))
            statuses.append(status)
            print(f"{seed:4d} | {e['norm2']:14.4f} {ce:6.2f} {'yes' if e['stealthy'] else 'no':>3} {status:<19} | "
                  f"{b['norm2']:14.4f} {cb:6.2f} {'yes' if b['stealthy'] else 'no':>3}", flush=True)
    r = np.array(rows, dtype=float)
    reach = np.mean((r[:, 1] == 1) & ((r[:, 0] >= r[:, 4] * (1 - 1e-6)) | (r[:, 5] == 0)))
    print(f"\nengine stealthy on {int(r[:, 1].sum())}/{len(r)} (solved and certified on "
          f"{statuses.count('solved')}), SLSQP stealthy on {int(r[:, 5].sum())}/{len(r)}; engine stealthy and "
          f"||d[A B]||_2 >= SLSQP's (or SLSQP not stealthy) on {reach:.0%}; median ||d[A B]||_2 engine "
          f"{np.median(r[:, 0]):.4f}, SLSQP {np.median(r[:, 4]):.4f}")
    print(f"SLSQP / engine time: CPU total {r[:, 6].sum() / r[:, 2].sum():.1f}x (median per data set "
          f"{np.median(r[:, 6] / r[:, 2]):.1f}x), wall total {r[:, 7].sum() / r[:, 3].sum():.1f}x; median engine cpu "
          f"{np.median(r[:, 2]):.2f} s, SLSQP {np.median(r[:, 6]):.2f} s per data set (engine's first solve not "
          "counted: once per worker process)")


if __name__ == "__main__":
    main(*(int(a) if i < 2 else float(a) for i, a in enumerate(sys.argv[1:])))
