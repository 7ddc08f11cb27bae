"""Stealthy poisoning of state-space identification: the engine (ident-ss declared with stealth, method ipopt) against
a baseline written here, scipy SLSQP with exact gradients on the same problem (100 iterations).

Problem (bilevel.problems.identification, learner "ss"): the flexible transmission in controllable canonical form,
T samples, input std 1, process-noise std 0.1; ||dX||_F <= delta ||X||_F, ||dU||_F <= delta ||U||_F; maximize
||[A B]' - [A B]_clean||_F^2 subject to |1 - stat'/stat| <= delta for the variance, whiteness and input statistics.
Baseline: the same program reduced to the attacker's variables with the learner in closed form, [A B](x) = Y Z'(Z Z')^-1
(and the input test's restricted fit likewise), as CasADi expressions differentiated exactly; SLSQP from a seeded point
on the budget spheres, maxiter 100. Both points are judged by the defender's tests (bilevel.ddc.residual_tests) on the
returned data, refitted with numpy: "stealthy" when every statistic is within delta (+1e-6) of its clean value.
The engine declares the problem once and re-targets it to each data set (load_instance), as a sweep does.
Times are wall clock in one process; compare the ratio, not the seconds.
Run: python benchmarks/bench_identification.py [data_sets] [T] [delta]
"""

from __future__ import annotations

import os
import platform
import sys
import time
from datetime import datetime, timezone

import casadi as ca
import numpy as np
from scipy.optimize import minimize

from bilevel import BilevelProblem
from bilevel.problems.identification import STATISTICS, declare, load_instance, statistics
from bilevel.problems.identification_instance import IdentificationAttack, attack_instance, ss_regression

ENGINES = {"L-BFGS": {"method": "ipopt", "starts": 1, "ipopt": {"hessian_approximation": "limited-memory"}},
           "exact": {"method": "ipopt", "starts": 1}}
"""The engine's configurations: IPOPT on the KKT form with a limited-memory Hessian, and with the exact one."""
START_SCALE = 0.1
"""SLSQP starts at a random point at this fraction of each budget radius: inside the stealth constraints (from the
budget spheres themselves it ends infeasible after 100 iterations on 19 of 20 data sets, T = 100, delta = 0.05)."""


def closed_form(Y: ca.SX, Z: ca.SX) -> ca.SX:
    """argmin_Theta ||Y - Theta Z||_F^2 = Y Z' (Z Z')^-1 as an expression."""
    return ca.solve(ca.mtimes(Z, Z.T), ca.mtimes(Z, Y.T)).T


def slsqp(atk: IdentificationAttack, seed: int, maxiter: int = 100, start_scale: float = 1.0
          ) -> tuple[dict[str, np.ndarray], float]:
    """The baseline's poisoned signals and wall time, from a random point at start_scale times each budget radius."""
    t0 = time.perf_counter()
    X, U = atk.signals["X"], atk.signals["U"]
    dX, dU = ca.SX.sym("dX", *X.shape), ca.SX.sym("dU", *U.shape)
    x = ca.vertcat(ca.vec(dX), ca.vec(dU))
    Y, Z = ss_regression(ca.DM(X) + dX, ca.DM(U) + dU)
    theta = closed_form(Y, Z)
    keep = [i for i in range(Z.shape[0]) if i not in atk.input_rows]
    E, E_r = Y - ca.mtimes(theta, Z), Y - ca.mtimes(closed_form(Y, Z[keep, :]), Z[keep, :])
    stats = statistics(E, E_r, Z.shape[0], len(atk.input_rows), atk.setting.noise_std, atk.lags)
    clean = atk.tests()
    ratios = ca.vertcat(*[stats[k] / clean[k].statistic for k in STATISTICS])
    g = ca.vertcat(atk.radius("X") ** 2 - ca.sumsqr(dX), atk.radius("U") ** 2 - ca.sumsqr(dU),
                   1 + atk.stealth - ratios, ratios - (1 - atk.stealth))  # >= 0
    f = -ca.sumsqr(theta - ca.DM(atk.theta0))
    fun = ca.Function("f", [x], [f, ca.gradient(f, x)])
    con = ca.Function("g", [x], [g, ca.jacobian(g, x)])
    rng = np.random.default_rng(seed)
    x0 = np.concatenate([start_scale * atk.radius(k) * (v := rng.standard_normal(atk.signals[k].size)) / np.linalg.norm(v)
                         for k in ("X", "U")])
    res = minimize(lambda v: tuple(np.array(o).ravel() for o in fun(v)), x0, jac=True, method="SLSQP",
                   constraints={"type": "ineq", "fun": lambda v: np.array(con(v)[0]).ravel(),
                                "jac": lambda v: np.array(con(v)[1])},
                   options={"maxiter": maxiter, "ftol": 1e-12})
    nX = X.size
    return {"X": X + res.x[:nX].reshape(X.shape, order="F"), "U": U + res.x[nX:].reshape(U.shape, order="F")}, \
        time.perf_counter() - t0


