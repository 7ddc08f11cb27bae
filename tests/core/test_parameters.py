"""Model parameters: declare once, set_value, re-solve without rebuilding; same answers as a fresh declaration."""

from __future__ import annotations

import casadi as ca
import numpy as np
import pytest
from hypothesis import given, settings, strategies as st

import bilevel as bl
from bilevel.solvers.engine.prepared import prepare


def _projection_qp(target: ca.SX | np.ndarray, rhs: ca.SX | float, p: bl.BilevelProblem | None = None
                   ) -> bl.BilevelProblem:
    """tests/conftest.py's projection QP with its data (target, constraint right-hand side) as given."""
    p = p or bl.BilevelProblem("projection-qp")
    x = p.upper_variable("x", 2, lb=-5, ub=5)
    y = p.lower_variable("y", 2)
    p.minimize_upper(ca.sumsqr(y - target) + 0.1 * ca.sumsqr(x))
    p.minimize_lower(ca.sumsqr(y - x))
    p.lower_constraint(y[0] + y[1] <= rhs)
    return p


def _declared() -> bl.BilevelProblem:
    p = bl.BilevelProblem("projection-qp")
    return _projection_qp(p.parameter("target", 2), p.parameter("rhs"), p)


@settings(max_examples=6, deadline=None)
@given(st.lists(st.floats(-3, 3), min_size=2, max_size=2), st.floats(-2, 2))
def test_set_value_equals_a_fresh_declaration(target: list[float], rhs: float) -> None:
    p = _declared()
    p.set_value("target", [0.0, 0.0])
    p.set_value("rhs", 1.0)
    p.solve(method="ipopt", starts=1)  # a first solve with other values: its preparation is reused below
    p.set_value("target", target)
    p.set_value("rhs", rhs)
    fresh = _projection_qp(ca.DM(target), rhs)
    for method in ("ipopt", "hypergradient", "relaxation", "global"):
        a, b = p.solve(method=method, starts=2, seed=1), fresh.solve(method=method, starts=2, seed=1)
        assert a.status == b.status
        assert a.upper_objective == pytest.approx(b.upper_objective, rel=1e-8, abs=1e-10)
        np.testing.assert_allclose(a.x["x"], b.x["x"], atol=1e-7)
        assert a.certificate.passed


def test_preparation_is_reused_until_a_declaration_changes() -> None:
    p = _declared()
    p.set_value("target", [1.0, 2.0])
    p.set_value("rhs", 1.0)
    first = prepare(p)
    p.set_value("rhs", 0.5)
    assert prepare(p) is first
    p.upper_constraint(p.variables[0].sym[0] <= 4)
    assert prepare(p) is not first


def test_ball_radius_and_fixed_lower_level_follow_the_values() -> None:
    """max ||y||^2 with y = x over ||x|| <= r: optimum r^2 (block-exact and hypergradient); a lower level that
    ignores x, y* = c, under min (x - y)^2: x* = c."""
    p = bl.BilevelProblem("ball")
    r = p.parameter("r", value=1.0)
    x = p.upper_variable("x", 3)
    y = p.lower_variable("y", 3)
    p.maximize_upper(ca.sumsqr(y))
    p.minimize_lower(ca.sumsqr(y - x))
    p.upper_constraint(ca.sumsqr(x) <= r ** 2)
    for radius in (1.0, 2.5, 0.3):
        p.set_value("r", radius)
        for method in ("block-exact", "hypergradient"):
            res = p.solve(method=method, starts=2)  # the declared start x = 0 is stationary; a second one is not
            assert res.status is bl.Status.SOLVED
            assert res.upper_objective == pytest.approx(radius ** 2, rel=1e-6)
    q = bl.BilevelProblem("fixed")
    c = q.parameter("c", value=1.0)
    x = q.upper_variable("x", lb=-10, ub=10)
    y = q.lower_variable("y")
    q.minimize_upper((x - y) ** 2)
    q.minimize_lower((y - c) ** 2)
    for value in (1.0, -3.0, 7.5):
        q.set_value("c", value)
        res = q.solve(method="hypergradient", starts=1)
        assert res.x["x"] == pytest.approx(value, abs=1e-6) and res.y["y"] == pytest.approx(value, abs=1e-8)


def test_parameter_errors_name_the_problem() -> None:
    p = _declared()
    with pytest.raises(bl.ModelError, match="'target'.*no value"):
        p.solve()
    with pytest.raises(bl.ModelError, match="shape"):
        p.set_value("target", [1.0, 2.0, 3.0])
    with pytest.raises(bl.InvalidData, match="NaN"):
        p.set_value("rhs", np.nan)
    with pytest.raises(bl.ModelError, match="no parameter named 'rsh'.*target, rhs"):
        p.set_value("rsh", 1.0)
    with pytest.raises(bl.ModelError, match="already declared"):
        p.parameter("x")
    m = bl.BilevelProblem()
    m.parameter("A", (2, 3), value=np.arange(6.0).reshape(2, 3))
    assert m.parameters.value.tolist() == [0.0, 3.0, 1.0, 4.0, 2.0, 5.0]  # column-major, like variables


def test_undeclared_symbol_still_rejected() -> None:
    p = bl.BilevelProblem()
    x = p.upper_variable("x")
    y = p.lower_variable("y")
    stray = ca.SX.sym("stray")
    p.minimize_upper((x - y) ** 2)
    p.minimize_lower((y - stray) ** 2)
    with pytest.raises(bl.ModelError, match="stray.*not variables"):
        p.solve()
