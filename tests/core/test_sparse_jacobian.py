"""sparse_jacobian.jacobian: the same Jacobian as CasADi's, also where dense rows and columns are differentiated
apart; the NLP's derivative functions are built once for every IPOPT options."""

from __future__ import annotations

import casadi as ca
import numpy as np
import pytest

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


def _casadi_derivatives(nlp) -> tuple[ca.Function, ca.Function]:
    """CasADi's own jac_g and hess_lag of a transcribed NLP."""
    p = ca.vertcat(nlp.p, nlp.params.sym)
    sigma, lam = ca.SX.sym("s"), ca.SX.sym("l", nlp.g.numel())
    hess = ca.triu(ca.hessian(sigma * nlp.f + ca.dot(lam, nlp.g), nlp.x)[0])
    return (ca.Function("j", [nlp.x, p], [nlp.g, ca.jacobian(nlp.g, nlp.x)]),
            ca.Function("h", [nlp.x, p, sigma, lam], [hess]))


@pytest.mark.parametrize("which", ["bard", "disc-sdp"])
def test_nlp_derivatives_match_casadis_for_every_transcription(which: str) -> None:
    """The relaxed and the branch NLP of an MPCC (one with PSD factors as auxiliary variables) share the derivatives
    of f and the common rows; each one's jac_g and hess_lag equal CasADi's at random points."""
    from bilevel.mpcc import Branch, Scholtes
    from bilevel.solvers.engine.prepared import prepare

    if which == "bard":
        from tests.conftest import bard_511 as build
    else:
        from tests.core.test_sdp import disc_problem as build
    mpcc = prepare(build()).mpcc
    rng = np.random.default_rng(1)
    sides = {name: rng.random(G.size) < 0.5 for name, (G, _) in mpcc.pair_values(np.zeros(mpcc.n_variables)).items()}
    forms = [mpcc.transcribe(Scholtes(1e-3)), mpcc.transcribe(Branch(sides=sides))]
    assert forms[0]._shared is forms[1]._shared and forms[0].common_rows > 0
    for nlp in forms:
        ours, theirs = nlp.derivatives(), _casadi_derivatives(nlp)
        for _ in range(3):
            x, lam = rng.standard_normal(int(nlp.x.numel())), rng.standard_normal(int(nlp.g.numel()))
            p = np.concatenate([nlp.p_value, nlp.params.value])
            jac, ref = ours["jac_g"](x, p)[1], theirs[0](x, p)[1]
            np.testing.assert_allclose(np.asarray(ca.densify(jac)), np.asarray(ca.densify(ref)), atol=1e-12)
            hess, ref = ours["hess_lag"](x, p, 0.7, lam), theirs[1](x, p, 0.7, lam)
            np.testing.assert_allclose(np.asarray(ca.densify(hess)), np.asarray(ca.densify(ref)), atol=1e-12)
    assert len(mpcc._shared_derivatives) == 2
