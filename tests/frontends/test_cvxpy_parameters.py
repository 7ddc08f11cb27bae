"""Unbound cvxpy Parameters become model parameters: new data re-solve the declared problem without rebuilding."""

from __future__ import annotations

import casadi as ca
import cvxpy as cp
import numpy as np
import pytest

import bilevel as bl
from bilevel.solvers.engine.prepared import prepare


def data(seed: int) -> tuple[np.ndarray, ...]:
    rng = np.random.default_rng(seed)
    xtr, xval, truth = rng.standard_normal((30, 8)), rng.standard_normal((20, 8)), rng.standard_normal(8)
    return xtr, xtr @ truth + rng.standard_normal(30), xval, xval @ truth + rng.standard_normal(20)


def declare(xtr: np.ndarray, ytr: np.ndarray, xval: np.ndarray, yval: np.ndarray):
    """Ridge with the training data as unbound cvxpy Parameters and the validation data as model parameters."""
    a, b = cp.Parameter(xtr.shape, name="Xtr", value=xtr), cp.Parameter(ytr.size, name="ytr", value=ytr)
    lam, w = cp.Parameter(nonneg=True), cp.Variable(xtr.shape[1])
    p = bl.BilevelProblem("ridge")
    l = p.upper_variable("l", lb=1e-3, ub=100.0, start=1.0)
    xv, yv = p.parameter("Xval", xval.shape, xval), p.parameter("yval", yval.size, yval)
    ll = p.lower_cvxpy(cp.Problem(cp.Minimize(cp.sum_squares(a @ w - b) + lam * cp.sum_squares(w))),
                       parameters={lam: l})
    p.minimize_upper(ca.sumsqr(ca.mtimes(xv, ll[w]) - yv))
    return p, ll, a, b


def test_new_data_reuse_the_declaration_and_match_a_fresh_one() -> None:
    p, ll, a, b = declare(*data(0))
    assert ll.parameter_name(a) == "cvxpy_Xtr"
    first = p.solve(method="hypergradient")
    prepared = prepare(p)
    for seed in (1, 2):
        xtr, ytr, xval, yval = data(seed)
        ll.set_value(a, xtr)
        ll.set_value(b, ytr)
        p.set_value("Xval", xval)
        p.set_value("yval", yval)
        again = p.solve(method="hypergradient")
        assert prepare(p) is prepared  # no re-canonicalization
        fresh = declare(xtr, ytr, xval, yval)[0].solve(method="hypergradient")
        assert again.status is bl.Status.SOLVED and again.certificate.passed, again.message
        assert again.upper_objective == pytest.approx(fresh.upper_objective, rel=1e-9, abs=1e-9)
        assert again.x["l"] == pytest.approx(fresh.x["l"], rel=1e-6)
        assert again.upper_objective != pytest.approx(first.upper_objective)
    assert np.array_equal(a.value, data(2)[0])


def test_set_value_of_a_bound_parameter_is_refused() -> None:
    p, ll, a, _ = declare(*data(0))
    with pytest.raises(bl.ModelError, match="not an unbound Parameter"):
        ll.set_value(cp.Parameter(), 1.0)
