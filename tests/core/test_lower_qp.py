"""Lower levels declared by matrices (BilevelProblem.lower_qp): the same answers as the expression declaration,
known optima, exact gradients, verified active-set warm starts, and clear errors."""

from __future__ import annotations

import casadi as ca
import numpy as np
import pytest
from hypothesis import given, settings, strategies as st
from scipy.optimize import linprog

from bilevel import BilevelProblem
from bilevel.defaults import defaults
from bilevel.errors import InvalidData, ModelError, RankDeficientRegressor
from bilevel.lower.matrix import MatrixLower
from bilevel.solvers.engine.prepared import prepare
from bilevel.solvers.engine.block_exact import exact_block_of
from bilevel.solvers.engine.implicit import hypergradient

RNG = np.random.default_rng(1)
M_LS, N_LS = 30, 8
C_LS = RNG.standard_normal((M_LS, N_LS))
T_LS = RNG.standard_normal(M_LS)
REG = 0.1
RADIUS = 0.5


def ridge(matrix: bool) -> BilevelProblem:
    """Label poisoning of ridge regression: max ||w(t + dt) - w(t)||^2 over ||dt|| <= RADIUS."""
    p = BilevelProblem("ridge-poisoning")
    dt = p.upper_variable("dt", M_LS)
    p.upper_constraint(ca.sumsqr(dt) <= RADIUS ** 2)
    w = p.lower_variable("w", N_LS)
    w_clean = np.linalg.solve(C_LS.T @ C_LS + REG * np.eye(N_LS), C_LS.T @ T_LS)
    p.maximize_upper(ca.sumsqr(w - w_clean))
    if matrix:
        p.lower_qp(w, C=C_LS, d=T_LS + dt, P=REG * np.eye(N_LS))
    else:
        p.minimize_lower(0.5 * ca.sumsqr(ca.mtimes(ca.DM(C_LS), w) - T_LS - dt) + 0.5 * REG * ca.sumsqr(w))
    return p


N_LP, M_LP = 6, 20
A_LP = RNG.standard_normal((M_LP, N_LP))
Y0 = RNG.uniform(-0.5, 0.5, N_LP)
B_LP = A_LP @ Y0 + RNG.uniform(0.3, 1.0, M_LP)  # Y0 stays feasible for every attack in the box
C_LP = RNG.standard_normal(N_LP)
DELTA = 0.2


def rhs_attack(matrix: bool, upper: str = "maxmin") -> BilevelProblem:
    """The follower minimizes c'y s.t. A y <= b + x, -1 <= y <= 1; the leader moves b by x in [-DELTA, DELTA]."""
    p = BilevelProblem("lp-rhs")
    x = p.upper_variable("x", M_LP, lb=-DELTA, ub=DELTA)
    y = p.lower_variable("y", N_LP, lb=-1, ub=1)
    target = C_LP if upper == "maxmin" else RNG.standard_normal(N_LP)
    p.maximize_upper(ca.dot(ca.DM(target), y))
    if matrix:
        p.lower_qp(y, q=C_LP, A=A_LP, b=B_LP + x)
    else:
        p.minimize_lower(ca.dot(ca.DM(C_LP), y))
        p.lower_constraint(ca.mtimes(ca.DM(A_LP), y) <= B_LP + x)
    return p


@pytest.mark.parametrize("method", ["hypergradient", "ipopt"])
def test_matrix_least_squares_equals_expression_declaration(method):
    """The same algorithm on both declarations; the descent (exact_block=False) for the hypergradient, since the
    exact block's global step may pick either sign of the leading singular direction, an equally optimal point."""
    options = {"exact_block": False} if method == "hypergradient" else {}
    a, b = (ridge(m).solve(method=method, starts=2, **options) for m in (False, True))
    assert a.certificate.passed and b.certificate.passed
    assert b.upper_objective == pytest.approx(a.upper_objective, rel=1e-8)
    assert b.lower_objective == pytest.approx(a.lower_objective, rel=1e-8)
    np.testing.assert_allclose(b.y["w"], a.y["w"], atol=1e-7)


def test_matrix_least_squares_reaches_trust_region_optimum():
    """w(t + dt) - w(t) = M dt with M = (C'C + reg I)^{-1} C', so the optimum is RADIUS^2 ||M||_2^2 (the leading
    singular direction; the trust-region subproblem, More & Sorensen 1983)."""
    M = np.linalg.solve(C_LS.T @ C_LS + REG * np.eye(N_LS), C_LS.T)
    best = RADIUS ** 2 * np.linalg.norm(M, 2) ** 2
    res = ridge(True).solve(method="hypergradient", starts=4, gain_tol=1e-10)
    assert res.certificate.passed
    assert res.upper_objective == pytest.approx(best, rel=1e-6)
    assert prepare(ridge(True)).canon.lower.kind == "least-squares"
    assert res.stats["exact_block"] == [0, M_LS]  # the matrix form has its exact block too


