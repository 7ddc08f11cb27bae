"""Hypergradient: agreement with finite differences of the re-solved lower level, and the descent method."""

from __future__ import annotations

from typing import Callable

import casadi as ca
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

import bilevel as bl
from bilevel.solvers.engine.prepared import prepare
from bilevel.solvers.engine.block_exact import SINGULAR_LEARNER
from bilevel.solvers.engine.implicit import Hypergradient, hypergradient, row_jacobian
from bilevel.solvers.engine.projections import NormBall

FD_STEP = 1e-5


def _upper_objective(x: ca.SX, y: ca.SX) -> ca.SX:
    """A smooth, nonlinear upper objective coupling x and y."""
    return ca.sum1(ca.sin(y)) + ca.dot(x, x) * y[0] + ca.exp(0.2 * ca.sum1(x)) * ca.sumsqr(y)


def random_qp(seed: int, n_x: int, n_y: int, m: int, linear: bool) -> tuple[bl.BilevelProblem, np.ndarray,
                                                                             np.ndarray, np.ndarray]:
    """A lower QP (LP if linear) whose solution at x0 is y* with active set of size n_a, lam_A in [0.5, 2]
    and inactive slacks in [0.5, 2]: strict complementarity and LICQ (smallest singular value of A_A >= 0.3,
    redrawn until so) by construction, so the active set is stable near x0 (an LP vertex if linear).

    g(x, y) = A y + C x + 0.2 D sin(x) + b <= 0, f = 1/2 y'P(x)y + (Q x + q0)'y, P(x) = M M' + (1 + 0.1|x|^2) I.
    """
    rng = np.random.default_rng(seed)
    n_a = n_y if linear else int(rng.integers(0, min(m, n_y) + 1))
    x0, y_star = rng.uniform(-1, 1, n_x), rng.standard_normal(n_y)
    A = rng.standard_normal((m, n_y))
    while n_a and np.linalg.svd(A[:n_a], compute_uv=False).min() < 0.3:
        A = rng.standard_normal((m, n_y))
    C, D = rng.standard_normal((m, n_x)), rng.standard_normal((m, n_x))
    lam_a = rng.uniform(0.5, 2.0, n_a)
    b = -(A @ y_star + C @ x0 + 0.2 * D @ np.sin(x0))
    b[n_a:] -= rng.uniform(0.5, 2.0, m - n_a)
    M, Q = rng.standard_normal((n_y, n_y)), rng.standard_normal((n_y, n_x))
    P0 = np.zeros((n_y, n_y)) if linear else M @ M.T + (1.0 + 0.1 * x0 @ x0) * np.eye(n_y)
    q0 = -(P0 @ y_star + Q @ x0 + A[:n_a].T @ lam_a)

    p = bl.BilevelProblem(f"random-{'lp' if linear else 'qp'}-{seed}")
    x = p.upper_variable("x", n_x, start=x0)
    y = p.lower_variable("y", n_y)
    p.minimize_upper(_upper_objective(x, y))
    Px = ca.DM.zeros(n_y, n_y) if linear else ca.DM(M @ M.T) + (1.0 + 0.1 * ca.dot(x, x)) * ca.DM.eye(n_y)
    p.minimize_lower(0.5 * ca.bilin(Px, y, y) + ca.dot(ca.mtimes(ca.DM(Q), x) + ca.DM(q0), y))
    if m:
        p.lower_constraint(ca.mtimes(ca.DM(A), y) + ca.mtimes(ca.DM(C), x) + 0.2 * ca.mtimes(ca.DM(D), ca.sin(x))
                           + ca.DM(b) <= 0)
    lam = np.concatenate([lam_a, np.zeros(m - n_a)])
    return p, x0, y_star, lam


