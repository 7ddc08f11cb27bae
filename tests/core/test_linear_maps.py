"""Linear maps in declarations (BilevelProblem.linear_map) and the residual form of large least squares: the same
problem declared with the matrix written into the expressions gives the same values and hypergradients, and the
answers are re-checked by independent numpy fits."""

from __future__ import annotations

import casadi as ca
import numpy as np
import pytest
import scipy.sparse as sp
from scipy.sparse.linalg import aslinearoperator

import bilevel as bl
from bilevel import linear_maps
import bilevel.lower.residual as residual
from bilevel.problems.vrft_instance import attack_instance
from bilevel.attacks.vrft_methods import attack_alternating
from bilevel.defaults import defaults
from bilevel.errors import ModelError
from bilevel.lower.images import ImageLower
from bilevel.lower.least_squares import factor_solve, hessian_factor
from bilevel.lower.least_squares import sum_of_squares
from bilevel.lower.residual import ResidualLeastSquares
from bilevel.solvers.engine.prepared import prepare
from bilevel.solvers.engine.implicit import Hypergradient


def _vrft(seed: int, N: int, wrap=None) -> bl.BilevelProblem:
    """The paper's VRFT max-min attack (Sec. 4.4) with the regressor's Toeplitz maps T_k: as linear maps (wrap
    turns each dense matrix into the form to declare), or written into the expressions (wrap None)."""
    atk = attack_instance("maxmin", "B", 0.1, 0.057, seed, N)
    rows, T = atk.t0.size, atk.setting.regressor.dense(N)
    p = bl.BilevelProblem("vrft")
    a_u = p.upper_variable("a_u", N)
    a_y = p.upper_variable("a_y", N)
    theta = p.lower_variable("theta", T.shape[0])
    if wrap is None:
        phi = ca.horzcat(*[ca.mtimes(ca.DM(Tk), atk.y + a_y) for Tk in T])
    else:
        phi = ca.horzcat(*[p.linear_map(wrap(Tk), f"T{k}") @ (atk.y + a_y) for k, Tk in enumerate(T)])
    p.minimize_lower(ca.sumsqr(atk.t0 + a_u[:rows] - ca.mtimes(phi, theta)) / rows)
    p.upper_constraint(ca.sumsqr(a_u) <= atk.delta_u ** 2)
    p.upper_constraint(ca.sumsqr(a_y) <= atk.delta_y ** 2)
    p.maximize_upper(ca.sumsqr(atk.t0 - ca.mtimes(ca.DM(atk.phi0), theta)) / rows)
    return p


def _phi_and_gradient(p: bl.BilevelProblem, x: np.ndarray) -> tuple[float, np.ndarray]:
    oracle = Hypergradient(prepare(p))
    ev = oracle.evaluate(x)
    return ev.phi, oracle.gradient(ev)[0]


@pytest.mark.parametrize("wrap", [np.asarray, aslinearoperator], ids=["dense", "operator"])
def test_the_lower_solutions_at_rows_lifted_at_once_are_the_solves_point_by_point(wrap) -> None:
    """ImageLower.solve_rows (the local probe's lower solve) lifts all rows in one product per map group: the same
    solutions as `solve` at each point, and None at a point where the learner cannot be solved (a NaN entry)."""
    N = 48
    low = prepare(_vrft(0, N, wrap)).canon.lower
    X = np.random.default_rng(5).standard_normal((3, 2 * N)) * 0.05
    X[2, N + 1] = np.nan
    rows = low.solve_rows(X)
    for x, y in zip(X[:2], rows):
        want = low.solve(x).y
        assert np.abs(y - want).max() <= 1e-12 * np.abs(want).max()
    assert rows[2] is None


@pytest.mark.parametrize("wrap", [np.asarray, sp.csr_matrix, aslinearoperator], ids=["dense", "sparse", "operator"])
def test_linear_maps_give_the_expanded_declarations_values_and_hypergradients(wrap) -> None:
    N = 48
    x = np.random.default_rng(3).standard_normal(2 * N) * 0.05
    phi0, g0 = _phi_and_gradient(_vrft(0, N), x)
    p = _vrft(0, N, wrap)
    phi, g = _phi_and_gradient(p, x)
    assert isinstance(prepare(p).canon.lower, ImageLower)
    assert phi == pytest.approx(phi0, rel=1e-10)
    assert np.abs(g - g0).max() <= 1e-9 * np.abs(g0).max()