def test_auto_leaves_a_large_exact_block_to_the_descent(monkeypatch) -> None:
    """exact_block="auto" takes an exact block only while its subproblem is small (a dense eigendecomposition per
    evaluation); above the bound it runs the descent and says why; exact_block=True still takes it."""
    monkeypatch.setitem(defaults, "hypergradient.auto_exact_dimension", N_LS - 1)
    res = ridge(True).solve(method="hypergradient", starts=1)
    assert res.stats["exact_block"] is None and any("the descent is cheaper" in w for w in res.stats["not_exact"])
    assert ridge(True).solve(method="hypergradient", starts=1, exact_block=True).stats["exact_block"] == [0, M_LS]


def test_exact_block_reads_the_matrix_form() -> None:
    """lower_qp's least squares gets the exact block (its gradient q - C'd assembled from the data, C'd never built
    as an expression): one start reaches the trust-region optimum as the expression declaration does."""
    M = np.linalg.solve(C_LS.T @ C_LS + REG * np.eye(N_LS), C_LS.T)
    best = RADIUS ** 2 * np.linalg.norm(M, 2) ** 2
    for matrix in (True, False):
        res = ridge(matrix).solve(method="block-exact", starts=1)
        assert res.certificate.passed and res.upper_objective == pytest.approx(best, rel=1e-9)
        exact, _ = exact_block_of(prepare(ridge(matrix)))  # the constant matrix Hessian is factored once
        assert (exact.factor is not None) is matrix


def test_matrix_gradient_matches_finite_differences():
    """The adjoint R'z of the matrix form (one reverse sweep through d) against central differences."""
    for problem in (ridge(True), rhs_attack(True, "target")):
        prep = prepare(problem)
        rng = np.random.default_rng(3)
        x = np.clip(rng.uniform(-0.05, 0.05, prep.canon.x_start.size), prep.canon.x_lb, prep.canon.x_ub)
        phi, grad, _ = hypergradient(prep, x)
        h = 1e-6
        for i in rng.choice(x.size, 5, replace=False):
            e = np.zeros_like(x)
            e[i] = h
            fd = (hypergradient(prep, x + e)[0] - hypergradient(prep, x - e)[0]) / (2 * h)
            assert grad[i] == pytest.approx(fd, abs=1e-6 * (1 + abs(phi)))


@pytest.mark.parametrize("method", ["hypergradient", "ipopt", "global"])
def test_matrix_lp_equals_expression_declaration(method):
    a, b = (rhs_attack(m).solve(method=method, starts=2) for m in (False, True))
    assert a.certificate.passed and b.certificate.passed
    assert b.upper_objective == pytest.approx(a.upper_objective, rel=1e-7)


def test_matrix_lp_maxmin_known_optimum():
    """The follower's optimal cost v(x) = min {c'y : A y <= b + x} never increases when a right-hand side grows, so
    the leader's best attack is x = -DELTA everywhere: v(-DELTA) from an independent HiGHS solve is the optimum,
    and the global method proves it."""
    ref = linprog(C_LP, A_ub=A_LP, b_ub=B_LP - DELTA, bounds=(-1, 1), method="highs")
    res = rhs_attack(True).solve(method="global")
    assert res.certificate.passed and res.certificate.global_bound.proven
    assert res.upper_objective == pytest.approx(ref.fun, abs=1e-7)


@settings(max_examples=15, deadline=None)
@given(st.lists(st.floats(-DELTA, DELTA), min_size=M_LP, max_size=M_LP), st.integers(0, 2 ** 16))
def test_active_set_warm_start_is_optimal(x_list, seed):
    """A solve that reuses the previous active set equals a fresh HiGHS solve and satisfies the LP's KKT
    conditions (the warm start is verified, never trusted)."""
    low = prepare(rhs_attack(True)).canon.lower
    assert isinstance(low, MatrixLower) and low.kind == "lp"
    rng = np.random.default_rng(seed)
    x1 = np.asarray(x_list)
    low.solve(np.clip(x1 + rng.uniform(-0.05, 0.05, M_LP), -DELTA, DELTA))  # leaves an active set behind
    sol = low.solve(x1)
    ref = linprog(C_LP, A_ub=A_LP, b_ub=B_LP + x1, bounds=(-1, 1), method="highs")
    assert sol.objective == pytest.approx(ref.fun, abs=1e-9)
    stat, _ = low.stationarity(x1, sol.y, sol.lam, sol.mu, [])
    _, g, _, _ = low.evaluate(x1, sol.y)
    assert np.abs(stat).max() <= 1e-9 and g.max() <= 1e-9 and sol.lam.min() >= 0.0
    assert np.abs(sol.lam * g).max() <= 1e-9


