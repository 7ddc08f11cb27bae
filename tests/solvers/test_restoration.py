"""Restoration of an upper point onto the upper feasible set along y*(x) (bilevel.solvers.engine.restoration), on
least-squares learners y*(x) = x whose feasible sets and Gauss-Newton iterates are known in closed form."""

from __future__ import annotations

import casadi as ca
import numpy as np
import pytest

import bilevel as bl
from bilevel.solvers.engine.prepared import prepare
from bilevel.solvers.engine.implicit import shared_oracle
from bilevel.solvers.engine.restoration import restore


def _copying_learner(n: int) -> tuple[bl.BilevelProblem, ca.SX]:
    p = bl.BilevelProblem("copy")
    x = p.upper_variable("x", n, lb=-10, ub=10)
    y = p.lower_variable("y", n)
    p.minimize_lower(ca.sumsqr(y - x))
    p.maximize_upper(ca.sum1(y))
    return p, y


def _restore(p: bl.BilevelProblem, x0: np.ndarray):
    prep = prepare(p)
    return restore(shared_oracle(prep), x0, prep.projection)


def test_a_point_outside_a_ball_on_the_lower_solution_is_restored_along_its_ray() -> None:
    """||y||^2 <= 1 with y = x: the minimum-norm step of Newton on ||x||^2 = 1 stays on the ray of x0 and converges to
    x0 / ||x0|| (x_{k+1} = (x_k + 1/x_k) / 2 along it)."""
    p, y = _copying_learner(3)
    p.upper_constraint(ca.sumsqr(y) <= 1)
    x0 = np.array([3.0, 0.0, 4.0])
    ev = _restore(p, x0)
    assert ev is not None and ev.violation <= 1e-6
    np.testing.assert_allclose(ev.x, x0 / 5.0, atol=1e-6)
    np.testing.assert_allclose(ev.lower.y, ev.x, atol=1e-12)


def test_a_linear_equality_on_the_lower_solution_is_met_by_the_projection_in_one_step() -> None:
    """y0 + y1 = 1 with y = x: from 0 the minimum-norm correction is (1/2, 1/2)."""
    p, y = _copying_learner(2)
    p.upper_constraint(y[0] + y[1] == 1)
    ev = _restore(p, np.zeros(2))
    assert ev is not None
    np.testing.assert_allclose(ev.x, [0.5, 0.5], atol=1e-12)


def test_a_feasible_point_is_kept_and_an_overshooting_newton_step_ends_the_restoration() -> None:
    """atan(y) = 0 with y = x: from x = 2 Newton jumps to 2 - 5 atan(2) = -3.54, where |atan| = 1.30 > atan(2) / 2:
    no contraction, so None; from x = 0.5 it converges to 0."""
    p, y = _copying_learner(1)
    p.upper_constraint(ca.atan(y) == 0)
    assert _restore(p, np.array([2.0])) is None
    ev = _restore(p, np.array([0.5]))
    assert ev is not None and ev.x[0] == pytest.approx(0.0, abs=1e-6)
    kept = _restore(p, np.array([0.0]))
    assert kept is not None and kept.x[0] == 0.0