@pytest.mark.parametrize("seed", [0, 1])
def test_vrft_declared_with_maps_reaches_the_structured_attack(seed: int) -> None:
    """One start (the conditioning start of the least-squares learner) reaches the structured attack's objective
    (attack_alternating, from its own conditioning start); the answer is re-checked by a numpy refit."""
    N = 64
    p = _vrft(seed, N, np.asarray)
    res = p.solve("hypergradient", starts=1)
    atk = attack_instance("maxmin", "B", 0.1, 0.057, seed, N)
    assert res.success and res.certificate.passed
    assert res.upper_objective >= 0.98 * attack_alternating(atk, seed=seed).upper_objective
    phi = atk.setting.regressor(atk.y + res.x["a_y"])
    theta = np.linalg.lstsq(phi, atk.t0 + res.x["a_u"][:atk.t0.size], rcond=None)[0]
    assert np.abs(theta - res.y["theta"]).max() <= 1e-8 * (1 + np.abs(theta).max())
    assert np.linalg.norm(res.x["a_u"]) <= atk.delta_u * (1 + 1e-9)


def test_the_kkt_route_expands_the_maps_and_agrees() -> None:
    N = 24
    p = _vrft(0, N, np.asarray)
    low = prepare(p).canon.lower
    rng = np.random.default_rng(0)
    x, y = 0.05 * rng.standard_normal(2 * N), rng.standard_normal(low.n_y)
    assert low.symbolic().evaluate(x, y)[0] == pytest.approx(low.evaluate(x, y)[0], rel=1e-12)
    res = p.solve("ipopt")
    assert res.certificate.passed and res.upper_objective > 0


def test_linear_map_errors_name_the_fix(monkeypatch) -> None:
    p = bl.BilevelProblem("bad")
    x = p.upper_variable("x", 3)
    y = p.lower_variable("y", 2)
    A = p.linear_map(np.ones((2, 3)), "A")
    with pytest.raises(ModelError, match="3 columns but the expression has 2 rows"):
        A @ y
    with pytest.raises(ModelError, match="mix upper and lower"):
        A @ (x + ca.vertcat(y, 0))
    with pytest.raises(ModelError, match="expected a numeric matrix"):
        p.linear_map("not a matrix")
    z = A @ x
    p.minimize_lower(ca.sumsqr(y - z))
    p.minimize_upper(ca.sumsqr(z))
    with pytest.raises(ModelError, match="products of a linear map outside the lower level"):
        p.solve("hypergradient")
    p.minimize_upper(ca.sumsqr(y))
    assert p.solve("hypergradient").certificate.passed
    monkeypatch.setitem(defaults, "linear_maps.dense_limit", 1)
    q = bl.BilevelProblem("operator")
    x = q.upper_variable("x", 3, lb=-1, ub=1)
    y = q.lower_variable("y", 2)
    q.minimize_lower(ca.sumsqr(y - q.linear_map(aslinearoperator(np.ones((2, 3)))) @ x))
    q.minimize_upper(ca.sumsqr(y - 1))
    with pytest.raises(ModelError, match="use method='hypergradient'"):
        q.solve("ipopt")


