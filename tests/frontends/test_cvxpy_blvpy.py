"""BLVPY's published examples re-declared with lower_cvxpy, each solved to the value BLVPY documents or better.

Source: github.com/dxogrp/blvpy, examples/analytic_quadratic.py (optimum 2 at x = y = 0),
examples/parameter_dependent_socp.py (x* ~ 1.265084, objective ~ 0.062240), examples/ridge_hyperparameter.py
(the selected penalty beats lambda = 1 on validation MSE by more than 0.1), examples/optimistic_lp.py (a lower
level with a constant objective: rejected here, see the last test). Plus Bard (1998) Example 5.1.1 by cvxpy
and method="global".
"""

from __future__ import annotations

import casadi as ca
import cvxpy as cp
import numpy as np
import pytest

import bilevel as bl


def analytic_quadratic() -> bl.BilevelProblem:
    """min (x-1)^2 + (y+1)^2, y in argmin_z (z - x)^2: y = x, optimum 2 at x = y = 0."""
    p = bl.BilevelProblem("blvpy-analytic-quadratic")
    x = p.upper_variable("x", lb=-2, ub=2, start=1.5)
    a, z = cp.Parameter(), cp.Variable()
    ll = p.lower_cvxpy(cp.Problem(cp.Minimize(cp.square(z - a))), parameters={a: x})
    p.minimize_upper((x - 1) ** 2 + (ll[z] + 1) ** 2)
    return p


def parameter_dependent_socp() -> tuple[bl.BilevelProblem, bl.frontends.CvxpyLower, cp.Variable, cp.Variable]:
    """min (x - 1.25)^2 + 0.1 t, 0.5 <= x <= 2, (y, t) in argmin { t : ||y|| <= t, x y_1 + y_2 >= 1 }."""
    p = bl.BilevelProblem("blvpy-parameter-dependent-socp")
    x = p.upper_variable("x", lb=0.5, ub=2.0, start=1.0)
    a, y, t = cp.Parameter(), cp.Variable(2), cp.Variable()
    learner = cp.Problem(cp.Minimize(t), [cp.norm(y, 2) <= t, a * y[0] + y[1] >= 1.0])
    ll = p.lower_cvxpy(learner, parameters={a: x})
    p.minimize_upper((x - 1.25) ** 2 + 0.1 * ll[t])
    return p, ll, y, t


@pytest.mark.parametrize("method", ["hypergradient", "ipopt"])
def test_analytic_quadratic_reaches_two(method: str) -> None:
    res = analytic_quadratic().solve(method=method)
    assert res.status is bl.Status.SOLVED and res.certificate.passed, res.message
    assert res.upper_objective == pytest.approx(2.0, abs=1e-8)
    assert res.x["x"] == pytest.approx(0.0, abs=1e-6)


@pytest.mark.parametrize("method", ["hypergradient", "ipopt", "relaxation"])
def test_parameter_dependent_socp_matches_blvpy_reference(method: str) -> None:
    p, ll, y, t = parameter_dependent_socp()
    res = p.solve(method=method)
    assert res.status is bl.Status.SOLVED and res.certificate.passed, res.message
    ref_x = 1.265084110259083  # BLVPY's reference; phi(x*) ~ 0.062240
    assert res.x["x"] == pytest.approx(ref_x, abs=1e-6)
    assert res.upper_objective <= (ref_x - 1.25) ** 2 + 0.1 / np.hypot(ref_x, 1.0) + 1e-9
    direction = np.array([ref_x, 1.0])
    assert np.asarray(res.value(ll[y])).ravel() == pytest.approx(direction / direction.dot(direction), abs=1e-6)


def test_ridge_hyperparameter_beats_the_lambda_one_baseline() -> None:
    rng = np.random.default_rng(1907)
    w_true = np.array([1.6, -1.2, 0.8, 0.0, -0.5, 0.35, 0.0, 0.6])
    x_tr, x_val = rng.normal(size=(24, 8)), rng.normal(size=(80, 8))
    scale = np.std(x_tr, axis=0)
    x_tr, x_val = x_tr / scale, x_val / scale
    y_tr = x_tr @ w_true + rng.normal(scale=1.1, size=24)
    y_val = x_val @ w_true + rng.normal(scale=0.25, size=80)
    lbd, w = cp.Parameter(nonneg=True), cp.Variable(8)
    learner = cp.Problem(cp.Minimize(cp.sum_squares(x_tr @ w - y_tr) / 24 + lbd * cp.sum_squares(w)))
    p = bl.BilevelProblem("blvpy-ridge")
    lam = p.upper_variable("lam", lb=1e-4, ub=10.0, start=1.0)
    ll = p.lower_cvxpy(learner, parameters={lbd: lam})
    p.minimize_upper(ca.sumsqr(ca.mtimes(ca.DM(x_val), ll[w]) - y_val) / 80)
    res = p.solve(method="hypergradient")
    assert res.status is bl.Status.SOLVED and res.certificate.passed, res.message

    def mse(value: float) -> float:
        fit = np.linalg.solve(x_tr.T @ x_tr / 24 + value * np.eye(8), x_tr.T @ y_tr / 24)
        return float(np.mean((x_val @ fit - y_val) ** 2))

    assert res.upper_objective < mse(1.0) - 0.1
    assert res.upper_objective <= min(mse(v) for v in np.geomspace(1e-4, 10.0, 2001)) + 1e-9


def test_bard_lp_by_cvxpy_is_proven_by_the_global_method() -> None:
    """Bard (1998) Example 5.1.1 with the lower LP in cvxpy: global optimum -12 at x = 4, y = 4."""
    p = bl.BilevelProblem("bard-cvxpy")
    x = p.upper_variable("x", lb=0, ub=10)
    a, y = cp.Parameter(), cp.Variable(nonneg=True)
    learner = cp.Problem(cp.Minimize(y), [-a - y <= -3, -2 * a + y <= 0, 2 * a + y <= 12, 3 * a - 2 * y <= 4])
    ll = p.lower_cvxpy(learner, parameters={a: x})
    p.minimize_upper(x - 4 * ll[y])
    res = p.solve(method="global")
    assert res.status is bl.Status.SOLVED and res.certificate.passed, res.message
    assert res.certificate.global_bound.proven
    assert res.upper_objective == pytest.approx(-12.0, abs=1e-7)


def test_optimistic_lp_constant_lower_objective_is_rejected_clearly() -> None:
    """BLVPY's optimistic LP has lower objective 0; the core requires one that depends on the lower variables."""
    p = bl.BilevelProblem("blvpy-optimistic-lp")
    x = p.upper_variable("x", lb=0, ub=1)
    a, y = cp.Parameter(), cp.Variable()
    ll = p.lower_cvxpy(cp.Problem(cp.Minimize(0 * y), [y >= a, y <= 1.0]), parameters={a: x})
    p.minimize_upper(x ** 2 + (ll[y] - 1) ** 2)
    with pytest.raises(bl.ModelError, match="does not depend on the lower variables"):
        p.solve()
