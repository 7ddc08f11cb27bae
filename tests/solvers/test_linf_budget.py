"""An l_inf budget written as `norm_inf(a - c) <= r` is read as the box it is (issue 50): projected onto exactly by
hypergradient, a box for reduced, and `auto` picks hypergradient for it."""

import casadi as ca
import numpy as np
import pytest

import bilevel as bl
from bilevel.solvers.engine.prepared import prepare
from bilevel.solvers.engine.structure import find_balls

C = np.linspace(-1.0, 1.0, 6)


def _problem(row) -> bl.BilevelProblem:
    """max sum(y) + ||y||^2 / 2 with y = c + a (least squares), a in an l_inf ball: every a_i = 0.1 + 0.3 at the
    optimum since each y_i = c_i + a_i >= -0.9 > -1 there (the objective grows with y_i above -1)."""
    p = bl.BilevelProblem("linf")
    a = p.upper_variable("a", C.size)
    y = p.lower_variable("y", C.size)
    p.maximize_upper(ca.sum1(y) + 0.5 * ca.sumsqr(y))
    p.minimize_lower(ca.sumsqr(y - C - a))
    p.upper_constraint(row(a))
    return p


OPTIMUM = float(np.sum(C + 0.4) + 0.5 * np.sum((C + 0.4) ** 2))


def test_norm_inf_row_is_an_linf_ball() -> None:
    balls = find_balls(prepare(_problem(lambda a: ca.norm_inf(a - 0.1) <= 0.3)).canon)
    assert len(balls) == 1 and balls[0].norm == np.inf and balls[0].block == slice(0, C.size)
    np.testing.assert_allclose(balls[0].center, 0.1, rtol=0, atol=1e-15)
    assert balls[0].radius == pytest.approx(0.3, rel=1e-15)
    point = balls[0].sphere_point(np.random.default_rng(0))
    assert np.max(np.abs(point - 0.1)) == pytest.approx(0.3, rel=1e-12)


@pytest.mark.parametrize("row", [lambda a: ca.norm_inf(2 * a) <= 0.3,  # slope 2: not the unit-coefficient form
                                 lambda a: ca.fmax(ca.fabs(a[0]), ca.fabs(a[2])) <= 0.3,  # not a contiguous block
                                 lambda a: ca.norm_inf(a[0] + a[1]) <= 0.3])  # one entry reads two variables
def test_other_max_rows_are_not_balls(row) -> None:
    assert find_balls(prepare(_problem(row)).canon) == []


@pytest.mark.parametrize("method", ["auto", "hypergradient", "reduced"])
def test_linf_budget_solved_exactly(method: str) -> None:
    res = bl.solve(_problem(lambda a: ca.norm_inf(a - 0.1) <= 0.3), method=method)
    assert res.status is bl.Status.SOLVED and res.certificate.passed
    assert res.upper_objective == pytest.approx(OPTIMUM, rel=1e-6)  # IPOPT (reduced) relaxes bounds by ~1e-8
    np.testing.assert_allclose(res.x["a"], 0.4, atol=1e-6)
    if method == "auto":
        assert res.method == "hypergradient" and "l_inf" in res.message
