"""The translated lower level is the cvxpy problem: at a fixed upper point, the engine's own lower solve gives the
cvxpy optimal value and the user's variables (ll[v]) for atoms that produce every supported cone."""

from __future__ import annotations

import warnings

import casadi as ca
import cvxpy as cp
import numpy as np
import pytest

import bilevel as bl
from bilevel.lower.quadratic import solve_clarabel
from bilevel.solvers.engine.prepared import prepare


def multi_soc(a: cp.Parameter) -> tuple[cp.Problem, list[cp.Variable]]:
    z, t = cp.Variable((3, 4)), cp.Variable(4)
    return cp.Problem(cp.Minimize(cp.sum(t) + cp.sum_squares(z[:, 0] - a)),
                      [cp.norm(z, 2, axis=0) <= t, z[0, :] >= 0.1 + a[0]]), [z, t]


def lasso(a: cp.Parameter) -> tuple[cp.Problem, list[cp.Variable]]:
    w = cp.Variable(3)
    return cp.Problem(cp.Minimize(cp.sum_squares(w - a) + 0.3 * cp.norm1(w))), [w]


def hinge(a: cp.Parameter) -> tuple[cp.Problem, list[cp.Variable]]:
    w = cp.Variable(3)
    return cp.Problem(cp.Minimize(cp.sum(cp.pos(1 - cp.multiply(a, w))) + cp.sum_squares(w))), [w]


def huber(a: cp.Parameter) -> tuple[cp.Problem, list[cp.Variable]]:
    w = cp.Variable(3)
    return cp.Problem(cp.Minimize(cp.sum(cp.huber(w - a, 0.5)) + 0.1 * cp.sum_squares(w))), [w]


def symmetric_lmi(a: cp.Parameter) -> tuple[cp.Problem, list[cp.Variable]]:
    x = cp.Variable((3, 3), symmetric=True)
    return cp.Problem(cp.Minimize(cp.trace(x) + cp.sum_squares(cp.diag(x) - a)),
                      [x >> 0.1 * np.ones((3, 3)), x[0, 1] == a[1]]), [x]


def psd_variable(a: cp.Parameter) -> tuple[cp.Problem, list[cp.Variable]]:
    x = cp.Variable((3, 3), PSD=True)
    return cp.Problem(cp.Minimize(cp.sum_squares(x - cp.diag(a)))), [x]


def bounded_variable(a: cp.Parameter) -> tuple[cp.Problem, list[cp.Variable]]:
    w = cp.Variable(3, bounds=[-0.5, 0.5])
    return cp.Problem(cp.Minimize(cp.sum_squares(w - a))), [w]


def lambda_max(a: cp.Parameter) -> tuple[cp.Problem, list[cp.Variable]]:
    m = cp.Variable((2, 2), symmetric=True)
    return cp.Problem(cp.Minimize(cp.lambda_max(m) + cp.sum_squares(cp.vec(m, order="F") - cp.hstack([a, a[0]])))), [m]


@pytest.mark.parametrize("make", [multi_soc, lasso, hinge, huber, symmetric_lmi, psd_variable, bounded_variable,
                                  lambda_max])
def test_engine_lower_solve_is_the_cvxpy_solution(make) -> None:
    a = cp.Parameter(3)
    learner, variables = make(a)
    p = bl.BilevelProblem(make.__name__)
    x = p.upper_variable("x", 3)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        ll = p.lower_cvxpy(learner, parameters={a: x})
    p.minimize_upper(ca.sumsqr(x))
    prep = prepare(p)
    point = np.array([0.9, -0.2, -0.7])
    lower = prep.lower_point(point)
    value = prep.canon.lower.evaluate(lower.x, lower.y)[0]
    a.value = point
    solve_clarabel(learner, make.__name__)
    assert value == pytest.approx(learner.value, abs=1e-7 * (1 + abs(learner.value)))
    for v in variables:
        ours = np.asarray(ca.evalf(ca.substitute(ll[v], prep.canon.y, ca.DM(lower.y))))
        assert np.max(np.abs(ours.ravel(order="F") - np.asarray(v.value).ravel(order="F"))) <= 1e-5