def random_least_squares(seed: int, n_x: int, n_y: int) -> tuple[bl.BilevelProblem, np.ndarray]:
    """min_y 1/2 |A(x) y - b(x)|^2 + 0.05 |y|^2 with A(x) = A0 + x_0 A1 and b(x) = b0 + B sin(x)."""
    rng = np.random.default_rng(seed)
    n_obs = n_y + 3
    A0, A1 = rng.standard_normal((n_obs, n_y)), 0.3 * rng.standard_normal((n_obs, n_y))
    b0, B = rng.standard_normal(n_obs), rng.standard_normal((n_obs, n_x))
    p = bl.BilevelProblem(f"random-ls-{seed}")
    x = p.upper_variable("x", n_x)
    y = p.lower_variable("y", n_y)
    p.minimize_upper(_upper_objective(x, y))
    residual = ca.mtimes(ca.DM(A0) + x[0] * ca.DM(A1), y) - ca.DM(b0) - ca.mtimes(ca.DM(B), ca.sin(x))
    p.minimize_lower(0.5 * ca.sumsqr(residual) + 0.05 * ca.sumsqr(y))
    return p, rng.uniform(-1, 1, n_x)


def assert_matches_central_differences(prep, x0: np.ndarray) -> np.ndarray:
    """Hypergradient vs central differences of phi, each evaluation re-solving the lower level."""
    oracle = Hypergradient(prep)
    phi, grad, _ = oracle(x0)
    fd = np.zeros_like(x0)
    for i in range(x0.size):
        e = np.zeros_like(x0)
        e[i] = FD_STEP
        fd[i] = (oracle.evaluate(x0 + e).phi - oracle.evaluate(x0 - e).phi) / (2 * FD_STEP)
    assert np.linalg.norm(grad - fd) <= 1e-6 * max(1.0, np.linalg.norm(grad)), (grad, fd)
    assert hypergradient(prep, x0)[0] == pytest.approx(phi, rel=1e-12)
    return grad


@settings(max_examples=40, deadline=None)
@given(seed=st.integers(0, 2**31 - 1), n_x=st.integers(1, 3), n_y=st.integers(1, 4), extra=st.integers(0, 3),
       linear=st.booleans())
def test_qp_and_lp_hypergradient_matches_finite_differences(seed: int, n_x: int, n_y: int, extra: int,
                                                             linear: bool) -> None:
    m = n_y + extra if linear else extra + 1
    p, x0, y_star, lam = random_qp(seed, n_x, n_y, m, linear)
    prep = prepare(p)
    assert prep.canon.lower.kind == ("lp" if linear else "qp")
    oracle = Hypergradient(prep)
    ev = oracle.evaluate(x0)
    np.testing.assert_allclose(ev.lower.y, y_star, atol=1e-9)
    np.testing.assert_allclose(ev.lower.lam, lam, atol=1e-9)
    _, degenerate, n_active = oracle.gradient(ev)
    assert not degenerate and n_active == int(np.count_nonzero(lam))
    assert_matches_central_differences(prep, x0)


@settings(max_examples=20, deadline=None)
@given(seed=st.integers(0, 2**31 - 1), n_x=st.integers(1, 3), n_y=st.integers(1, 4))
def test_least_squares_hypergradient_matches_finite_differences(seed: int, n_x: int, n_y: int) -> None:
    p, x0 = random_least_squares(seed, n_x, n_y)
    prep = prepare(p)
    assert prep.canon.lower.kind == "least-squares"
    assert_matches_central_differences(prep, x0)


def test_lp_vertex_hypergradient_is_the_closed_form() -> None:
    """min 2 y0 + y1 s.t. y0 >= x, y0 + y1 >= 2x, y1 <= 10: vertex y* = (x, x), so F = x y0 + y1^2 = 2 x^2."""
    p = bl.BilevelProblem("lp-vertex")
    x = p.upper_variable("x")
    y = p.lower_variable("y", 2)
    p.minimize_upper(x * y[0] + y[1] ** 2)
    p.minimize_lower(2 * y[0] + y[1])
    p.lower_constraint(x - y[0] <= 0)
    p.lower_constraint(2 * x - y[0] - y[1] <= 0)
    p.lower_constraint(y[1] - 10 <= 0)
    phi, grad, low = hypergradient(prepare(p), np.array([1.5]))
    np.testing.assert_allclose(low.y, [1.5, 1.5], atol=1e-12)
    np.testing.assert_allclose(low.lam, [1.0, 1.0, 0.0], atol=1e-9)
    assert phi == pytest.approx(2 * 1.5**2, rel=1e-12) and grad == pytest.approx([4 * 1.5], rel=1e-10)


