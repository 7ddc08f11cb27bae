"""Structure recognition (budget balls, exact blocks), the block-exact method, and honest stationary points."""

from __future__ import annotations

import casadi as ca
import numpy as np
import pytest

import bilevel as bl
from bilevel.problems.vrft_instance import attack_instance
from bilevel.attacks.vrft_methods import attack_alternating
from bilevel.errors import ModelError
from bilevel.problems import registry
from bilevel.solvers.engine.prepared import prepare
from bilevel.solvers.engine.block_exact import SINGULAR_LEARNER, find_exact_block
from bilevel.solvers.engine.implicit import shared_oracle
from bilevel.solvers.engine.structure import find_balls
from bilevel.solvers.engine.trust_region import maximize_quadratic_on_ball


def test_balls_are_read_from_squared_norm_constraints() -> None:
    p = bl.BilevelProblem("balls")
    u = p.upper_variable("u", 3)
    w = p.upper_variable("w", 2)
    v = p.upper_variable("v", 2)
    y = p.lower_variable("y")
    p.minimize_upper(ca.sumsqr(u) + y + ca.sumsqr(w) + ca.sumsqr(v))
    p.minimize_lower((y - u[0]) ** 2)
    p.upper_constraint(2 * ca.sumsqr(u - ca.DM([1, 2, 3])) <= 8)  # ||u - c|| <= 2
    p.upper_constraint(ca.sumsqr(w) + u[0] <= 1)                   # couples two variables: not a ball
    p.upper_constraint(v[0] ** 2 + 2 * v[1] ** 2 <= 1)             # an ellipse: not a ball
    balls = find_balls(prepare(p).canon)
    assert len(balls) == 1
    b = balls[0]
    assert b.row == 0 and b.block == slice(0, 3) and b.radius == pytest.approx(2.0, rel=1e-14)
    np.testing.assert_allclose(b.center, [1, 2, 3], rtol=1e-14)
    point = b.sphere_point(np.random.default_rng(0))
    assert np.linalg.norm(point - b.center) == pytest.approx(2.0, rel=1e-14)


def _ridge(radius: float = 0.7) -> tuple[bl.BilevelProblem, np.ndarray, np.ndarray]:
    """max ||y*(u) - y0||^2 over ||u|| <= r with y*(u) = (A'A + I)^{-1} A'(b + B u): a convex maximization."""
    rng = np.random.default_rng(3)
    A, B = rng.standard_normal((6, 3)), rng.standard_normal((6, 2))
    b, y0 = rng.standard_normal(6), rng.standard_normal(3)
    p = bl.BilevelProblem("ridge-ball")
    u = p.upper_variable("u", 2)
    y = p.lower_variable("y", 3)
    p.minimize_lower(ca.sumsqr(ca.mtimes(ca.DM(A), y) - ca.DM(b) - ca.mtimes(ca.DM(B), u)) + ca.sumsqr(y))
    p.upper_constraint(ca.sumsqr(u) <= radius ** 2)
    p.maximize_upper(ca.sumsqr(y - ca.DM(y0)))
    M = np.linalg.solve(A.T @ A + np.eye(3), A.T)
    return p, M @ b - y0, M @ B


def test_hard_case_ties_are_broken_towards_the_preferred_point_not_by_the_eigensolver() -> None:
    """max v'Av over ||v|| <= 1 with b = 0 (a stationary centre): +-q_top tie. The returned one is the one along
    prefer, whatever sign the eigensolver gave q_top (which changes with the BLAS kernel); with a two-dimensional top
    eigenspace it is prefer's direction in that space."""
    A = np.diag([3.0, 1.0, -2.0])
    for prefer, expected in (([1.0, 0.5, 0.0], [1.0, 0.0, 0.0]), ([-1.0, 3.0, 2.0], [-1.0, 0.0, 0.0])):
        np.testing.assert_allclose(maximize_quadratic_on_ball(A, np.zeros(3), 1.0, np.array(prefer)), expected,
                                   atol=1e-12)
    double = np.diag([2.0, 2.0, -1.0])
    v = maximize_quadratic_on_ball(double, np.zeros(3), 2.0, np.array([3.0, 4.0, 7.0]))
    np.testing.assert_allclose(v, [1.2, 1.6, 0.0], atol=1e-12)


