"""Issue 44 item 5: a result's objective is the one its returned x gets from the lower level, whatever the status.
`defense-vrft-iv` at its defaults drives cond(Z'Phi) to about 1e8, where the least-squares lower level's normal
equations (Hessian (Z'Phi)'(Z'Phi), cond 1e16) keep no digit of theta: the result was certificate_failed with the
spectral radius 79.4 (seed 0) / 87.5 (seed 1) of a theta the IV learner does not give (an independent re-fit: 48.7 /
42.4), and the certificate's re-solve, the same normal equations, gave a negative sum of squares."""

from __future__ import annotations

import casadi as ca
import numpy as np
import pytest

import bilevel as bl
from bilevel.problems import registry
from bilevel.problems.defended_vrft import defended_instance
from bilevel.reduction import KKTPoint
from bilevel.result import Status
from bilevel.solvers.engine.prepared import MethodRun, prepare


def numpy_radius(seed: int, x: dict[str, np.ndarray]) -> float:
    """The spectral radius of the attacker's model loop under the IV learner refitted by numpy at the poisoning x."""
    d = defended_instance("iv", seed=seed)
    reg = d.atk.setting.regressor
    phi, t, Z = reg(d.atk.y + x["a_y"]), reg.targets(d.atk.u + x["a_u"]), reg(d.y2 + x["a_y2"])
    theta = np.linalg.solve(Z.T @ phi, Z.T @ t)
    loop = d.atk.model_loop
    coeffs = loop.base + loop.slopes.T @ theta
    companion = np.vstack([-coeffs[1:] / coeffs[0], np.eye(coeffs.size - 2, coeffs.size - 1)])
    return float(np.max(np.abs(np.linalg.eigvals(companion))))


@pytest.mark.parametrize("seed", [0, 1])
def test_iv_attack_objective_is_the_iv_learners_at_the_returned_poisoning(seed: int) -> None:
    result = bl.solve(registry.get("defense-vrft-iv", seed=seed))
    x = {k: np.asarray(v, dtype=float) for k, v in result.x.items()}
    assert result.upper_objective == pytest.approx(numpy_radius(seed, x), rel=1e-5), result.status


def test_least_squares_reference_solve_does_not_square_the_condition_number() -> None:
    """min ||A(x) y - b||^2 with cond(A(1)) = 1e8 (well conditioned where the lower level is classified): the
    certificate's re-solve at x = 1 is numpy's lstsq, its value >= 0; the closed form's normal equations are not."""
    rng = np.random.default_rng(0)
    U, _ = np.linalg.qr(rng.standard_normal((6, 6)))
    V, _ = np.linalg.qr(rng.standard_normal((6, 6)))
    b = rng.standard_normal(6)
    p = bl.BilevelProblem()
    x = p.upper_variable("x", lb=0, ub=2)
    y = p.lower_variable("y", 6)
    scales = ca.vertcat(ca.DM.ones(5), 1 - x * (1 - 1e-8))
    A = ca.mtimes([ca.DM(U), ca.diag(scales), ca.DM(V.T)])
    p.minimize_upper(ca.sumsqr(y))
    p.minimize_lower(ca.sumsqr(ca.mtimes(A, y) - ca.DM(b)))
    low = prepare(p).canon.lower
    A1 = U @ np.diag([1, 1, 1, 1, 1, 1e-8]) @ V.T
    exact = np.linalg.lstsq(A1, b, rcond=None)[0]
    sol, closed = low.reference_solve(np.array([1.0])), low.solve(np.array([1.0]))
    assert np.linalg.norm(sol.y - exact) <= 1e-6 * np.linalg.norm(exact)
    assert 0 <= sol.objective <= 1e-12
    assert np.linalg.norm(closed.y - exact) > 1e-3 * np.linalg.norm(exact)  # what the re-solve was before


@pytest.mark.parametrize("y_method", [(1.0, 1.0), (0.0, 0.0)])
def test_a_failed_certificate_reports_the_objective_at_a_lower_solution_of_x(y_method: tuple[float, float]) -> None:
    """A method (a callable) returns x = 0.5 with a y that is not a lower solution there (suboptimal, infeasible) of an
    LP whose solution set is the segment y1 + y2 = x, y >= 0 (so the certificate's uniqueness check does not apply):
    certificate_failed, and the result's y is a lower solution at x with the objective F = 2 y1 + y2 there (the
    method's y and objective in stats)."""
    p = bl.BilevelProblem()
    x = p.upper_variable("x", lb=0, ub=1)
    y = p.lower_variable("y", 2, lb=0)
    p.minimize_upper(2 * y[0] + y[1])
    p.minimize_lower(y[0] + y[1])
    p.lower_constraint(y[0] + y[1] >= x)

    def method(prep, **options) -> MethodRun:
        w = prep.pack(KKTPoint(np.array([0.5]), np.array(y_method), np.zeros(3), np.zeros(0), []))
        return MethodRun(w, Status.SOLVED, "a wrong y", 1)

    result = bl.solve(p, method=method)
    y_result = np.asarray(result.y["y"], dtype=float)
    assert result.status.value == "certificate_failed"
    assert y_result.sum() == pytest.approx(0.5, abs=1e-7) and y_result.min() >= -1e-8
    assert result.upper_objective == pytest.approx(2 * y_result[0] + y_result[1], abs=1e-12)
    assert result.stats["method_upper_objective"] == pytest.approx(2 * y_method[0] + y_method[1])
