"""A DeePC learner declared as a user would, through lower_cvxpy, attacked by poisoning its output data.

The learner (Coulson, Lygeros & Doerfler 2019): min_{g, u, y, s} sum (y_k - r)^2 + R sum u_k^2 + lambda_g ||g||^2
+ lambda_y ||s||_1 s.t. Up g = u_ini, Yp g = y_ini + s, Uf g = u, Yf g = y, with Up, Uf, Yp, Yf the depth-L Hankel
matrices of the recorded input/output data as cvxpy Parameters; the output ones are bound to the poisoned data
y_d + dy, the attacker changing ATTACKED samples within an l_inf budget |dy_t| <= eps. The attacker maximizes the
true plant's tracking cost of the planned inputs (the plant's response from the same past, an affine map of u).

Every applicable method runs on it (time, objective, status) and the default; the best objective is the reference.
Usage: python benchmarks/bench_deepc.py > benchmarks/results/bench_deepc.txt
"""

from __future__ import annotations

import os
import platform
import time
from datetime import datetime, timezone

import casadi as ca
import control
import cvxpy as cp
import numpy as np

import bilevel as bl
from bilevel.ddc import simulate

T, ATTACKED, T_INI, HORIZON = 200, 80, 4, 10
LAMBDA_G, LAMBDA_Y, R_WEIGHT, REFERENCE = 1e-1, 1e3, 1e-2, 1.0
PLANT = control.tf([0.1, 0.05], [1.0, -1.5, 0.7], True)


def hankel(signal: ca.SX, depth: int) -> ca.SX:
    """The depth x (n - depth + 1) Hankel matrix of a column signal."""
    n = int(signal.numel())
    return ca.horzcat(*[signal[j:j + depth] for j in range(n - depth + 1)])


def deepc_problem(eps_fraction: float = 0.1, seed: int = 0) -> bl.BilevelProblem:
    """The attacked DeePC learner: T recorded samples, the first ATTACKED outputs poisoned, |dy| <= eps."""
    rng = np.random.default_rng(seed)
    u_d = rng.standard_normal(T)
    y_d = simulate(PLANT, u_d)
    past_u = rng.standard_normal(30)
    past_y = simulate(PLANT, past_u)
    u_ini, y_ini = past_u[-T_INI:], past_y[-T_INI:]
    depth, cols = T_INI + HORIZON, T - T_INI - HORIZON + 1
    free = simulate(PLANT, np.concatenate([past_u, np.zeros(HORIZON)]))[-HORIZON:]  # the plant's own future
    step = np.column_stack([simulate(PLANT, np.concatenate([np.zeros(30), np.eye(HORIZON)[k]]))[-HORIZON:]
                            for k in range(HORIZON)])
    eps = eps_fraction * float(np.std(y_d))

    Hu = cp.Parameter((depth, cols), name="Hu", value=np.array(hankel(ca.DM(u_d), depth)))
    Hy = cp.Parameter((depth, cols), name="Hy")
    g, u, y, s = cp.Variable(cols), cp.Variable(HORIZON), cp.Variable(HORIZON), cp.Variable(T_INI)
    learner = cp.Problem(cp.Minimize(cp.sum_squares(y - REFERENCE) + R_WEIGHT * cp.sum_squares(u)
                                     + LAMBDA_G * cp.sum_squares(g) + LAMBDA_Y * cp.norm1(s)),
                         [Hu[:T_INI] @ g == u_ini, Hy[:T_INI] @ g == y_ini + s,
                          Hu[T_INI:] @ g == u, Hy[T_INI:] @ g == y])
    p = bl.BilevelProblem("deepc")
    dy = p.upper_variable("dy", ATTACKED, lb=-eps, ub=eps)
    poisoned = ca.DM(y_d) + ca.vertcat(dy, ca.DM.zeros(T - ATTACKED))
    ll = p.lower_cvxpy(learner, parameters={Hy: hankel(poisoned, depth)})
    plan = ll[u]
    p.maximize_upper(ca.sumsqr(ca.DM(free) + ca.mtimes(ca.DM(step), plan) - REFERENCE))
    return p
