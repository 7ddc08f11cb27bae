"""Random LP, SOCP and SDP lower levels in cvxpy with a known upper optimum: the certificate passes, 0 is reached.

Construction: x0 inside the upper box, w0 = the user's lower solution at x0 (an independent cvxpy solve); the upper
objective ||x - x0||^2 + ||w - w0||^2 is >= 0 and 0 exactly at x0, where the (generically unique) lower solution
is w0. So the global upper optimum is 0 at x = x0.
"""

from __future__ import annotations

from typing import Callable

import casadi as ca
import cvxpy as cp
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

import bilevel as bl

N_X = 2


def lp(rng: np.random.Generator) -> tuple[cp.Problem, cp.Variable, cp.Parameter, Callable[[ca.SX], ca.SX]]:
    """min c'y s.t. A y <= b0 + B x, |y| <= 5 (y = 0 strictly feasible for |x| <= 1)."""
    ny, m = 3, 6
    y, b = cp.Variable(ny), cp.Parameter(m)
    a, b0, bx = rng.standard_normal((m, ny)), rng.uniform(1.0, 2.0, m), 0.3 * rng.standard_normal((m, N_X))
    problem = cp.Problem(cp.Minimize(rng.standard_normal(ny) @ y), [a @ y <= b, cp.abs(y) <= 5])
    return problem, y, b, lambda x: ca.DM(b0) + ca.mtimes(ca.DM(bx), x)


def socp(rng: np.random.Generator) -> tuple[cp.Problem, cp.Variable, cp.Parameter, Callable[[ca.SX], ca.SX]]:
    """min c'y s.t. ||G y - center(x)|| <= 1, center affine in x: a unique point on an ellipsoid."""
    ny = 3
    y, center = cp.Variable(ny), cp.Parameter(ny)
    g = np.eye(ny) + 0.3 * rng.standard_normal((ny, ny))
    c0, cx = rng.standard_normal(ny), rng.standard_normal((ny, N_X))
    problem = cp.Problem(cp.Minimize(rng.standard_normal(ny) @ y), [cp.norm(g @ y - center, 2) <= 1])
    return problem, y, center, lambda x: ca.DM(c0) + ca.mtimes(ca.DM(cx), x)


def sdp(rng: np.random.Generator) -> tuple[cp.Problem, cp.Variable, cp.Parameter, Callable[[ca.SX], ca.SX]]:
    """min <C(x), Y> s.t. tr Y = 1, Y >= 0: Y = v v' for the bottom eigenvector of C(x) (eigengap kept > 0)."""
    def sym(scale: float) -> np.ndarray:
        m = scale * rng.standard_normal((3, 3))
        return (m + m.T) / 2

    c0, c1, c2 = np.diag([0.0, 1.5, 3.0]) + sym(0.1), sym(0.15), sym(0.15)
    y, c = cp.Variable((3, 3), symmetric=True), cp.Parameter((3, 3))
    problem = cp.Problem(cp.Minimize(cp.trace(c @ y)), [cp.trace(y) == 1, y >> 0])
    return problem, y, c, lambda x: ca.DM(c0) + x[0] * ca.DM(c1) + x[1] * ca.DM(c2)


def known_optimum(kind: Callable, seed: int) -> tuple[bl.BilevelProblem, np.ndarray]:
    rng = np.random.default_rng(seed)
    learner, w, param, bind = kind(rng)
    x0 = rng.uniform(-0.5, 0.5, N_X)
    param.value = np.asarray(ca.evalf(bind(ca.DM(x0)))).reshape(param.shape, order="F")
    learner.solve(solver=cp.CLARABEL)
    w0 = np.asarray(w.value)
    p = bl.BilevelProblem(f"random-{kind.__name__}")
    x = p.upper_variable("x", N_X, lb=-1, ub=1)
    ll = p.lower_cvxpy(learner, parameters={param: ca.reshape(bind(x), *(param.shape + (1,))[:2])})
    p.minimize_upper(ca.sumsqr(x - x0) + ca.sumsqr(ll[w] - ca.DM(w0.reshape(ll[w].shape, order="F"))))
    return p, x0


@pytest.mark.parametrize("kind", [lp, socp, sdp])
@given(seed=st.integers(0, 2**31 - 1))
@settings(max_examples=4, deadline=None, derandomize=True)
def test_random_conic_lower_level_reaches_the_known_optimum(kind: Callable, seed: int) -> None:
    p, x0 = known_optimum(kind, seed)
    res = p.solve(method="hypergradient", starts=4, seed=0)
    assert res.certificate.passed, res.certificate
    assert res.upper_objective <= 1e-8, (res.upper_objective, res.x, x0)
    assert np.max(np.abs(res.x["x"] - x0)) <= 1e-4
