"""Expression lower levels that are matrix QPs take lower_qp's path (bilevel.lower.qp_form); the rest do not."""

from __future__ import annotations

import casadi as ca
import numpy as np
import pytest

import bilevel as bl
from bilevel.errors import NonConvexLowerLevel
from bilevel.lower import LinearLower, QuadraticLower
from bilevel.lower.matrix import MatrixLower
from bilevel.problems.rhs_lp import rhs_lp, rhs_lp_data
from bilevel.solvers.engine.prepared import prepare

M, N, DELTA = 300, 30, 0.2


@pytest.fixture
def small_matrices():
    """Small lower levels recognized too (classify.matrix_min_entries keeps them on the expression kinds)."""
    bl.set_defaults("classify", matrix_min_entries=1)
    yield
    bl.reset_defaults()


def _lp_data() -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """bench_scale's right-hand-side attack at 300 rows x 30 variables (bilevel.problems.rhs_lp)."""
    return rhs_lp_data(M, N)


def _lp(form: str) -> bl.BilevelProblem:
    """The leader moves the right-hand sides within [-0.2, 0.2] to raise the follower's optimal cost c'y."""
    return rhs_lp(M, N, form, DELTA)


@pytest.mark.parametrize("form", ["vector", "rows"])
def test_expression_lp_is_the_matrix_lp_and_solves_like_lower_qp(form: str) -> None:
    """300 rows x 30 variables declared by expressions (360 x 30 entries with the bounds, above
    classify.matrix_min_entries): the same A, b(x) and kind as lower_qp's, read exactly, and hypergradient ends at the
    same point with the same objective as on the lower_qp declaration."""
    A, b, c = _lp_data()
    low = prepare(p := _lp(form)).canon.lower
    ref = prepare(q := _lp("lower_qp")).canon.lower
    assert isinstance(low, MatrixLower) and low.kind == ref.kind == "lp"
    np.testing.assert_array_equal(low.A, ref.A)  # [A; -I; I], each entry as the expression computes it
    np.testing.assert_array_equal(low.A[:M], A)
    assert low.E.shape == (0, N) and not np.any(low.P)
    x0 = np.random.default_rng(1).uniform(-DELTA, DELTA, M)
    for mine, theirs, want in zip(low.vectors(x0), ref.vectors(x0), (None, c, np.concatenate([b + x0, np.ones(2 * N)]),
                                                                     None)):
        np.testing.assert_allclose(mine, theirs, rtol=1e-15, atol=0)
        if want is not None:
            np.testing.assert_allclose(mine, want, rtol=1e-15, atol=0)
    res, base = p.solve("hypergradient", starts=1), q.solve("hypergradient", starts=1)
    assert res.status is base.status is bl.Status.SOLVED
    np.testing.assert_allclose(res.x["x"], base.x["x"], atol=1e-12)
    assert res.upper_objective == pytest.approx(base.upper_objective, rel=1e-12)
    if form == "rows":
        assert set(res.multipliers) >= {"row0", f"row{M - 1}", "y.lb", "y.ub"}


def _qp(shift: float = 0.0) -> bl.BilevelProblem:
    """A strictly convex QP with a term constant in y (|x|^2 + shift), x-dependent linear term, an equality and
    bounds; the lower level maximizes the negated objective."""
    p = bl.BilevelProblem("qp-form")
    x = p.upper_variable("x", 2, lb=-1, ub=1)
    y = p.lower_variable("y", 3, lb=-2, ub=2)
    Q = np.array([[2.0, 0.5, 0.0], [0.5, 1.0, 0.2], [0.0, 0.2, 3.0]])
    f = 0.5 * ca.mtimes([y.T, ca.DM(Q), y]) - ca.dot(ca.vertcat(x, x[0] * x[1]), y) + ca.sumsqr(x) + shift
    p.maximize_lower(-f)
    p.lower_constraint(y[0] + 2 * y[1] - y[2] == 0.5 * x[0])
    p.lower_constraint(y[0] - y[1] <= 1 + x[1] ** 2)
    p.minimize_upper(ca.sumsqr(y - ca.DM([1.0, -1.0, 0.5])) + 0.1 * ca.sumsqr(x))
    return p


