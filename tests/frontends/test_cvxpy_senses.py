"""A maximizing cvxpy learner equals the minimizing one, and objectives are reported in the learner's own sense."""

from __future__ import annotations

import cvxpy as cp
import pytest

import bilevel as bl


@pytest.mark.parametrize("sense", ["min", "max"])
@pytest.mark.parametrize("method", ["hypergradient", "ipopt"])
def test_max_learner_equals_min_learner(sense: str, method: str) -> None:
    """min (x - 1)^2 + (y + 1)^2 with y = x + 1 (the learner's optimum, inside y <= 2): x = -1/2, value 4.5."""
    p = bl.BilevelProblem(f"sense-{sense}")
    x = p.upper_variable("x", lb=-2, ub=2, start=1.0)
    a, y = cp.Parameter(), cp.Variable()
    fit = cp.square(y - a - 1) + 3
    learner = cp.Problem(cp.Minimize(fit) if sense == "min" else cp.Maximize(-fit), [y <= 2])
    ll = p.lower_cvxpy(learner, parameters={a: x})
    p.minimize_upper((x - 1) ** 2 + (ll[y] + 1) ** 2)
    res = p.solve(method=method)
    assert res.status is bl.Status.SOLVED and res.certificate.passed, res.message
    assert res.x["x"] == pytest.approx(-0.5, abs=1e-6)
    assert res.upper_objective == pytest.approx(4.5, abs=1e-8)
    assert res.lower_objective == pytest.approx(3.0 if sense == "min" else -3.0, abs=1e-8)