def test_least_squares_with_a_map_of_the_lower_variable_is_the_matrix_form() -> None:
    """min ||A w - b - db||^2 declared with A as a linear map gives lower_qp's problem: same answer, and the lower
    solution is numpy's least-squares fit of the poisoned data."""
    rng = np.random.default_rng(1)
    A, b = rng.standard_normal((60, 40)), rng.standard_normal(60)
    w0 = np.linalg.lstsq(A, b, rcond=None)[0]
    answers = []
    for how in ("map", "lower_qp"):
        p = bl.BilevelProblem(how)
        db = p.upper_variable("db", 60)
        w = p.lower_variable("w", 40)
        if how == "map":
            p.minimize_lower(0.5 * ca.sumsqr(p.linear_map(A) @ w - b - db))
        else:
            p.lower_qp(w, C=A, d=b + db)
        p.upper_constraint(ca.sumsqr(db) <= 0.1 ** 2)
        p.maximize_upper(ca.sumsqr(w - w0))
        answers.append(p.solve("hypergradient", starts=2))
    mine, theirs = answers
    assert mine.success and mine.certificate.passed
    assert mine.upper_objective == pytest.approx(theirs.upper_objective, rel=1e-8)
    refit = np.linalg.lstsq(A, b + mine.x["db"], rcond=None)[0]
    assert np.abs(refit - mine.y["w"]).max() <= 1e-9 * (1 + np.abs(refit).max())
    p = bl.BilevelProblem("not least squares")
    p.upper_variable("x")
    w = p.lower_variable("w", 2)
    p.minimize_lower(ca.sumsqr(p.linear_map(np.eye(2)) @ w) + w[0])
    p.minimize_upper(ca.sumsqr(w))
    with pytest.raises(ModelError, match="must be a least squares"):
        p.solve("hypergradient")


def test_sum_of_squares_reads_weights_and_refuses_other_forms() -> None:
    x, y = ca.SX.sym("x", 2), ca.SX.sym("y", 2)
    r, c = sum_of_squares(3 * ca.sumsqr(y - x) / 2 + ca.dot(y, y) - 4 * x[0], y)
    point = {"x": np.array([0.3, -1.2]), "y": np.array([0.7, 2.0])}
    value = ca.Function("f", [x, y], [0.5 * ca.sumsqr(r) + c])(point["x"], point["y"])
    assert float(value) == pytest.approx(3 * np.sum((point["y"] - point["x"]) ** 2) / 2 + point["y"] @ point["y"]
                                         - 4 * point["x"][0], rel=1e-14)
    assert sum_of_squares(ca.sumsqr(y) - ca.sumsqr(y - x), y) is None  # a negative weight: not a least squares
    assert sum_of_squares(ca.sumsqr(y) + y[0] * x[1], y) is None  # a term with y that is no square
    assert sum_of_squares(ca.sumsqr(y ** 2 - x), y) is None  # squares of expressions nonlinear in y


def test_block_gram_is_the_dense_product_on_block_patterns() -> None:
    """BlockGram of the pattern of two learners' C = kron(Z', I) (rows by output, separate fits) gives C'C at random
    values; a pattern whose row supports overlap (a dense block) has none."""
    rng = np.random.default_rng(5)
    blocks = [np.kron(rng.standard_normal((30, k)), np.eye(2)) for k in (3, 2)]
    C = np.zeros((120, 10))
    C[:60, :6], C[60:, 6:] = blocks
    rows, cols = np.nonzero(C)
    gram = residual.BlockGram.of(ca.Sparsity.triplet(120, 10, rows.tolist(), cols.tolist()))
    np.testing.assert_allclose(gram(np.asfortranarray(C)), C.T @ C, rtol=1e-12, atol=1e-12 * np.abs(C.T @ C).max())
    assert residual.BlockGram.of(ca.Sparsity.dense(120, 10)) is None


def _residual_matches_expressions(monkeypatch, declare, x: np.ndarray, affine: bool) -> bl.BilevelProblem:
    """The problem `declare` builds, in the residual kind (forced) with its data evaluated as a sparse product or
    not (`affine`), with the expression kind's phi and hypergradient at x; returned for more checks."""
    phi0, g0 = _phi_and_gradient(declare(), x)
    monkeypatch.setitem(defaults, "residual.form_size", 0)
    p = declare()
    low = prepare(p).canon.lower
    assert isinstance(low, ResidualLeastSquares) and (low._affine is not None) == affine
    phi, g = _phi_and_gradient(p, x)
    assert phi == pytest.approx(phi0, rel=1e-10)
    assert np.abs(g - g0).max() <= 1e-9 * np.abs(g0).max()
    return p


