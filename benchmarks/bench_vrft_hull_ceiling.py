"""How far can any certificate of the VRFT kind (an outer convex set of reachable controllers, then zero exclusion of
the true loop's polynomial, affine in theta) go? At a frequency z, the reachable values p(theta(a), z) form a set in
the complex plane; every convex outer set of the controllers contains their convex hull, so if 0 lies in the convex
hull of reachable values found by ascent, no such certificate proves that budget, whatever its bounds. Per budget
(fractions of the attack's delta_ub, docs/results/certify/certify.csv) and frequency (a grid on [0, pi]), projected
gradient descent of Re(conj(u) p(theta(a), z)) over both budget balls (exact gradients of the numpy least squares, dense
operators) for 6 directions u (2 starts: the linearized minimizer and a random point, 30 steps), the values re-fitted
by np.linalg.lstsq, at 16 frequencies: the 8 smallest local minima of |p0(z)| / ||s(z)|| (p = p0 + theta's, a grid of
1024) and the 8 where the certificate's set at that budget comes closest to failing (vrft.critical; none where
beta >= 1); reported: the hull margin max_u min_found Re(conj(u) p) / |p0| (<= 0: 0 is in the hull, no convex
certificate exists) at the frequency where it is smallest (only on those frequencies: a positive margin proves nothing),
and, as a second attack on the true loop (direction (a): is delta_ub tight?), the largest true spectral radius of the
found poisonings against that of the reproduction's joint attack (8 starts) at the same budget."""
import csv, os, sys, time
import numpy as np

import bilevel.robust.vrft as V
from bilevel.experiments.certify import certify_tasks
from bilevel.attacks.vrft_methods import attack
from bilevel.problems.vrft_instance import attack_instance

ANGLES, STEPS = 6, 30


def setup(atk):
    T, Tu = V._operators(atk)
    return T, Tu


def fit(T, Tu, u, y):
    phi = np.einsum("irn,n->ri", T, y)
    return np.linalg.lstsq(phi, Tu @ u, rcond=None)[0], phi


def descend(atk, T, Tu, c, ru, ry, rng):
    """Minimize c'theta(a) over ||a_u|| <= ru, ||a_y|| <= ry (projected normalized gradient, 2 starts)."""
    def value_grad(au, ay):
        th, phi = fit(T, Tu, atk.u + au, atk.y + ay)
        r = Tu @ (atk.u + au) - phi @ th
        lam = np.linalg.solve(phi.T @ phi, c)
        pl = phi @ lam
        gy = np.einsum("i,irn->rn", lam, T).T @ r - np.einsum("i,irn->rn", th, T).T @ pl
        return c @ th, Tu.T @ pl, gy, th
    proj = lambda a, r: a * min(1.0, r / max(np.linalg.norm(a), 1e-300))  # noqa: E731
    _, gu, gy, _ = value_grad(np.zeros_like(atk.u), np.zeros_like(atk.y))
    starts = [(-ru * gu / np.linalg.norm(gu), -ry * gy / np.linalg.norm(gy))]
    z = rng.standard_normal((2, atk.u.size))
    starts.append((ru * z[0] / np.linalg.norm(z[0]), ry * z[1] / np.linalg.norm(z[1])))
    best = (np.inf, None)
    for au, ay in starts:
        for k in range(STEPS):
            val, gu, gy, th = value_grad(au, ay)
            if val < best[0]:
                best = (val, th)
            step = 0.5 / (1 + k / 8)
            au = proj(au - step * ru * gu / max(np.linalg.norm(gu), 1e-300), ru)
            ay = proj(ay - step * ry * gy / max(np.linalg.norm(gy), 1e-300), ry)
    return best[1]


ub = {int(r["data_seed"]): float(r["delta_ub"]) for r in csv.DictReader(open("docs/results/certify/certify.csv"))
      if r["family"] == "vrft" and r["size"] == "512"}
count = int(sys.argv[1]) if len(sys.argv) > 1 else 1
fractions = [float(f) for f in (sys.argv[2] if len(sys.argv) > 2 else "0.25,0.333,0.5").split(",")]
print(f"# {time.strftime('%Y-%m-%d %H:%M UTC', time.gmtime())}, load {os.getloadavg()}")
for task in [t for t in certify_tasks(32, False, 0, 10000, ("vrft",)) if t["size"] == 512][:count]:
    atk = attack_instance("destabilize", "B", 0.0, 0.0, seed=task["seed"], N=512)
    T, Tu = setup(atk)
    loop = atk.setting.loop
    rng = np.random.default_rng(0)
    degree = loop.base.size - 1
    for frac in fractions:
        c0 = time.process_time()
        delta = frac * ub[task["seed"]]
        ru, ry = delta * np.linalg.norm(atk.u), delta * np.linalg.norm(atk.y)
        worst, radius = (np.inf, None), 0.0
        grid = np.linspace(0.0, np.pi, 1024)
        zs = np.exp(1j * grid)[:, None] ** np.arange(degree, -1, -1)[None, :]
        ratio = np.abs(zs @ loop.base) / np.linalg.norm(zs @ loop.slopes.T, axis=1)
        minima = [i for i in np.argsort(ratio) if 0 < i < 1023 and ratio[i] <= min(ratio[i - 1], ratio[i + 1])][:8]
        _, P, _ = V._entry(atk)
        _, keys = V.critical(atk, P, delta)
        coarse = np.linspace(0.0, np.pi, V.COARSE)
        freqs = sorted({float(grid[i]) for i in minima} | {float(coarse[i]) for i, _ in keys})
        for w in freqs:
            zp = np.exp(1j * w) ** np.arange(degree, -1, -1)
            p0, s = loop.base @ zp, loop.slopes @ zp
            points = [p0]
            for j in range(ANGLES):
                u = p0 / abs(p0) * np.exp(2j * np.pi * j / ANGLES)
                th = descend(atk, T, Tu, np.real(np.conj(u) * s), ru, ry, rng)
                points.append(loop.base @ zp + th @ s)
                radius = max(radius, loop.spectral_radius(th))
            points = np.array(points)
            phis = np.exp(1j * np.linspace(0, 2 * np.pi, 1440, endpoint=False))
            margin = float(np.max(np.min(np.real(np.conj(phis)[:, None] * points[None, :]), axis=1))) / abs(p0)
            if margin < worst[0]:
                worst = (margin, w)
        joint = attack(V.at_budget(atk, delta), "joint", seed=task["attack_seed"], starts=8)
        signals = {"u": atk.u + np.asarray(joint.x["a_u"]), "y": atk.y + np.asarray(joint.x["a_y"])}
        print(f"data seed {task['seed']}: delta {delta:.5g} ({frac:g} delta_ub): smallest hull margin {worst[0]:.3f} "
              f"at {worst[1]:.3f} rad (<= 0: no convex certificate); largest true spectral radius found {radius:.4f}, "
              f"joint attack's {loop.spectral_radius(V.refit(atk, signals)):.4f}; "
              f"{time.process_time() - c0:.0f} CPU s, load {os.getloadavg()[0]:.1f}", flush=True)