def test_bard_reaches_known_optimum(bard: bl.BilevelProblem) -> None:
    """Bard (1998) Example 5.1.1: F* = -12 at (4, 4), on the boundary of the lower level's domain x <= 4."""
    res = bard.solve(method="hypergradient", starts=4, seed=0)
    assert res.status is bl.Status.SOLVED and res.certificate.passed
    assert res.upper_objective == pytest.approx(-12.0, abs=1e-8)
    assert res.x["x"] == pytest.approx(4.0, abs=1e-8) and res.y["y"] == pytest.approx(4.0, abs=1e-8)
    assert len(res.start_records) == 4
    assert set(res.history[0]) >= {"iter", "objective", "step", "grad_norm", "projected_step_norm"}


def _ball_problem(norm: float) -> tuple[bl.BilevelProblem, Callable[[np.ndarray], np.ndarray]]:
    """Upper u in R^2 (u0 >= -0.5) within a norm ball; y*(u) = (M u + t) / 1.1 from a ridge lower level."""
    M, t = np.array([[2.0, -1.0], [0.5, 1.5]]), np.array([0.3, -0.2])
    p = bl.BilevelProblem(f"ball-{norm}")
    u = p.upper_variable("u", 2, lb=[-0.5, -np.inf])
    y = p.lower_variable("y", 2)
    p.minimize_upper((y[0] - 2) ** 2 + (y[1] + 1) ** 2 + 0.5 * ca.sin(3 * u[0]) + 0.3 * u[1] ** 2)
    p.minimize_lower(0.5 * ca.sumsqr(y - ca.mtimes(ca.DM(M), u) - ca.DM(t)) + 0.05 * ca.sumsqr(y))

    def reduced(points: np.ndarray) -> np.ndarray:
        ys = (points @ M.T + t) / 1.1
        return ((ys[:, 0] - 2) ** 2 + (ys[:, 1] + 1) ** 2 + 0.5 * np.sin(3 * points[:, 0])
                + 0.3 * points[:, 1] ** 2)

    return p, reduced


def _ball_grid(norm: float, radius: float) -> np.ndarray:
    """Feasible points of {|u| <= radius, u0 >= -0.5}: a fine grid, the ball's boundary and the line u0 = -0.5."""
    g = np.linspace(-radius, radius, 801)
    grid = np.stack(np.meshgrid(g, g), -1).reshape(-1, 2)
    theta = np.linspace(0, 2 * np.pi, 200_001)
    circle = np.stack([np.cos(theta), np.sin(theta)], -1)
    circle *= radius / np.linalg.norm(circle, ord=norm, axis=1)[:, None]
    line = np.stack([np.full(20_001, -0.5), np.linspace(-radius, radius, 20_001)], -1)
    pts = np.vstack([grid, circle, line])
    return pts[(np.linalg.norm(pts, ord=norm, axis=1) <= radius + 1e-12) & (pts[:, 0] >= -0.5)]


@pytest.mark.parametrize("norm", [2, np.inf, 1])
def test_norm_ball_projection_matches_brute_force(norm: float) -> None:
    """The unconstrained optimum lies outside the ball of radius 0.6 in all three norms."""
    p, reduced = _ball_problem(norm)
    res = p.solve(method="hypergradient", projection=NormBall(0.6, norm), starts=4, seed=0)
    pts = _ball_grid(norm, 0.6)
    values = reduced(pts)
    best = int(np.argmin(values))
    u = res.x["u"]
    assert res.status is bl.Status.SOLVED
    assert np.linalg.norm(u, ord=norm) == pytest.approx(0.6, abs=1e-9) and u[0] >= -0.5 - 1e-12
    assert res.upper_objective <= values[best] + 1e-9  # no feasible grid point beats the solution
    assert res.upper_objective == pytest.approx(values[best], abs=1e-6)
    assert np.linalg.norm(u - pts[best]) <= 1e-3