@pytest.mark.parametrize("bent", [False, True], ids=["affine data", "data nonlinear in x"])
def test_residual_form_matches_the_expression_form(monkeypatch, bent: bool) -> None:
    """An ARX(2, 2) identification attack: the residual kind (forced on a small instance) and the expression kind
    give the same hypergradient; the attack's answer is numpy's refit of the poisoned data. Regressors affine in the
    poisoning are evaluated as one sparse product; bent ones (y + dy + dy^2) by the expressions."""
    rng = np.random.default_rng(0)
    T = 200
    u = rng.standard_normal(T)
    y = np.zeros(T)
    for t in range(2, T):
        y[t] = 0.5 * y[t - 1] - 0.2 * y[t - 2] + u[t - 1] + 0.3 * u[t - 2] + 0.1 * rng.standard_normal()

    def declare() -> bl.BilevelProblem:
        p = bl.BilevelProblem("arx")
        dy = p.upper_variable("dy", T)
        theta = p.lower_variable("theta", 4)
        yp = y + dy + (dy ** 2 if bent else 0)
        reg = ca.horzcat(-yp[1:T - 1], -yp[0:T - 2], ca.DM(u[1:T - 1]), ca.DM(u[0:T - 2]))
        p.minimize_lower(ca.sumsqr(yp[2:] - ca.mtimes(reg, theta)))
        p.upper_constraint(ca.sumsqr(dy) <= (0.05 * np.linalg.norm(y)) ** 2)
        p.maximize_upper(ca.sumsqr(theta))
        return p

    p = _residual_matches_expressions(monkeypatch, declare, 0.01 * rng.standard_normal(T), affine=not bent)
    res = p.solve("hypergradient", starts=1)
    assert res.success and res.certificate.passed
    yp = y + res.x["dy"] + (res.x["dy"] ** 2 if bent else 0)
    reg = np.column_stack([-yp[1:T - 1], -yp[0:T - 2], u[1:T - 1], u[0:T - 2]])
    refit = np.linalg.lstsq(reg, yp[2:], rcond=None)[0]
    assert np.abs(refit - res.y["theta"]).max() <= 1e-9 * (1 + np.abs(refit).max())


def test_lower_qp_takes_a_regressor_the_leader_moves() -> None:
    """lower_qp(C=expression) is the least squares written out: same values at a point, and a certified attack."""
    rng = np.random.default_rng(2)
    Phi, t = rng.standard_normal((30, 3)), rng.standard_normal(30)
    solutions = []
    for how in ("lower_qp", "expressions"):
        p = bl.BilevelProblem(how)
        dphi = p.upper_variable("dphi", (30, 3))
        theta = p.lower_variable("theta", 3)
        C = ca.DM(Phi) + dphi
        if how == "lower_qp":
            p.lower_qp(theta, C=C, d=t, P=0.1 * np.eye(3))
        else:
            p.minimize_lower(0.5 * ca.sumsqr(ca.mtimes(C, theta) - t) + 0.05 * ca.sumsqr(theta))
        p.upper_constraint(ca.sumsqr(dphi) <= 0.5 ** 2)
        p.maximize_upper(ca.sumsqr(theta))
        solutions.append(p.solve("hypergradient", starts=1))
    mine, theirs = solutions
    assert mine.certificate.passed and mine.upper_objective == pytest.approx(theirs.upper_objective, rel=1e-8)
    Cp = Phi + mine.x["dphi"]
    refit = np.linalg.solve(Cp.T @ Cp + 0.1 * np.eye(3), Cp.T @ t)
    assert np.abs(refit - mine.y["theta"]).max() <= 1e-9 * (1 + np.abs(refit).max())


def test_residual_data_from_a_recursion_stay_expressions(monkeypatch) -> None:
    """A first-order filter of the poisoning written as a recursion (2 operations per sample, a dense lower-triangular
    Jacobian) is evaluated by its expressions, not as a dense sparse matrix, and gives the same hypergradient as the
    expression kind; the answer is a numpy refit."""
    rng = np.random.default_rng(1)
    T = 300
    u, y = rng.standard_normal(T), rng.standard_normal(T)

    def declare() -> bl.BilevelProblem:
        p = bl.BilevelProblem("filtered")
        dy = p.upper_variable("dy", T)
        theta = p.lower_variable("theta", 2)
        f = [y[0] + dy[0]]
        for k in range(1, T):
            f.append(0.9 * f[-1] + y[k] + dy[k])
        reg = ca.horzcat(ca.vertcat(*f), ca.DM(u))
        p.minimize_lower(ca.sumsqr(ca.DM(y) - ca.mtimes(reg, theta)))
        p.upper_constraint(ca.sumsqr(dy) <= 0.01 * T)
        p.maximize_upper(ca.sumsqr(theta))
        return p

    _residual_matches_expressions(monkeypatch, declare, 0.01 * rng.standard_normal(T), affine=False)