def test_block_exact_step_is_global_on_a_convex_maximization() -> None:
    """The maximum of a convex quadratic over a disc lies on its circle: compare with 200,001 circle points."""
    radius = 0.7
    p, c, D = _ridge(radius)
    res = p.solve(method="block-exact", starts=1)
    theta = np.linspace(0, 2 * np.pi, 200_001)
    circle = radius * np.stack([np.cos(theta), np.sin(theta)], -1)
    brute = float(np.max(np.sum((c + circle @ D.T) ** 2, axis=1)))
    assert res.success and res.certificate.passed
    assert res.upper_objective >= brute - 1e-9 and res.upper_objective == pytest.approx(brute, rel=1e-9)
    assert np.linalg.norm(res.x["u"]) == pytest.approx(radius, rel=1e-12)
    assert res.stats["exact_block"] == [0, 2]


def test_exact_block_hands_the_oracle_its_lower_objective_and_kkt_values() -> None:
    """The exact step returns y*(x) with the lower Hessian as its KKT matrix; the oracle fills in f(x, y*)."""
    p, _, _ = _ridge()
    prep = prepare(p)
    low = prep.canon.lower
    exact, _ = find_exact_block(prep.canon, prep.balls)
    x, sol, kkt = exact.solve(np.array([0.3, -0.2]))
    assert np.isnan(sol.objective) and np.linalg.norm(x) == pytest.approx(0.7, rel=1e-12)
    ev = shared_oracle(prep, projected_rows=tuple(b.row for b in prep.balls)).evaluate(x, sol, kkt)
    assert ev.lower.objective == pytest.approx(low.evaluate(x, sol.y)[0], rel=1e-12)
    np.testing.assert_allclose(kkt.hessian, low.hessian(x, sol.y), rtol=1e-12)
    assert kkt.g.size == kkt.h.size == 0 and not kkt.stationarity.any()
    np.testing.assert_allclose(low.kkt_values(x, sol).stationarity.ravel(), 0.0, atol=1e-10)  # stationary: y = y*(x)


def test_block_exact_names_why_it_does_not_apply() -> None:
    p = bl.BilevelProblem("not-exact")
    u = p.upper_variable("u", 2)
    y = p.lower_variable("y", 2)
    p.minimize_lower(ca.sumsqr(y - u) + ca.sumsqr(u[0] * y))   # u enters the lower Hessian
    p.upper_constraint(ca.sumsqr(u) <= 1)
    p.maximize_upper(ca.sumsqr(y))
    exact, why = find_exact_block(prepare(p).canon, prepare(p).balls)
    assert exact is None and why == ["x[0:2] enters the lower Hessian"]
    with pytest.raises(ModelError, match="enters the lower Hessian"):
        p.solve(method="block-exact")


def _vrft_from_scratch(seed: int, N: int = 64) -> tuple[bl.BilevelProblem, float]:
    """The paper's VRFT max-min attack (Sec. 4.4) declared with the public API only, dense operators."""
    atk = attack_instance("maxmin", "B", 0.1, 0.057, seed, N)
    reg = atk.setting.regressor
    rows, T = reg.rows(N), reg.dense(N)
    p = bl.BilevelProblem("vrft-from-scratch")
    a_u = p.upper_variable("a_u", N)
    a_y = p.upper_variable("a_y", N)
    theta = p.lower_variable("theta", T.shape[0])
    phi = ca.DM(atk.phi0) + ca.horzcat(*[ca.mtimes(ca.DM(Ti), a_y) for Ti in T])
    p.minimize_lower(ca.sumsqr(ca.DM(atk.t0) + a_u[:rows] - ca.mtimes(phi, theta)) / rows)
    p.upper_constraint(ca.sumsqr(a_u) <= atk.delta_u ** 2)
    p.upper_constraint(ca.sumsqr(a_y) <= atk.delta_y ** 2)
    p.maximize_upper(ca.sumsqr(ca.DM(atk.t0) - ca.mtimes(ca.DM(atk.phi0), theta)) / rows)
    return p, attack_alternating(atk).upper_objective


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_vrft_declared_from_scratch_matches_the_registered_problem(seed: int) -> None:
    """The generic hypergradient on a user's own declaration reaches the registered problem's objective (1e-6)."""
    p, structured = _vrft_from_scratch(seed)
    mine = p.solve(method="hypergradient", starts=1)
    registered = registry.get("vrft-maxmin", N=64, seed=seed).solve(method="hypergradient", starts=1)
    assert mine.success and registered.success and mine.certificate.passed
    assert mine.upper_objective == pytest.approx(registered.upper_objective, rel=1e-6)
    assert mine.upper_objective >= structured * (1 - 1e-6)  # and the structured attack's value
    assert mine.stats["projected_gradient_norm"] <= 1e-3 * np.sqrt(2 * 64)  # stationary to the method's tolerance


