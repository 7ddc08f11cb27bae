"""Does the VRFT certificate's need for ||B|| <= beta < 1 limit delta_lb? On the reproduction's first three data sets
(N = 512, delta_ub from docs/results/certify/certify.csv): (1) the smallest singular value of the poisoned whitened
regressor A = Q + Phi(a_y) R^-1 over the output budget ball, found by alternating descent (x: A's weakest right
singular vector; a_y: the trust-region minimizer of ||Qx + H(R^-1 x) a_y||; 4 random starts; an upper bound on the
true minimum), against the certificate's lower bound 1 - beta; (2) delta_lb by bisection (2 %, no re-check, not a
proof) with the certificate's floor s = 1 - beta, with the descent's value as the floor (what a certified floor as
good as the descent could give), and with s = 1 (the most any floor could give). CPU seconds, load."""
import csv, os, sys, time
import numpy as np
from scipy.optimize import brentq

import bilevel.robust.vrft as V
from bilevel.experiments.certify import certify_tasks
from bilevel.problems.vrft_instance import attack_instance


def trs(H, q, rho):
    """argmin ||q + H a|| over ||a|| <= rho (SVD and the secular equation)."""
    U, s, Vt = np.linalg.svd(H, full_matrices=False)
    g = U.T @ q
    keep = s > 1e-12 * s[0]
    a = -(Vt[keep].T @ (g[keep] / s[keep]))
    if np.linalg.norm(a) <= rho:
        return a
    f = lambda lam: np.linalg.norm(s[keep] * g[keep] / (s[keep] ** 2 + lam)) - rho  # noqa: E731
    hi = 1.0
    while f(hi) > 0:
        hi *= 4
    lam = brentq(f, 0.0, hi, xtol=1e-14)
    return -(Vt[keep].T @ (s[keep] * g[keep] / (s[keep] ** 2 + lam)))


def descent_floor(atk, P, delta, starts=4, iters=30, seed=0):
    rho = delta * P.norm_y
    Rinv = np.linalg.inv(P.R)
    Q = atk.phi0 @ Rinv
    Mi = np.tensordot(Rinv, P.T, axes=(0, 0))
    rng, best = np.random.default_rng(seed), np.inf
    for _ in range(starts):
        x = rng.standard_normal(Rinv.shape[0])
        x /= np.linalg.norm(x)
        val = np.inf
        for _ in range(iters):
            a = trs(np.tensordot(x, Mi, axes=(0, 0)), Q @ x, rho)
            _, s, vt = np.linalg.svd(Q + np.stack([m @ a for m in Mi], axis=1))
            x, done, val = vt[-1], val - s[-1] < 1e-6, min(val, s[-1])
            if done:
                break
        best = min(best, val)
    return best


def proves(atk, P, known, delta, floor):
    original = V.remainder
    V.remainder = lambda P_, d, floor_=0.0: original(P_, d, floor(d))
    try:
        W, keys = V.critical(atk, P, delta)
        _, _, found = V._sweep(atk, P, delta, joint=V.joint_norms(P, W, V._eig_norm, keys, known))
        return found is not None and found.proven
    finally:
        V.remainder = original


def bisect(test, top, tol=0.02):
    """The largest budget in (0, top] where test holds, by bisection to tol * top (0 if none)."""
    low, high = 0.0, top
    while high - low > tol * high:
        mid = 0.5 * (low + high) if low > 0 else high / 2
        low, high = (mid, high) if test(mid) else (low, mid)
    return low


def vrft_512(count):
    """(the reproduction's first `count` N = 512 data sets' tasks, their committed delta_ub by data seed); prints the
    header line (date, load)."""
    ub = {int(r["data_seed"]): float(r["delta_ub"]) for r in csv.DictReader(open("docs/results/certify/certify.csv"))
          if r["family"] == "vrft" and r["size"] == "512"}
    print(f"# {time.strftime('%Y-%m-%d %H:%M UTC', time.gmtime())}, load {os.getloadavg()}")
    return [t for t in certify_tasks(32, False, 0, 10000, ("vrft",)) if t["size"] == 512][:count], ub


def main(count):
    tasks, ub = vrft_512(count)
    for task in tasks:
        atk = attack_instance("destabilize", "B", 0.0, 0.0, seed=task["seed"], N=512)
        _, P, known = V._entry(atk)
        top, limit = ub[task["seed"]], 1 / (P.beta1 * P.norm_y)
        print(f"data seed {task['seed']}: delta_ub {top:.5g}, beta limit 1/(beta1 ||y||) {limit:.5g}", flush=True)
        lbs = {}
        for label, floor in (("1 - beta", lambda d: 0.0), ("s = 1", lambda d: 1.0)):
            c = time.process_time()
            lbs[label] = bisect(lambda d: proves(atk, P, known, d, floor), top)
            print(f"  delta_lb, floor {label}: {lbs[label]:.5g} (ratio {top / lbs[label]:.3g}), "
                  f"{time.process_time() - c:.0f} CPU s", flush=True)
        for delta in (lbs["1 - beta"], 2 * lbs["1 - beta"], limit, top / 3, top):
            c = time.process_time()
            mu = descent_floor(atk, P, delta)
            beta = delta * P.norm_y * P.beta1
            print(f"  delta {delta:.5g}: 1 - beta {1 - beta:.3f}, descent's sigma_min(A) {mu:.3f}; proven with the "
                  f"descent's floor: {proves(atk, P, known, delta, lambda d: mu)} "
                  f"({time.process_time() - c:.0f} CPU s, "
                  f"load {os.getloadavg()[0]:.1f})", flush=True)


if __name__ == "__main__":
    main(int(sys.argv[1]) if len(sys.argv) > 1 else 3)
