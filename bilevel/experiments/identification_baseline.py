"""The SLSQP baseline of the stealthy identification attack, and the defender's verdict on any poisoned data.

Baseline: the attack program of bilevel.problems.identification (learner "ss", stealth) reduced to the attacker's
variables with the learner in closed form, [A B](x) = Y Z'(Z Z')^-1 (the input test's restricted fit likewise), as
CasADi expressions differentiated exactly; scipy SLSQP from a seeded point at START_SCALE times each budget radius,
maxiter 100. The verdict (judge) refits the poisoned data with numpy and runs bilevel.ddc.residual_tests on it.
"""

from __future__ import annotations

import time
from typing import Any

import casadi as ca
import numpy as np
from scipy.optimize import minimize

from ..problems.identification import STATISTICS, statistics
from ..problems.identification_instance import IdentificationAttack, least_squares_fit, ss_regression

START_SCALE = 0.1
"""SLSQP starts at a random point at this fraction of each budget radius, inside the stealth constraints (from the
budget spheres themselves it ends infeasible after 100 iterations on 19 of 20 data sets, T = 100, delta = 0.05)."""
SLSQP_ITERATIONS = 100
STEALTH_SLACK = 1e-6
"""judge calls a statistic stealthy when |1 - stat'/stat| <= delta + STEALTH_SLACK (solver tolerance)."""


def closed_form(Y: ca.SX, Z: ca.SX) -> ca.SX:
    """argmin_Theta ||Y - Theta Z||_F^2 = Y Z' (Z Z')^-1 as an expression."""
    return ca.solve(ca.mtimes(Z, Z.T), ca.mtimes(Z, Y.T)).T


def slsqp_attack(atk: IdentificationAttack, seed: int, maxiter: int = SLSQP_ITERATIONS,
                 start_scale: float = START_SCALE) -> tuple[dict[str, np.ndarray], float, int]:
    """The baseline's poisoned signals, its wall time (s, expressions built and compiled included) and iterations."""
    if atk.learner != "ss" or atk.stealth is None:
        raise ValueError(f"the SLSQP baseline attacks the stealthy state-space learner, got learner {atk.learner!r}, "
                         f"stealth {atk.stealth}")
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
    x0 = np.concatenate([start_scale * atk.radius(k) * (v := rng.standard_normal(atk.signals[k].size))
                         / np.linalg.norm(v) for k in ("X", "U")])
    res = minimize(lambda v: tuple(np.array(o).ravel() for o in fun(v)), x0, jac=True, method="SLSQP",
                   constraints={"type": "ineq", "fun": lambda v: np.array(con(v)[0]).ravel(),
                                "jac": lambda v: np.array(con(v)[1])},
                   options={"maxiter": maxiter, "ftol": 1e-12})
    nX = X.size
    signals = {"X": X + res.x[:nX].reshape(X.shape, order="F"), "U": U + res.x[nX:].reshape(U.shape, order="F")}
    return signals, time.perf_counter() - t0, int(res.nit)


def judge(atk: IdentificationAttack, signals: dict[str, np.ndarray]) -> dict[str, Any]:
    """The defender's view of poisoned signals, from a numpy refit: ||d[A B]||_2 and _F, the data change relative to
    each signal, each test (statistic, p-value) before and after, the residual norm ||E||_F before and after, the
    largest |1 - stat'/stat| and whether it is within the stealth level (None without stealth)."""
    Y, Z = atk.regression(signals)
    d = least_squares_fit(Y, Z) - atk.theta0
    before, after = atk.tests(), atk.tests(signals)
    change = max(abs(1 - after[k].statistic / before[k].statistic) for k in STATISTICS)
    sigma = atk.setting.noise_std
    return {"norm2": float(np.linalg.norm(d, 2)), "frobenius": float(np.linalg.norm(d)),
            "budget_used": {k: float(np.linalg.norm(signals[k] - atk.signals[k]) / np.linalg.norm(atk.signals[k]))
                            for k in atk.signals},
            "max_relative_change": float(change),
            "stealthy": None if atk.stealth is None else bool(change <= atk.stealth + STEALTH_SLACK),
            "residual_norm": {"before": sigma * float(np.sqrt(before["variance"].statistic)),
                              "after": sigma * float(np.sqrt(after["variance"].statistic))},
            **{when: {k: {"statistic": t.statistic, "p_value": t.p_value} for k, t in ts.items()}
               for when, ts in (("before", before), ("after", after))}}
