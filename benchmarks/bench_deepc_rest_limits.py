"""What limits the DeePC certificate (issue 46), on one reproduction data set (T = 100): per budget, the bound's terms
in sqrt(J) against a projected ascent of the linear + quadratic part ||r0 + G a + q(a)|| over the budget balls (a lower
bound on any joint bound of those two parts, e.g. an S-lemma SDP; its sum with the cubic rest's bound is the most such
a joint bound could prove), the smallest eigenvalue of M0^-1/2 M M0^-1/2 found by alternating descent against its two
lower bounds (1 - beta)^2 and (1 - gamma / 2)^2, and the certified budget when each ingredient of the rest's bound
is halved (not a proof; how much a 2 times tighter ingredient would give). With the load.
Usage: python benchmarks/bench_deepc_rest_limits.py [data seed]"""

from __future__ import annotations

import dataclasses
import os
import platform
import sys
import time

import numpy as np

from bench_deepc_plan_sensitivity import proven_up_to
from bilevel.problems.deepc_instance import attack_instance
from bilevel.robust import as_target
from bilevel.robust.deepc import _best_multipliers, _cost_metric, _unit_rows, cost_bound, gram_maps, hankel_rows


def main(seed: int) -> None:
    print(f"# bench_deepc_rest_limits.py {seed}, {time.strftime('%Y-%m-%d %H:%M UTC', time.gmtime())}, "
          f"{platform.machine()}, {os.cpu_count()} cores shared with other jobs, load {os.getloadavg()[0]:.1f}")
    c0 = time.process_time()
    atk = attack_instance(T=100, seed=seed)
    cost = as_target(atk).declaration
    maps = gram_maps(cost)
    t, k, n, lam = atk.u.size, atk.t_ini, atk.horizon, atk.lambda_g
    w0 = hankel_rows(atk, atk.u, atk.y)
    pi = lam * np.diag(np.concatenate([np.zeros(2 * k), np.full(n, 1 / atk.r_weight), np.full(n, 1 / atk.q)]))
    h = np.concatenate([atk.past_u[-k:], atk.past_y[-k:], np.zeros(n), np.full(n, atk.reference)])
    m0 = w0 @ w0.T + pi
    ev, vec = np.linalg.eigh(m0)
    s = vec @ np.diag(ev ** -0.5) @ vec.T
    v0 = np.linalg.solve(m0, h)
    g0 = w0.T @ v0
    units = _unit_rows(atk)
    dvt_v0 = np.einsum("src,r->sc", units, v0)
    dv1 = -np.linalg.solve(m0, (np.einsum("src,c->sr", units, g0) + dvt_v0 @ w0.T).T).T
    dg1 = dv1 @ w0 + dvt_v0
    mm, _ = _cost_metric(atk)
    p = (lam / atk.r_weight) * mm @ np.linalg.inv(m0)[2 * k:2 * k + n]
    quad = (np.tensordot(p @ w0, units, axes=([1], [2])) @ dv1.T + np.tensordot(p, units, axes=([1], [1])) @ dg1.T)
    scale = (float(np.linalg.norm(atk.u)), float(np.linalg.norm(atk.y)))
    rng = np.random.default_rng(0)

    def onto(a, rad):
        for blk, r in ((slice(0, t), rad[0]), (slice(t, 2 * t), rad[1])):
            a[blk] *= min(1.0, r / max(np.linalg.norm(a[blk]), 1e-300))
        return a

    def joint(rad):  # ascent of ||r0 + G a + q(a)||^2 over the balls, 6 starts
        def f(a):
            res = maps.r0 + maps.g @ a + np.einsum("isj,s,j->i", quad, a, a)
            return res @ res, 2 * (maps.g + np.einsum("isj,j->is", quad + quad.transpose(0, 2, 1), a)).T @ res
        best = 0.0
        for _ in range(6):
            a = rng.standard_normal(2 * t)
            a = np.concatenate([rad[0] * a[:t] / np.linalg.norm(a[:t]), rad[1] * a[t:] / np.linalg.norm(a[t:])])
            val, grad, step = *f(a), 1.0
            while step > 1e-8:
                b = onto(a + step * max(rad) * grad / np.linalg.norm(grad), rad)
                fb, gb = f(b)
                a, val, grad, step = (b, fb, gb, 1.3 * step) if fb > val else (a, val, grad, 0.5 * step)
            best = max(best, val)
        return np.sqrt(best)

    def weakest(rad):  # min over the balls of lambda_min(M0^-1/2 M M0^-1/2), alternating descent, 4 starts
        worst = np.inf
        for _ in range(4):
            z, a = rng.standard_normal(2 * (k + n)), np.zeros(2 * t)
            for _ in range(60):
                x = s @ z / np.linalg.norm(z)
                zx, b = np.einsum("src,r->cs", units, x), w0.T @ x
                for _ in range(60):
                    a = onto(a - zx.T @ (b + zx @ a) / np.linalg.norm(zx, 2) ** 2, rad)
                w = w0 + np.tensordot(a, units, axes=1)
                e, vv = np.linalg.eigh(s @ (w @ w.T + pi) @ s)
                z = vv[:, 0]
            worst = min(worst, e[0])
        return worst

    level = np.sqrt(cost.level)
    print(f"J0 {cost.clean_cost:.4f}, sqrt(level) {level:.4f}; per unit delta beta {maps.beta:.1f}, gamma / 2 "
          f"{maps.gamma / 2:.1f}")
    for delta in (0.0005, 0.0008, 0.001, 0.0014):
        rad = (delta * scale[0], delta * scale[1])
        found = cost_bound(maps, atk, delta, _best_multipliers(maps, t, rad))
        third = min(found["third_through_m"], found["third_through_plan"])
        lq = joint(rad)
        print(f"delta {delta}: sqrt(linear) {np.sqrt(found['linear']):.4f} + quadratic {found['second_order']:.4f} "
              f"= {np.sqrt(found['linear']) + found['second_order']:.4f} against the joint ascent {lq:.4f}; cubic "
              f"rest {third:.4f}; bound {np.sqrt(found['bound']):.4f}, with a joint bound at best {lq + third:.4f}; "
              f"lambda_min(M0^-1/2 M M0^-1/2) found {weakest(rad):.3f}, (1 - beta)^2 "
              f"{max(1 - maps.beta * delta, 0) ** 2:.3f}, (1 - gamma / 2)^2 "
              f"{max(1 - maps.gamma * delta / 2, 0) ** 2:.3f}")
    base = proven_up_to(maps, atk, cost.level)
    halves = {"||Delta' dv1||": {"delta_frob": maps.delta_frob / 2, "dv1_m0": maps.dv1_m0 / 2},
              "||M0^1/2 R2||": {"quad_m0": maps.quad_m0 / 2}, "||dg1||": {"dg1": maps.dg1 / 2},
              "sup ||P0 Delta||": {"beta_p": maps.beta_p / 2}, "||P0 W0||": {"p0w0": maps.p0w0 / 2},
              "beta": {"beta": maps.beta / 2}, "gamma": {"gamma": maps.gamma / 2},
              "quadratic part": {"quad": maps.quad / 2}}
    halves["all of them"] = {key: val for change in halves.values() for key, val in change.items()}
    alone = proven_up_to(dataclasses.replace(maps, gamma=np.inf), atk, cost.level)
    print(f"certified 2 J0 budget {base:.5g} (with kappa; {alone:.5g} with beta alone); halving one ingredient "
          f"multiplies it by: " + ", ".join(
              f"{name} {proven_up_to(dataclasses.replace(maps, **change), atk, cost.level) / base:.3f}"
              for name, change in halves.items()))
    print(f"CPU s {time.process_time() - c0:.1f}, load {os.getloadavg()[0]:.1f}")


if __name__ == "__main__":
    main(int(sys.argv[1]) if len(sys.argv) > 1 else 3757552657)