def test_residual_form_with_affine_data_keeps_the_terms_free_of_y(monkeypatch) -> None:
    """A least squares plus a term of x alone (c(x) = ||dy||^2 / 10): the residual kind (forced) takes the
    sparse-product path for its data and its value at (x, y) equals the declared objective's."""
    monkeypatch.setitem(defaults, "residual.form_size", 0)
    rng = np.random.default_rng(4)
    T = 400
    u, y = rng.standard_normal(T), rng.standard_normal(T)
    p = bl.BilevelProblem("with-c")
    dy = p.upper_variable("dy", T)
    theta = p.lower_variable("theta", 2)
    yp = y + dy
    f = ca.sumsqr(yp[1:] - ca.mtimes(ca.horzcat(yp[:T - 1], ca.DM(u[:T - 1])), theta)) + 0.1 * ca.sumsqr(dy)
    p.minimize_lower(f)
    p.maximize_upper(ca.sumsqr(theta))
    low = prepare(p).canon.lower
    assert isinstance(low, ResidualLeastSquares) and low._affine is not None
    x, th = rng.standard_normal(T), rng.standard_normal(2)
    expected = float(ca.evalf(ca.substitute(ca.substitute(f, dy, ca.DM(x)), theta, ca.DM(th))))
    assert low.evaluate(x, th)[0] == pytest.approx(expected, rel=1e-12)


@pytest.mark.parametrize("sense", ["min", "max"])
def test_an_upper_objective_with_a_numeric_matrix_is_evaluated_by_blas(sense: str) -> None:
    """F = ||A y - b||^2 / 3 + 2 with A written into the graph is read as numeric squares (residual.NumericSquares);
    with y* = x, F and its gradient are checked against the closed form."""
    rng = np.random.default_rng(5)
    A, b = rng.standard_normal((200, 6)), rng.standard_normal(200)
    p = bl.BilevelProblem("squares")
    x = p.upper_variable("x", 6)
    y = p.lower_variable("y", 6)
    p.minimize_lower(ca.sumsqr(y - x))
    F = ca.sumsqr(ca.mtimes(ca.DM(A), y) - b) / 3 + 2
    (p.minimize_upper if sense == "min" else p.maximize_upper)(F)
    oracle = Hypergradient(prepare(p))
    assert oracle._squares is not None
    x0 = rng.standard_normal(6)
    ev = oracle.evaluate(x0)
    sign = 1.0 if sense == "min" else -1.0  # the canonical form minimizes
    r = A @ x0 - b
    assert ev.F == pytest.approx(sign * (r @ r / 3 + 2), rel=1e-12)
    assert float(prepare(p).canon.functions(x0, ev.lower.y)[0][0, 0]) == pytest.approx(ev.F, rel=1e-12)  # the probe's
    assert np.abs(oracle.gradient(ev)[0] - sign * 2 * A.T @ r / 3).max() <= 1e-10 * np.abs(A.T @ r).max()


def test_residual_data_follow_a_parameter_at_the_same_point() -> None:
    """The residual form's data are kept per point and parameter revision: after set_value the learner at the same x
    is numpy's fit of the new data."""
    rng = np.random.default_rng(4)
    A, b = rng.standard_normal((400, 6)), rng.standard_normal(400)
    p = bl.BilevelProblem("ridge")
    db = p.upper_variable("db", 400)
    scale = p.parameter("scale", value=1.0)
    w = p.lower_variable("w", 6)
    p.minimize_lower(ca.sumsqr(scale * ca.mtimes(ca.DM(A), w) - b - db))
    p.upper_constraint(ca.sumsqr(db) <= 1.0)
    p.maximize_upper(ca.sumsqr(w))
    low = prepare(p).canon.lower
    assert isinstance(low, ResidualLeastSquares)
    x = 0.01 * rng.standard_normal(400)
    for s in (1.0, 2.0):
        p.set_value("scale", s)
        assert np.allclose(low.solve(x).y, np.linalg.lstsq(s * A, b + x, rcond=None)[0], rtol=1e-10, atol=1e-12)


