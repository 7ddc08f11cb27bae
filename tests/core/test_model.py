"""Declaration errors: each bad input raises a narrow exception that names the problem."""

from __future__ import annotations

import casadi as ca
import numpy as np
import pytest

import bilevel as bl
from bilevel.solvers.engine.prepared import prepare


def _base() -> tuple[bl.BilevelProblem, ca.SX, ca.SX]:
    p = bl.BilevelProblem()
    x = p.upper_variable("x", 2, lb=0, ub=1)
    y = p.lower_variable("y", 2)
    return p, x, y


def test_bound_shape_mismatch_names_variable() -> None:
    p = bl.BilevelProblem()
    with pytest.raises(bl.ModelError, match="'x'.*3 entries"):
        p.upper_variable("x", 2, lb=[0, 0, 0])


def test_nan_bound_and_crossed_bounds() -> None:
    p = bl.BilevelProblem()
    with pytest.raises(bl.ModelError, match="NaN"):
        p.upper_variable("x", 1, lb=np.nan)
    with pytest.raises(bl.ModelError, match="exceeds"):
        p.upper_variable("z", 1, lb=2, ub=1)


def test_duplicate_and_invalid_names() -> None:
    p = bl.BilevelProblem()
    p.upper_variable("x")
    with pytest.raises(bl.ModelError, match="already declared"):
        p.lower_variable("x")
    with pytest.raises(bl.ModelError, match="identifier"):
        p.lower_variable("1y")


def test_constraint_must_be_a_comparison() -> None:
    p, x, y = _base()
    with pytest.raises(bl.ModelError, match="not a comparison"):
        p.lower_constraint(y[0] + x[0])
    with pytest.raises(bl.ModelError, match="no variables"):
        p.lower_constraint(ca.SX(1) <= 2)
    with pytest.raises(bl.ModelError, match="CasADi comparison"):
        p.upper_constraint(True)


def test_objective_must_be_scalar() -> None:
    p, x, y = _base()
    with pytest.raises(bl.ModelError, match="scalar"):
        p.minimize_upper(x)


def test_missing_objectives_and_lower_variables() -> None:
    p, x, y = _base()
    p.minimize_lower(ca.sumsqr(y - x))
    with pytest.raises(bl.ModelError, match="no upper objective"):
        prepare(p)
    q = bl.BilevelProblem()
    u = q.upper_variable("u")
    q.minimize_upper(u ** 2)
    with pytest.raises(bl.ModelError, match="no lower objective"):
        prepare(q)


def test_lower_objective_must_depend_on_lower_variables() -> None:
    p, x, y = _base()
    p.minimize_upper(ca.sumsqr(y))
    p.minimize_lower(ca.sumsqr(x))
    p.lower_constraint(y[0] <= 1)
    with pytest.raises(bl.ModelError, match="does not depend on the lower variables"):
        prepare(p)


def test_indefinite_lower_quadratic_is_rejected() -> None:
    p, x, y = _base()
    p.minimize_upper(ca.sumsqr(y))
    p.minimize_lower(y[0] ** 2 - y[1] ** 2 + ca.dot(x, y))
    with pytest.raises(bl.NonConvexLowerLevel, match="eigenvalue"):
        prepare(p)


def test_concave_lower_minimization_rejected_but_maximization_accepted() -> None:
    p, x, y = _base()
    p.minimize_upper(ca.sumsqr(y))
    p.minimize_lower(-ca.sumsqr(y - x))
    with pytest.raises(bl.NonConvexLowerLevel):
        prepare(p)
    q, x, y = _base()
    q.minimize_upper(ca.sumsqr(y))
    q.maximize_lower(-ca.sumsqr(y - x))
    assert prepare(q).canon.lower.kind == "least-squares"


def test_nonconvex_nlp_constraint_rejected() -> None:
    p, x, y = _base()
    p.minimize_upper(ca.sumsqr(y))
    p.minimize_lower(ca.sumsqr(y - x))
    p.lower_constraint(-y[0] ** 2 - y[1] ** 2 <= -1)  # outside of a disc: non-convex set
    with pytest.raises(bl.NonConvexLowerLevel, match="constraint"):
        prepare(p)


def test_nonaffine_lower_equality_rejected() -> None:
    p, x, y = _base()
    p.minimize_upper(ca.sumsqr(y))
    p.minimize_lower(ca.sumsqr(y - x))
    p.lower_constraint(y[0] ** 2 == x[0])
    with pytest.raises(bl.NonConvexLowerLevel, match="affine"):
        prepare(p)


def test_foreign_symbol_and_upper_only_lower_constraint() -> None:
    p, x, y = _base()
    z = ca.SX.sym("z")
    p.minimize_upper(ca.sumsqr(y) + z)
    p.minimize_lower(ca.sumsqr(y - x))
    with pytest.raises(bl.ModelError, match="not variables declared"):
        prepare(p)
    q, x, y = _base()
    q.minimize_upper(ca.sumsqr(y))
    q.minimize_lower(ca.sumsqr(y - x))
    q.lower_constraint(x[0] <= 1)
    with pytest.raises(bl.ModelError, match="upper_constraint"):
        prepare(q)


@pytest.mark.parametrize(
    "build, kind",
    [
        (lambda p, x, y: p.minimize_lower(ca.sumsqr(y - x)), "least-squares"),
        (lambda p, x, y: (p.minimize_lower(ca.sumsqr(y - x)), p.lower_constraint(y[0] <= 0.5)), "qp"),
        (lambda p, x, y: (p.minimize_lower(y[0] + y[1]), p.lower_constraint(y >= x)), "lp"),
        (lambda p, x, y: (p.minimize_lower(ca.exp(y[0]) + y[1] ** 2 - ca.dot(x, y))), "nlp"),
    ],
)
def test_lower_level_kind_is_classified(build, kind) -> None:
    p, x, y = _base()
    p.minimize_upper(ca.sumsqr(y))
    build(p, x, y)
    assert prepare(p).canon.lower.kind == kind
