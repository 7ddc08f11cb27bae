"""The DeePC certificate's cubic rest through M's weakest directions against the plan's own sensitivity (issue 46):
on attack_instance(T, seed 0), the budget at which each way's bound reaches the level 2 J0, the factors each way
multiplies, how far the engine's attack moves the Gram matrix along its weak directions, and one certificate's CPU
seconds (time.process_time), with the load. Usage: python benchmarks/bench_deepc_plan_sensitivity.py [T ...]"""

from __future__ import annotations

import dataclasses
import os
import platform
import sys
import time

import numpy as np

from bilevel.problems.deepc_instance import attack_instance
from bilevel.robust import as_target, certify
from bilevel.robust.deepc import _best_multipliers, cost_bound, gram_maps, hankel_rows


def proven_up_to(maps, atk, level: float, top: float = 0.01) -> float:
    """The largest budget (bisection, 30 steps on [0, top]) at which the maps' bound stays below the level."""
    lo, hi = 0.0, top
    scale = (float(np.linalg.norm(atk.u)), float(np.linalg.norm(atk.y)))
    for _ in range(30):
        mid = 0.5 * (lo + hi)
        found = cost_bound(maps, atk, mid, _best_multipliers(maps, atk.u.size, (mid * scale[0], mid * scale[1])))
        lo, hi = (mid, hi) if found["bound"] < level and found["slack_multiplier"] < atk.lambda_y else (lo, mid)
    return lo


def main(sizes: list[int]) -> None:
    print(f"# bench_deepc_plan_sensitivity.py, {time.strftime('%Y-%m-%d %H:%M UTC', time.gmtime())}, "
          f"{platform.machine()}, {os.cpu_count()} cores shared with other jobs, load {os.getloadavg()[0]:.1f}")
    for t in sizes:
        atk = attack_instance(T=t, seed=0)
        target = as_target(atk)
        cost = target.declaration
        c0 = time.process_time()
        certify(target, 5e-4)
        cold = time.process_time() - c0
        c0 = time.process_time()
        certify(target, 5e-4)
        warm = time.process_time() - c0
        maps = gram_maps(cost)
        m_only = dataclasses.replace(maps, p0w0=float("inf"), beta_p=float("inf"))
        print(f"T {t}: 2 J0 proven up to delta {proven_up_to(m_only, atk, cost.level):.4g} through M alone, "
              f"{proven_up_to(maps, atk, cost.level):.4g} with the plan's sensitivity; factors: out {maps.out:.3g} "
              f"against ||P0 W0|| {maps.p0w0:.3g}, out beta {maps.out * maps.beta:.4g} against sup ||P0 Delta|| "
              f"{maps.beta_p:.4g} (per unit delta); certificate CPU s {cold:.3f} cold, {warm:.4f} warm; "
              f"load {os.getloadavg()[0]:.1f}")
        k, n, lam = atk.t_ini, atk.horizon, atk.lambda_g
        w0 = hankel_rows(atk, atk.u, atk.y)
        pi = np.diag(np.concatenate([np.zeros(2 * k), np.full(n, 1 / atk.r_weight), np.full(n, 1 / atk.q)]))
        m0 = w0 @ w0.T + lam * pi
        ev, vec = np.linalg.eigh(m0)
        root = vec @ np.diag(ev ** -0.5) @ vec.T
        h = np.concatenate([atk.past_u[-k:], atk.past_y[-k:], np.zeros(n), np.full(n, atk.reference)])
        v0 = np.linalg.solve(m0, h)
        print(f"  M0's eigenvalues: smallest {', '.join(f'{e:.3g}' for e in ev[:6])}; largest {ev[-1]:.4g}")
        for delta in (4.5e-4, 0.002, 0.004, 0.006):
            a = target.attacks["engine"](delta, 0)
            d = hankel_rows(atk, a["u"], a["y"])
            w = w0 + d
            m = w @ w.T + lam * pi
            e = np.linalg.solve(m, h) - v0
            comp = vec.T @ e
            plan = (lam / atk.r_weight) * e[2 * k:2 * k + n]
            weak = (lam / atk.r_weight) * (vec[:, :6] @ comp[:6])[2 * k:2 * k + n]
            print(f"  delta {delta}: attack J/J0 {target.true_radius(a) * cost.level / cost.clean_cost:.4f}, "
                  f"||M0^-1/2 Delta|| {np.linalg.norm(root @ d, 2):.3f} (beta {maps.beta * delta:.3f}), "
                  f"lambda_min(M) {np.linalg.eigvalsh(m)[0]:.4g}, v's change along the 3 weakest "
                  f"{', '.join(f'{c:.3g}' for c in comp[:3])}, plan change {np.linalg.norm(plan):.3g} "
                  f"({np.linalg.norm(weak):.3g} from the 6 weakest)")


if __name__ == "__main__":
    main([int(s) for s in sys.argv[1:]] or [100, 60])