@pytest.mark.parametrize("columns", [1, 3, 512])
def test_factor_solve_solves_for_any_number_of_columns(columns: int) -> None:
    """P^{-1} B from the Cholesky factor (the exact block solves for a 6 x N matrix): P X = B to rounding, on an
    ill-conditioned P too."""
    rng = np.random.default_rng(6)
    Q = np.linalg.qr(rng.standard_normal((6, 6)))[0]
    P = Q @ np.diag(np.logspace(0, -8, 6)) @ Q.T
    B = rng.standard_normal((6, columns))
    X = factor_solve(hessian_factor(P), B)
    assert X.shape == B.shape
    assert np.abs(P @ X - B).max() <= 1e-12 * (1.0 + np.abs(X).max())  # backward stable: eps ||P|| ||X||


def test_numeric_squares_keep_a_diagonal_sparse() -> None:
    """||y - c||^2 / 2 over 1,500 entries (a diagonal of 1,500 coefficients) is read as sparse numeric squares; its
    value and gradient are the closed form."""
    rng = np.random.default_rng(7)
    y, c, v = ca.SX.sym("y", 1500), rng.standard_normal(1500), rng.standard_normal(1500)
    squares = residual.numeric_squares(-0.5 * ca.sumsqr(y - c), y, ca.SX.sym("x", 2))
    assert squares is not None and sp.issparse(squares.A)
    F, g = squares(v)
    assert F[0, 0] == pytest.approx(-0.5 * np.sum((v - c) ** 2), rel=1e-13)
    assert np.abs(g.ravel() + (v - c)).max() <= 1e-13


def test_a_gather_is_the_sparse_product_of_a_selection() -> None:
    """A selection with scalings and empty rows (a slice of a shifted signal) as a Gather: the same numbers as the sparse
    product, for vectors and columns, with -0.0 products summed to 0.0 as scipy sums; a row with two entries stays a
    sparse matrix."""
    rng = np.random.default_rng(8)
    rows = np.array([0, 2, 3, 5, 6])
    J = sp.csr_matrix((rng.standard_normal(5), (rows, rng.permutation(9)[:5])), shape=(7, 9))
    v, V = rng.standard_normal(9), rng.standard_normal((9, 3))
    J.data[0], v[J.indices[0]] = 2.0, -0.0  # a -0.0 product
    gather = linear_maps.Gather.of(J)
    assert isinstance(gather, linear_maps.Gather)
    assert np.array_equal(gather @ v, J @ v) and np.array_equal(gather @ V, J @ V)
    assert np.array_equal(np.signbit(gather @ v), np.signbit(J @ v))
    full = sp.csr_matrix(np.diag(rng.standard_normal(4)))
    assert np.array_equal(linear_maps.Gather.of(full) @ v[:4], full @ v[:4])
    assert isinstance(linear_maps.Gather.of(sp.csr_matrix(np.ones((2, 2)))), sp.csr_matrix)


@pytest.mark.parametrize("scales", ["one", "shared", "per run"])
def test_a_gather_of_runs_copies_slices_with_the_sparse_products_numbers(scales: str) -> None:
    """Runs of consecutive rows reading consecutive columns forwards or backwards (a lifted signal, a reversed slice,
    a gap of empty rows, a run reaching column 0 backwards) are copied as slices: the same bits as the sparse product,
    -0.0 products summed to 0.0, for vectors and columns; scattered entries keep the entry-by-entry gather."""
    rng = np.random.default_rng(3)
    rows = np.concatenate([np.arange(0, 40), np.arange(45, 85), np.arange(85, 125)])
    cols = np.concatenate([np.arange(39, -1, -1), np.arange(100, 140), np.arange(199, 159, -1)])
    value = {"one": np.ones(3), "shared": np.full(3, -0.0625), "per run": np.array([2.0, -0.5, 3.0])}[scales]
    J = sp.csr_matrix((np.repeat(value, 40), (rows, cols)), shape=(130, 200))
    gather = linear_maps.Gather.of(J)
    assert gather._runs is not None and len(gather._runs[0]) == 3
    v, V = rng.standard_normal(200), rng.standard_normal((200, 4))
    v[[0, 120, 170]] = -0.0
    for x in (v, V, np.asfortranarray(V)):
        assert np.array_equal(gather @ x, J @ x) and np.array_equal(np.signbit(gather @ x), np.signbit(J @ x))
    scattered = sp.csr_matrix((np.ones(40), (np.arange(40), rng.permutation(200)[:40])), shape=(40, 200))
    assert linear_maps.Gather.of(scattered)._runs is None
    assert np.array_equal(linear_maps.Gather.of(scattered) @ v, scattered @ v)