def test_clean_data_is_never_a_solved_attack() -> None:
    """Zero poisoning is stationary (the clean learner minimizes the attacker's loss) but is its worst point: the
    descent (exact_block=False) stays there and says so; the default exact-block mode leaves it at the first step
    (its block step is a global one, not trapped by stationarity)."""
    p, _ = _vrft_from_scratch(0)
    p.suggested_starts.clear()
    p.suggest_start(a_u=np.zeros(64), a_y=np.zeros(64))  # the first start: zero poisoning
    res = p.solve(method="hypergradient", starts=1, exact_block=False)
    assert res.x["a_u"] == pytest.approx(0.0, abs=1e-12) and res.x["a_y"] == pytest.approx(0.0, abs=1e-12)
    assert res.status is bl.Status.NOT_LOCALLY_OPTIMAL and not res.success
    assert res.stats["probe"]["objective"] > res.upper_objective  # the declared sense: maximize J
    assert p.solve(method="hypergradient", starts=2, exact_block=False).success  # the conditioning start
    exact = p.solve(method="hypergradient", starts=1)
    assert exact.success and exact.stats["exact_block"] == [0, 64]
    budget = attack_instance("maxmin", "B", 0.1, 0.057, 0, 64).delta_u
    assert np.linalg.norm(exact.x["a_u"]) == pytest.approx(budget, rel=1e-9)  # on the sphere: a convex maximum


def test_suggest_start_rejects_unknown_names_and_bad_shapes() -> None:
    p = bl.BilevelProblem("starts")
    p.upper_variable("x", 2)
    with pytest.raises(ModelError, match="'z' is not an upper variable"):
        p.suggest_start(z=1.0)
    with pytest.raises(ModelError, match="has 3 entries"):
        p.suggest_start(x=[1.0, 2.0, 3.0])


def test_a_start_where_the_learner_is_singular_is_a_failed_start() -> None:
    """The exact block x (a ball) with the learner min (w y_0 - 1)^2 + (y_1 - x_0 - x_1)^2, singular at w = 0 only:
    the conditioning start is w = 0, where the learner cannot be solved. That start fails (no point, no steps; it
    used to end solve with an AttributeError) and the other reaches x on the ball at (1, 1)/sqrt(2), w -> 0+."""
    p = bl.BilevelProblem("singular-block")
    x = p.upper_variable("x", 2)
    w = p.upper_variable("w", lb=0, ub=1, start=1.0)
    y = p.lower_variable("y", 2)
    p.upper_constraint(ca.sumsqr(x) <= 1)
    p.minimize_upper((y[1] - 2) ** 2 + (w + 0.5) ** 2)
    p.minimize_lower((w * y[0] - 1) ** 2 + (y[1] - x[0] - x[1]) ** 2)
    result = p.solve("block-exact", starts=2)
    failed, other = result.start_records
    assert failed["objective"] is None and failed["iterations"] == 0 and other["converged"]
    assert failed[SINGULAR_LEARNER] and not other[SINGULAR_LEARNER]
    np.testing.assert_allclose(result.x["x"], np.full(2, np.sqrt(0.5)), atol=1e-6)
    assert 0 < result.x["w"][0] < 1e-6