def test_quadratic_form_reproduces_the_expressions(small_matrices) -> None:
    """P, the x-dependent q, b, e and the constant term r(x) of the recognized QP give the expressions' f, g, h at
    random points; the solve agrees with the expression kinds' Clarabel solve there."""
    prep = prepare(p := _qp(shift=3.0))
    low = prep.canon.lower
    assert isinstance(low, MatrixLower) and low.kind == "qp"
    np.testing.assert_allclose(low.P, [[2.0, 0.5, 0.0], [0.5, 1.0, 0.2], [0.0, 0.2, 3.0]], rtol=1e-15)
    canon = prep.canon
    exprs = ca.Function("fgh", [canon.x, canon.y], [canon.f, canon.g, canon.h])
    rng = np.random.default_rng(3)
    for _ in range(5):
        xs, ys = rng.uniform(-1, 1, 2), rng.uniform(-2, 2, 3)
        f, g, h, _ = low.evaluate(xs, ys)
        want = [np.asarray(v, dtype=float).ravel() for v in exprs(xs, ys)]
        assert f == pytest.approx(float(want[0][0]), rel=1e-13)
        np.testing.assert_allclose(g, want[1], rtol=1e-13, atol=1e-14)
        np.testing.assert_allclose(h, want[2], rtol=1e-13, atol=1e-14)
    expression = QuadraticLower(canon.x, canon.y, canon.f, canon.g, canon.h, [], low.g_names, low.h_names, [])
    xs = np.array([0.3, -0.7])
    mine, theirs = low.solve(xs), expression.solve(xs)
    np.testing.assert_allclose(mine.y, theirs.y, atol=1e-8)
    assert mine.objective == pytest.approx(theirs.objective, rel=1e-9)
    res = p.solve("hypergradient", starts=2)
    assert res.status is bl.Status.SOLVED and res.certificate.passed
    f_declared = -float(np.asarray(exprs(res.x["x"], res.y["y"])[0]).ravel()[0])  # canon.f is -(the declared -f)
    assert res.lower_objective == pytest.approx(f_declared, rel=1e-12)


def test_parameters_in_the_data_are_read_at_their_current_values(small_matrices) -> None:
    """b may hold parameters (re-set without rebuilding); A may not: a parameter in a coefficient of y keeps the
    expression kinds."""
    p = bl.BilevelProblem("param-rhs")
    x = p.upper_variable("x", 1, lb=0, ub=1)
    y = p.lower_variable("y", 2, lb=0)
    t = p.parameter("t", 1, value=1.0)
    p.minimize_lower(-y[0] - y[1])
    p.lower_constraint(y[0] + y[1] <= t + x)
    p.minimize_upper(-y[0] - y[1] + x)
    low = prepare(p).canon.lower
    assert isinstance(low, MatrixLower)
    assert low.solve(np.array([0.5])).objective == pytest.approx(-1.5, abs=1e-9)
    p.set_value("t", 2.0)
    assert prepare(p).canon.lower.solve(np.array([0.5])).objective == pytest.approx(-2.5, abs=1e-9)
    q = bl.BilevelProblem("param-coefficient")
    x = q.upper_variable("x", 1, lb=0, ub=1)
    y = q.lower_variable("y", 2, lb=0)
    t = q.parameter("t", 1, value=1.0)
    q.minimize_lower(-y[0] - y[1])
    q.lower_constraint(t * y[0] + y[1] <= 1 + x)
    q.minimize_upper(x)
    assert isinstance(prepare(q).canon.lower, LinearLower)


@pytest.mark.parametrize("constraint", [
    lambda x, y: x[0] * y[0] + y[1] <= 1,  # a coefficient of y moves with x
    lambda x, y: ca.floor(y[0]) + y[1] <= 1,  # depends on y where its derivative (0) does not show it
    lambda x, y: ca.floor(y[0]) + y[0] + y[1] <= 1,  # the same, with a linear term in y[0]: caught at the samples
    lambda x, y: ca.fmod(y[0], 1.0) + y[1] <= 1,  # derivative 1, not affine: caught at the samples
])
def test_not_a_matrix_qp_keeps_the_expression_kinds(constraint, small_matrices) -> None:
    """A constraint that is not affine in y with numeric coefficients is never read as a matrix."""
    p = bl.BilevelProblem()
    x = p.upper_variable("x", 1, lb=0.5, ub=1)
    y = p.lower_variable("y", 2, lb=-3, ub=3)
    p.minimize_lower(y[0] + y[1])
    p.lower_constraint(constraint(x, y))
    p.minimize_upper(x)
    assert not isinstance(prepare(p).canon.lower, MatrixLower)


def test_non_convex_quadratic_is_still_refused(small_matrices) -> None:
    """An indefinite constant Hessian is not taken as a matrix QP: the expression kinds name the eigenvalue."""
    p = bl.BilevelProblem()
    x = p.upper_variable("x", 1, lb=0, ub=1)
    y = p.lower_variable("y", 2, lb=-1, ub=1)
    p.minimize_lower(y[0] ** 2 - y[1] ** 2 + x * y[0])
    p.minimize_upper(x)
    with pytest.raises(NonConvexLowerLevel, match="eigenvalue -2"):
        prepare(p)


def test_small_lower_levels_keep_the_expression_kinds() -> None:
    """Below classify.matrix_min_entries (Bard's 5.1.1: 5 rows x 1 variable) the expression kinds solve, as before."""
    p = bl.BilevelProblem()
    x = p.upper_variable("x", 1, lb=0)
    y = p.lower_variable("y", 1, lb=0)
    p.minimize_upper(x - 4 * y)
    p.minimize_lower(y)
    for c in (-x - y <= -3, -2 * x + y <= 0, 2 * x + y <= 12, 3 * x - 2 * y <= 4):
        p.lower_constraint(c)
    assert isinstance(prepare(p).canon.lower, LinearLower)