def engine(problem: BilevelProblem, atk: IdentificationAttack, options: dict) -> tuple[dict[str, np.ndarray], float,
                                                                                     str, bool]:
    """The engine's poisoned signals on the declared problem re-targeted to `atk` (load_instance), the wall time of
    loading and solving, the status and the certificate's verdict."""
    t0 = time.perf_counter()
    load_instance(problem, atk)
    result = problem.solve(**options, seed=0)
    seconds = time.perf_counter() - t0
    signals = {k: atk.signals[k] + np.reshape(result.x[f"d{k}"], atk.signals[k].shape) for k in atk.signals}
    return signals, seconds, result.status.value, result.certificate.passed


def judge(atk: IdentificationAttack, signals: dict[str, np.ndarray]) -> tuple[float, float, bool]:
    """(||d[A B]||_2, ||d[A B]||_F^2, stealthy) of the numpy refit on the poisoned signals."""
    Y, Z = atk.regression(signals)
    d = np.linalg.lstsq(Z.T, Y.T, rcond=None)[0].T - atk.theta0
    clean, after = atk.tests(), atk.tests(signals)
    stealthy = all(abs(1 - after[k].statistic / clean[k].statistic) <= atk.stealth + 1e-6 for k in STATISTICS)
    return float(np.linalg.norm(d, 2)), float(np.sum(d ** 2)), stealthy


def main(data_sets: int = 10, T: int = 100, delta: float = 0.05) -> None:
    print(f"# bench_identification  {datetime.now(timezone.utc):%Y-%m-%d %H:%M} UTC  {platform.node()}  "
          f"{platform.processor() or platform.machine()}  cores={os.cpu_count()}  python {platform.python_version()}")
    print(f"ident-ss, T = {T}, budgets and stealth delta = {delta}; engine {ENGINES}; baseline SLSQP, 100 iterations, "
          f"exact gradients, start at {START_SCALE} x the budget radii\n")
    problems, first = {}, {}
    for name, options in ENGINES.items():
        t0 = time.perf_counter()
        problems[name] = declare(attack_instance("ss", T=T, eps=delta, stealth=delta, seed=0))
        problems[name].solve(**options, seed=0)
        first[name] = time.perf_counter() - t0
    head = " | ".join(f"{name + ' |dAB|_2':>16} {'s':>6} {'ok':>3}" for name in (*ENGINES, "SLSQP"))
    print(f"{'seed':>4} | {head}   (ok: stealthy by the defender's tests, and for the engine solved and certified)")
    rows = []
    for seed in range(data_sets):
        atk = attack_instance("ss", T=T, eps=delta, stealth=delta, seed=seed)
        row = []
        for name, options in ENGINES.items():
            signals, seconds, status, cert = engine(problems[name], atk, options)
            norm2, _, stealthy = judge(atk, signals)
            row.append((norm2, seconds, stealthy and cert and status == "solved"))
        signals, seconds = slsqp(atk, seed, start_scale=START_SCALE)
        norm2, _, stealthy = judge(atk, signals)
        row.append((norm2, seconds, stealthy))
        rows.append(row)
        print(f"{seed:4d} | " + " | ".join(f"{v:16.4f} {t:6.2f} {'yes' if ok else 'no':>3}" for v, t, ok in row),
              flush=True)
    r = np.array(rows, dtype=float)  # data set x method x (norm, seconds, ok)
    base = r[:, -1]
    print()
    for i, name in enumerate(ENGINES):
        e = r[:, i]
        reach = np.mean((e[:, 2] == 1) & ((e[:, 0] >= base[:, 0] * (1 - 1e-6)) | (base[:, 2] == 0)))
        print(f"engine {name}: ok on {int(e[:, 2].sum())}/{len(e)}; ok and ||d[A B]||_2 >= SLSQP's (or SLSQP not "
              f"stealthy) on {reach:.0%}; median ||d[A B]||_2 {np.median(e[:, 0]):.4f} (SLSQP {np.median(base[:, 0]):.4f}, "
              f"stealthy {int(base[:, 2].sum())}/{len(base)}); median time {np.median(e[:, 1]):.2f} s per data set "
              f"(load_instance + solve; declaration, preparation and first solve {first[name]:.2f} s once), SLSQP "
              f"{np.median(base[:, 1]):.2f} s: median SLSQP/engine time ratio {np.median(base[:, 1] / e[:, 1]):.1f}x, "
              f"total time ratio {base[:, 1].sum() / (e[:, 1].sum() + first[name]):.1f}x with the first solve counted")


if __name__ == "__main__":
    main(*(int(a) if i < 2 else float(a) for i, a in enumerate(sys.argv[1:])))
