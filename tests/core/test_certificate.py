"""The certificate passes on solved points and fails when the point is perturbed (it can fail)."""

from __future__ import annotations

import dataclasses

import casadi as ca
import numpy as np
import pytest

import bilevel as bl
from bilevel.certificate import certify_point
from bilevel.solvers.engine.prepared import prepare
from tests.conftest import bard_511, projection_qp


def _solved_point(problem: bl.BilevelProblem):
    prep = prepare(problem)
    res = bl.solve(problem, starts=4)
    assert res.certificate is not None and res.certificate.passed
    w = prep.pack(prep.lower_point(np.concatenate([np.ravel(v) for v in res.x.values()])))
    return prep, prep.point(w), res


def test_certificate_passes_at_projection_qp_optimum() -> None:
    """Analytic optimum: x = y = (1/22, 21/22), F = 2.0954545... (Lagrange on y0 + y1 = 1)."""
    res = projection_qp().solve(starts=4)
    assert res.status is bl.Status.SOLVED
    np.testing.assert_allclose(res.x["x"], [1 / 22, 21 / 22], atol=1e-6)
    assert res.upper_objective == pytest.approx(2.0954545454545, abs=1e-8)
    c = res.certificate
    assert c.passed and c.stationarity < 1e-8 and c.complementarity < 1e-8 and abs(c.lower_gap) < 1e-7


@pytest.mark.parametrize("field, delta, failing", [
    ("y", 0.05, "lower_gap"),
    ("lam", 0.3, "stationarity"),
])
def test_perturbed_point_fails_certificate(field: str, delta: float, failing: str) -> None:
    prep, point, _ = _solved_point(bard_511())
    assert certify_point(prep.canon, point).passed
    bad = dataclasses.replace(point, **{field: getattr(point, field) + delta})
    cert = certify_point(prep.canon, bad)
    assert not cert.passed and failing in cert.failed


def test_negative_multiplier_and_upper_infeasibility_fail() -> None:
    prep, point, _ = _solved_point(bard_511())
    cert = certify_point(prep.canon, dataclasses.replace(point, lam=point.lam - 1.0))
    assert "dual_feasibility" in cert.failed
    cert = certify_point(prep.canon, dataclasses.replace(point, x=np.array([-1.0])))
    assert "upper_feasibility" in cert.failed


def test_infeasible_lower_level_gives_a_failed_certificate_with_a_note() -> None:
    p = bl.BilevelProblem()
    x = p.upper_variable("x", lb=-3, ub=3)
    y = p.lower_variable("y", lb=0, ub=1)
    p.minimize_upper((x - 2) ** 2)
    p.minimize_lower(y)
    p.lower_constraint(y >= x)  # infeasible when x > 1
    prep = prepare(p)
    with pytest.raises(bl.LowerLevelInfeasible):
        prep.canon.lower.solve(np.array([2.0]))
    point = prep.point(np.concatenate([[2.0], [1.0], np.zeros(3)]))
    cert = certify_point(prep.canon, point)
    assert not cert.passed and "infeasible" in cert.note
    res = p.solve(starts=4)  # the leader must stay where the follower is feasible: x = 1
    assert res.success and res.x["x"] == pytest.approx(1.0, abs=1e-6)


def test_unbounded_lower_level_is_reported() -> None:
    p = bl.BilevelProblem()
    x = p.upper_variable("x", lb=0, ub=1)
    y = p.lower_variable("y")
    p.minimize_upper(x)
    p.minimize_lower(-y)
    p.lower_constraint(y >= x)
    with pytest.raises(bl.LowerLevelUnbounded):
        prepare(p).canon.lower.solve(np.array([0.5]))


def test_nlp_lower_certificate_uses_ipopt_on_plain_problem() -> None:
    p = bl.BilevelProblem()
    x = p.upper_variable("x", lb=-2, ub=2)
    y = p.lower_variable("y", 2)
    p.minimize_upper((x - 1) ** 2 + ca.sumsqr(y))
    p.minimize_lower(ca.exp(y[0]) + y[1] ** 2 - x * y[0])
    p.lower_constraint(y[0] ** 2 + y[1] ** 2 <= 1)
    res = p.solve(starts=3)
    assert res.success and "ipopt" in res.certificate.lower_solver


def test_upper_objective_y_matches_hand_computed_values() -> None:
    """projection_qp: F = |y - (1, 2)|^2 + 0.1 |x|^2, grad_y F = 2 (y - (1, 2)), the certificate's F at the re-solved
    y equal to its upper_at_reference there."""
    prep = prepare(projection_qp())
    x, y = np.array([0.3, -0.4]), np.array([0.2, 0.5])
    F, grad = prep.canon.upper_objective_y(x, y)
    assert F == pytest.approx(0.8 ** 2 + 1.5 ** 2 + 0.1 * 0.25, abs=1e-12)
    np.testing.assert_allclose(grad, [-1.6, -3.0], atol=1e-12)
    res = projection_qp().solve(starts=4)
    c = res.certificate
    y_ref = np.array(c.lower_reference_y)
    assert c.upper_at_reference == pytest.approx(float(np.sum((y_ref - [1, 2]) ** 2)) + 0.1 * float(
        np.sum(np.asarray(res.x["x"]) ** 2)), abs=1e-9)


def test_certificate_quotes_a_maximized_objective_in_its_own_sign() -> None:
    """max y with y = argmin (y - x)^2, x = 2: a point whose y is off by 0.5 fails on lower_solution, and the
    message quotes F at the re-solved y as the user declared it, +2 (not the canonical -2)."""
    from bilevel.reduction import KKTPoint
    p = bl.BilevelProblem("max-sign")
    x = p.upper_variable("x", lb=2, ub=2)
    y = p.lower_variable("y")
    p.maximize_upper(y)
    p.minimize_lower((y - x) ** 2)
    canon = prepare(p).canon
    point = KKTPoint(np.array([2.0]), np.array([2.5]), np.zeros(0), np.zeros(0), [])
    cert = certify_point(canon, point, sense="max")
    assert "lower_solution" in cert.failed
    assert "F there = 2" in cert.describe_failures()
