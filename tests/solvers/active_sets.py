"""Brute-force optimistic optimum of a random linear bilevel program by enumerating lower-level active sets.

Independent of bilevel's solvers: for every subset S of the lower constraints (including the box on y), the
points where S is active and the lower cost d + Cx lies in the cone of the active normals (KKT, which is
necessary and sufficient for an LP) form a polyhedron in (x, y, lam_S); the upper objective is minimized over
it (scipy linprog, or cvxpy + Clarabel with the quadratic upper term). The best over all S is the optimistic
bilevel optimum, ties in the follower's response included (Bard 1998, Practical Bilevel Optimization, ch. 5).
"""

from __future__ import annotations

import itertools

import cvxpy as cp
import numpy as np
from scipy.optimize import linprog

from bilevel.problems.random_linear import LinearBilevelData


def lower_rows(data: LinearBilevelData) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(Ay, Ax, rhs) with every lower constraint written Ay y + Ax x <= rhs (box rows included)."""
    n_x, n_y, _ = data.shape
    eye = np.eye(n_y)
    Ay = np.vstack([data.A, -eye, eye])
    Ax = np.vstack([data.B, np.zeros((2 * n_y, n_x))])
    rhs = np.concatenate([data.b, np.zeros(n_y), np.full(n_y, data.y_max)])
    return Ay, Ax, rhs


def _piece(data: LinearBilevelData, S: tuple[int, ...]) -> float:
    """min of the upper objective over points whose lower active set contains S and whose cost is in cone(S)."""
    n_x, n_y, _ = data.shape
    Ay, Ax, rhs = lower_rows(data)
    k = len(S)
    n = n_x + n_y + k
    A_ub = np.hstack([Ax, Ay, np.zeros((rhs.size, k))])
    S_idx = list(S)
    A_eq = np.vstack([np.hstack([Ax[S_idx], Ay[S_idx], np.zeros((k, k))]),
                      np.hstack([data.C, np.zeros((n_y, n_y)), Ay[S_idx].T])])
    b_eq = np.concatenate([rhs[S_idx], -data.d])
    bounds = [(0.0, 1.0)] * n_x + [(None, None)] * n_y + [(0.0, None)] * k
    if not np.any(data.u):
        res = linprog(np.concatenate([data.c_x, data.c_y, np.zeros(k)]), A_ub=A_ub, b_ub=rhs, A_eq=A_eq, b_eq=b_eq,
                      bounds=bounds, method="highs")
        return float(res.fun) if res.status == 0 else np.inf
    v = cp.Variable(n)
    x = v[:n_x]
    objective = data.c_x @ x + data.c_y @ v[n_x:n_x + n_y] + 0.5 * cp.sum(cp.multiply(data.u, cp.square(x - data.x0)))
    cons = [A_ub @ v <= rhs, A_eq @ v == b_eq, x >= 0, x <= 1]
    if k:
        cons.append(v[n_x + n_y:] >= 0)
    prob = cp.Problem(cp.Minimize(objective), cons)
    prob.solve(solver=cp.CLARABEL, tol_gap_abs=1e-10, tol_gap_rel=1e-10, tol_feas=1e-10)
    return float(prob.value) if prob.status in (cp.OPTIMAL, cp.OPTIMAL_INACCURATE) else np.inf


def active_set_optimum(data: LinearBilevelData) -> float:
    """The optimistic bilevel optimum (inf if infeasible): the best piece over all subsets of lower constraints."""
    m_total = lower_rows(data)[2].size
    best = np.inf
    for size in range(m_total + 1):
        for S in itertools.combinations(range(m_total), size):
            best = min(best, _piece(data, S))
    return best