@pytest.mark.parametrize("columns", [1, 3])
def test_moving_adjoint_of_a_gather_is_the_seeded_product(columns: int) -> None:
    """Affine data [vec C; d] = J x + c where each x_i moves one entry (all of C and some of d: signals lifted through
    linear maps): the x-adjoint by seeds on all entries (J' a Gather) and by sums on the moving entries (J' a sparse
    matrix) both equal J' [vec(V_j a' + y B_j'); -B_j], formed densely here."""
    rng = np.random.default_rng(11)
    rows, n_y = 7, 3
    moved = np.concatenate([np.arange(rows * n_y), rows * n_y + rng.permutation(rows)[:4]])  # all of C, 4 of d
    n_x = moved.size + 2  # two entries of x move nothing
    J = sp.csr_matrix((rng.standard_normal(moved.size), (moved, rng.permutation(n_x)[:moved.size])),
                      shape=(rows * n_y + rows, n_x))
    Jt = J.T.tocsr()
    gather = linear_maps.Gather.of(Jt)
    assert isinstance(gather, linear_maps.Gather)
    y, a = rng.standard_normal(n_y), rng.standard_normal(rows)
    V, B = rng.standard_normal((n_y, columns)), rng.standard_normal((rows, columns))
    # vec C column-major: entry (p, q) at q * rows + p, its seed V[q, j] a[p] + y[q] B[p, j]
    seeds = np.array([[V[q, j] * a[p] + y[q] * B[p, j] for j in range(columns)]
                      for q in range(n_y) for p in range(rows)])
    expected = Jt.toarray() @ np.vstack([seeds, -B])
    seeded = residual.MovingAdjoint(gather, rows, n_y)(y, V, a, B)
    summed = residual.MovingAdjoint(Jt, rows, n_y)(y, V, a, B)
    assert seeded.shape == summed.shape == (n_x, columns)
    assert np.abs(seeded - expected).max() <= 1e-13 * np.abs(expected).max()
    assert np.abs(summed - expected).max() <= 1e-13 * np.abs(expected).max()


def test_jacobian_nonzeros_exceed_refuses_a_recursion_from_a_sample_and_counts_a_fir_exactly() -> None:
    """A recursion over N samples has a dense lower-triangular Jacobian (N(N+1)/2 nonzeros), refused from 32 sampled
    columns without forming the pattern (O(N^2)); a 3-tap FIR map (3N - 3 nonzeros) is counted exactly at the edge."""
    import casadi as ca

    from bilevel.linear_maps import jacobian_nonzeros_exceed

    n = 400
    x = ca.SX.sym("x", n)
    state, rec = ca.SX(0), []
    for k in range(n):
        state = 0.9 * state + x[k]
        rec.append(state)
    recursion = ca.vertcat(*rec)
    assert ca.jacobian_sparsity(recursion, x).nnz() == n * (n + 1) // 2
    assert jacobian_nonzeros_exceed(recursion, x, 10 * n)
    assert not jacobian_nonzeros_exceed(recursion, x, n * (n + 1) // 2)
    fir = ca.vertcat(*[x[k] + 0.5 * x[k - 1] + 0.25 * x[k - 2] for k in range(2, n)])
    exact = 3 * (n - 2)
    assert ca.jacobian_sparsity(fir, x).nnz() == exact
    assert jacobian_nonzeros_exceed(fir, x, exact - 1) and not jacobian_nonzeros_exceed(fir, x, exact)