def test_upper_constraint_enters_through_the_exact_penalty() -> None:
    """min (x - 3)^2 + y^2 s.t. x <= 1, y = argmin (y - x)^2: unconstrained optimum 1.5, constrained x = 1."""
    p = bl.BilevelProblem("penalty")
    x = p.upper_variable("x")
    y = p.lower_variable("y")
    p.minimize_upper((x - 3) ** 2 + y**2)
    p.minimize_lower((y - x) ** 2)
    p.upper_constraint(x <= 1)
    res = p.solve(method="hypergradient", starts=2, seed=1)
    assert res.status is bl.Status.SOLVED
    assert res.x["x"] == pytest.approx(1.0, abs=1e-6) and res.upper_objective == pytest.approx(5.0, abs=1e-5)


def test_bad_options_raise(bard: bl.BilevelProblem) -> None:
    with pytest.raises(bl.UnknownOption, match="step_size"):
        bard.solve(method="hypergradient", step_size=0.1)
    with pytest.raises(bl.ModelError, match="Projection"):
        bard.solve(method="hypergradient", projection=lambda v: v)


def test_two_sided_constraints_share_one_core_and_keep_their_jacobians() -> None:
    """lo <= e <= hi declared as two rows (and e's negation with a parameter offset) share e's derivative sweep; the
    total Jacobian of every row along y*(x) matches central differences of the re-solved rows."""
    p = bl.BilevelProblem("two-sided")
    x = p.upper_variable("x", 2)
    y = p.lower_variable("y", 2)
    c = p.parameter("c")
    p.set_value("c", 0.3)
    e = ca.sin(x[0]) * y[0] + y[1] ** 2
    p.minimize_upper(ca.sumsqr(y))
    p.minimize_lower(ca.sumsqr(y - ca.vertcat(x[0] * x[1], x[1])))
    p.upper_constraint(e <= 2)
    p.upper_constraint(e >= -1)
    p.upper_constraint(c - e <= 0)
    p.upper_constraint(ca.sumsqr(x) <= 4)
    prep = prepare(p)
    oracle = Hypergradient(prep)
    assert oracle._G_index.tolist() == [0, 0, 0, 1] and oracle._G_sign.tolist() == [1.0, -1.0, -1.0, 1.0]
    x0 = np.array([0.4, -0.7])
    ev = oracle.evaluate(x0)
    assert len(ev.upper) == 3  # values only until a derivative asks
    J = oracle.jacobian(ev)[0]
    rows = lambda xs: np.concatenate([[oracle.evaluate(xs).F], oracle.evaluate(xs).upper[1].ravel()])  # noqa: E731
    fd = np.column_stack([(rows(x0 + FD_STEP * d) - rows(x0 - FD_STEP * d)) / (2 * FD_STEP) for d in np.eye(2)])
    assert np.abs(J.T - fd).max() <= 1e-7 * max(1.0, np.abs(fd).max())


def test_rows_that_call_functions_are_differentiated_row_by_row() -> None:
    """row_jacobian of rows reading never-inlined Functions is their exact Jacobian, and its sweep runs each node's
    adjoint once, for the row that reads it (a joint reverse sweep runs every node's in every direction)."""
    v = ca.MX.sym("v", 3)
    square = ca.Function("square", [v], [ca.sumsqr(v)], {"never_inline": True})
    sine = ca.Function("sine", [v], [ca.sum1(ca.sin(v))], {"never_inline": True})
    x, c = ca.SX.sym("x", 3), ca.SX.sym("c")
    rows = ca.vertcat(square(x), c * sine(x), ca.sum1(x))
    J = ca.Function("J", [x, c], [row_jacobian(rows, x)])
    x0 = np.array([0.3, -1.2, 2.0])
    expected = np.vstack([2 * x0, 0.5 * np.cos(x0), np.ones(3)])
    np.testing.assert_allclose(np.asarray(J(x0, 0.5)), expected, rtol=1e-14, atol=1e-14)
    calls = sum(J.instruction_id(i) == ca.OP_CALL for i in range(J.n_instructions()))
    joint = ca.Function("joint", [x, c], [ca.jacobian(rows, x)])
    assert calls == 2 < sum(joint.instruction_id(i) == ca.OP_CALL for i in range(joint.n_instructions()))


