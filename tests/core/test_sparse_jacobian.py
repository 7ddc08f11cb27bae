"""sparse_jacobian.jacobian: the same Jacobian as CasADi's, also where dense rows and columns are differentiated
apart; the NLP's derivative functions are built once for every IPOPT options."""

from __future__ import annotations

import casadi as ca
import numpy as np

from bilevel.sparse_jacobian import dense_count, jacobian


def test_dense_count_takes_the_few_large_counts_apart() -> None:
    assert dense_count(np.array([3, 3, 3, 3])) == 0
    assert dense_count(np.array([2, 50, 2, 60, 2, 2])) == 2
    assert dense_count(np.zeros(0, dtype=int)) == 0


def test_kkt_like_pattern_matches_casadi_and_a_hand_derivative() -> None:
    """Rows A(x) y (dense in x and y) and stationarity rows P y + A(x)' mu (each multiplier in every row): the split
    Jacobian equals CasADi's and the derivative written out by hand."""
    rng = np.random.default_rng(0)
    n, m = 30, 3
    x, y, mu = ca.SX.sym("x", n), ca.SX.sym("y", n), ca.SX.sym("mu", m)
    B = rng.standard_normal((m, n))
    A = ca.DM(B) * ca.repmat(x.T, m, 1)  # A_ij = B_ij x_j
    g = ca.vertcat(ca.mtimes(A, y), 2.0 * y + ca.mtimes(A.T, mu))
    w = ca.vertcat(x, y, mu)
    split, plain = jacobian(g, w), ca.jacobian(g, w)
    assert split.sparsity() == plain.sparsity()
    xv, yv, mv = rng.standard_normal(n), rng.standard_normal(n), rng.standard_normal(m)
    values = ca.Function("j", [w], [split, plain])(np.concatenate([xv, yv, mv]))
    hand = np.block([[B * yv, B * xv, np.zeros((m, m))],
                     [np.diag(B.T @ mv), 2.0 * np.eye(n), (B * xv).T]])
    np.testing.assert_allclose(np.asarray(values[0]), hand, rtol=1e-12, atol=1e-12)
    np.testing.assert_allclose(np.asarray(values[1]), hand, rtol=1e-12, atol=1e-12)


def test_sparse_pattern_is_casadis_own() -> None:
    x = ca.SX.sym("x", 4)
    g = ca.vertcat(x[0] * x[1], ca.sin(x[2]), x[3] ** 2)
    assert ca.is_equal(jacobian(g, x), ca.jacobian(g, x), 2)