def test_matrix_certificate_re_solves_independently():
    low = prepare(rhs_attack(True)).canon.lower
    x = np.zeros(M_LP)
    assert low.solve(x).solver == "highs (dual simplex)"
    assert low.solve(x).solver == "active set of the previous solve, verified optimal"
    assert low.reference_solve(x).solver.startswith("cvxpy+clarabel")
    ls = prepare(ridge(True)).canon.lower
    assert ls.solve(np.zeros(M_LS)).solver == "closed-form" and ls.reference_solve(np.zeros(M_LS)).solver == "LU solve"


def _base() -> tuple[BilevelProblem, ca.SX, ca.SX]:
    p = BilevelProblem("bad")
    x = p.upper_variable("x", 2)
    w = p.lower_variable("w", 2)
    p.minimize_upper(ca.sumsqr(w))
    return p, x, w


@pytest.mark.parametrize("declare, error, match", [
    (lambda p, x, w: p.lower_qp(x, C=np.eye(2), d=x), ModelError, "vector lower variable"),
    (lambda p, x, w: p.lower_qp(w, C=np.eye(3), d=x), ModelError, "2 columns"),
    (lambda p, x, w: p.lower_qp(w, C=np.eye(2), d=ca.vertcat(x, x)), ModelError, "needs 2"),
    (lambda p, x, w: p.lower_qp(w, P=-np.eye(2), q=x), ModelError, "not positive semidefinite"),
    (lambda p, x, w: p.lower_qp(w, P=np.array([[1.0, 2.0], [0.0, 1.0]]), q=x), ModelError, "symmetric"),
    (lambda p, x, w: p.lower_qp(w, C=np.array([[np.nan, 0.0], [0.0, 1.0]]), d=x), InvalidData, "NaN"),
    (lambda p, x, w: p.lower_qp(w, C="data", d=x), ModelError, "numeric matrix"),
    (lambda p, x, w: p.lower_qp(w), ModelError, "no objective"),
])
def test_lower_qp_bad_declarations(declare, error, match):
    p, x, w = _base()
    with pytest.raises(error, match=match):
        declare(p, x, w)


def test_lower_qp_is_the_whole_lower_level():
    p, x, w = _base()
    p.lower_qp(w, C=np.eye(2), d=x)
    with pytest.raises(ModelError, match="lower_qp"):
        p.lower_constraint(w[0] <= 1)
    with pytest.raises(ModelError, match="lower_qp"):
        p.minimize_lower(ca.sumsqr(w))
    p2, x2, w2 = _base()
    p2.lower_qp(w2, C=np.eye(2), d=w2)
    with pytest.raises(ModelError, match="depends on the lower variable"):
        p2.solve(method="hypergradient")


def test_least_squares_adjoint_on_a_singular_hessian_is_a_failing_point() -> None:
    """Where the Hessian handed to the implicit-derivative solve is singular (a learner the attacker made
    rank-deficient, which rounding decides near the edge), the least-squares kind raises RankDeficientRegressor, which
    the methods take as a trial point that fails (bilevel.solvers.engine.ascent); a positive definite one is solved in
    full rank."""
    p = BilevelProblem("ls-adjoint")
    x = p.upper_variable("x", lb=-1, ub=1)
    y = p.lower_variable("y", 2)
    p.minimize_upper((y[0] - 2) ** 2)
    p.minimize_lower((y[0] - x) ** 2 + (y[1] - 1) ** 2)
    low = prepare(p).canon.lower
    assert low.kind == "least-squares"
    rhs = np.array([[1.0], [2.0]])
    with pytest.raises(RankDeficientRegressor, match="singular Hessian"):
        low.kkt_solve(np.zeros(1), np.array([[1.0, 1.0], [1.0, 1.0]]), rhs)  # PSD, rank 1
    Z, rank = low.kkt_solve(np.zeros(1), 2 * np.eye(2), rhs)
    np.testing.assert_allclose(Z, rhs / 2, atol=1e-15)
    assert rank == 2