def test_a_start_where_the_learner_is_singular_fails_with_its_cause() -> None:
    """min (x + 1/2)^2 over x in [0, 1] with the learner min (x y_0 - 1)^2 + (y_1 - x)^2, singular at x = 0 only: the
    conditioning start is x = 0, where the learner has no unique solution. That start is a failed start naming the
    cause (no exception from solve); the others reach the infimum 1/4 from x > 0, the learner solvable there."""
    p = bl.BilevelProblem("singular-learner")
    x = p.upper_variable("x", lb=0, ub=1, start=1.0)
    y = p.lower_variable("y", 2)
    p.minimize_upper((x + 0.5) ** 2)
    p.minimize_lower((x * y[0] - 1) ** 2 + (y[1] - x) ** 2)
    result = p.solve("hypergradient", starts=2)
    failed, other = result.start_records
    assert failed["x0"] == [0.0] and failed["status"] == "error"
    assert "rank-deficient at the poisoning reached: the attack made the learner singular" in failed["message"]
    assert failed[SINGULAR_LEARNER] and not other[SINGULAR_LEARNER]
    assert other["status"] == "solved" and 0 < result.x["x"][0] < 1e-6
    assert result.upper_objective == pytest.approx(0.25, abs=1e-6)
    assert result.y["y"][0] == pytest.approx(1 / result.x["x"][0], rel=1e-9)


def test_the_declared_conditioning_start_is_kept_for_a_re_solve_at_the_same_parameter_values() -> None:
    """The conditioning start found from the declaration is reused by a re-solve (no Hessian evaluated again) and found
    again where a parameter changed; both times it is the projected descent computed afresh."""
    from bilevel.solvers.engine import starts

    p = bl.BilevelProblem("kept-start")
    x = p.upper_variable("x", 2, lb=-2, ub=2, start=[1.0, 0.5])
    y = p.lower_variable("y", 2)
    c = p.parameter("c", value=1.0)
    p.minimize_upper(ca.sumsqr(y))
    p.minimize_lower((c * x[0] * y[0] - 1) ** 2 + ((x[1] + 2) * y[1] - x[0]) ** 2)
    prep = prepare(p)
    first = starts.conditioning_start(prep)
    key = ("conditioning-start",)
    hessian, adjoint = prep.memo[key].hessian, prep.memo[key].adjoint
    calls = []
    prep.memo[key] = starts.ConditioningParts(lambda xv: calls.append(1) or hessian(xv), adjoint)
    again = starts.conditioning_start(prep)
    assert not calls and np.array_equal(again, first) and again is not first
    np.testing.assert_array_equal(first, starts._conditioning_descent(prep, starts.ConditioningParts(hessian, adjoint)))
    p.set_value("c", 3.0)
    prep = prepare(p)
    moved = starts.conditioning_start(prep)
    assert calls and not np.array_equal(moved, first)
    np.testing.assert_array_equal(moved, starts._conditioning_descent(prep, starts.ConditioningParts(hessian, adjoint)))
    calls.clear()
    p.set_bounds(p.upper_variables[0].name, -0.5, 0.5)  # a new box (and a start clipped into it), same revision
    prep = prepare(p)
    boxed = starts.conditioning_start(prep)
    assert calls and np.all(np.abs(boxed) <= 0.5)
    np.testing.assert_array_equal(boxed, starts._conditioning_descent(prep, starts.ConditioningParts(hessian, adjoint)))
