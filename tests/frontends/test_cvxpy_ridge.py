"""The cvxpy front end on ridge regression: a least-squares learner stays least squares, every method agrees."""

from __future__ import annotations

import casadi as ca
import cvxpy as cp
import numpy as np
import pytest

import bilevel as bl
from bilevel.solvers.engine.prepared import prepare


def ridge(seed: int = 0) -> tuple[bl.BilevelProblem, float]:
    """Validation-loss hyperparameter choice for ridge on 40 x 20 data; returns the problem and the grid optimum."""
    rng = np.random.default_rng(seed)
    xtr, xval = rng.standard_normal((40, 20)), rng.standard_normal((30, 20))
    truth = rng.standard_normal(20)
    ytr, yval = xtr @ truth + 2 * rng.standard_normal(40), xval @ truth + 2 * rng.standard_normal(30)
    lam, w = cp.Parameter(nonneg=True), cp.Variable(20)
    learner = cp.Problem(cp.Minimize(cp.sum_squares(xtr @ w - ytr) + lam * cp.sum_squares(w)))
    p = bl.BilevelProblem("ridge")
    l = p.upper_variable("l", lb=0, start=1.0)
    ll = p.lower_cvxpy(learner, parameters={lam: l})
    p.minimize_upper(ca.sumsqr(ca.mtimes(ca.DM(xval), ll[w]) - yval))
    grid = np.logspace(-3, 3, 3001)
    best = min(np.sum((xval @ np.linalg.solve(xtr.T @ xtr + a * np.eye(20), xtr.T @ ytr) - yval) ** 2) for a in grid)
    return p, float(best)


def test_ridge_is_least_squares_after_translation() -> None:
    p, _ = ridge()
    assert prepare(p).canon.lower.kind == "least-squares"


@pytest.mark.parametrize("method", ["hypergradient", "ipopt", "relaxation"])
def test_ridge_every_method_reaches_the_grid_optimum_with_a_certificate(method: str) -> None:
    p, best = ridge()
    res = p.solve(method=method)
    assert res.status is bl.Status.SOLVED, res.message
    assert res.certificate.passed and "user's problem" in res.certificate.lower_solver
    assert res.upper_objective <= best + 1e-9
