"""The affine least-squares kind (bilevel.lower.affine_least_squares) and its ascent pieces
(bilevel.solvers.engine.affine_ls) on a learner that is not VRFT: FIR identification y_t = sum_j w_j u_{t-j}, the
outputs poisoned by a (the target) and the inputs by b (the regressor, a Toeplitz matrix of the lagged inputs), checked
against numpy's lstsq, central differences and a brute-force search of the target ball."""

from __future__ import annotations

import numpy as np
import pytest
import scipy.linalg

from bilevel.errors import RankDeficientRegressor
from bilevel.lower.affine_least_squares import AffineLeastSquares, AffineMaps
from bilevel.solvers.engine.affine_ls import Oracle, TargetBlock, UpperObjective

T, K = 60, 4


def lagged(u: np.ndarray) -> np.ndarray:
    """The FIR regressor: row t holds u_t, u_{t-1}, ..., u_{t-K+1} (zeros before the record)."""
    return scipy.linalg.toeplitz(u, np.zeros(K))


def lagged_adjoint(G: np.ndarray) -> np.ndarray:
    """<G, lagged(b)> = b . lagged_adjoint(G)."""
    out = np.zeros(T)
    for j in range(K):
        out[: T - j] += G[j:, j]
    return out


def fir_learner(seed: int = 0) -> tuple[AffineLeastSquares, np.ndarray]:
    rng = np.random.default_rng(seed)
    u = rng.standard_normal(T)
    w = np.array([1.0, -0.5, 0.25, 0.1])
    y = lagged(u) @ w + 0.05 * rng.standard_normal(T)
    return AffineLeastSquares(lagged(u), y, AffineMaps(lagged, lagged_adjoint), T, T), w


def target_distance(theta_a: np.ndarray) -> UpperObjective:
    """J = -||theta_a - theta||^2 (drive the identified FIR towards theta_a)."""
    return UpperObjective(lambda th: -float((theta_a - th) @ (theta_a - th)), lambda th: 2.0 * (theta_a - th),
                          -2.0 * np.eye(K))


def test_fit_and_gradient_match_lstsq_and_central_differences() -> None:
    low, _ = fir_learner()
    rng = np.random.default_rng(1)
    a, b = 0.1 * rng.standard_normal(T), 0.1 * rng.standard_normal(T)
    fit = low.fit(a, b)
    np.testing.assert_allclose(fit.theta, np.linalg.lstsq(lagged(low.C0[:, 0] + b), low.d0 + a, rcond=None)[0],
                               rtol=1e-10, atol=1e-12)
    J = target_distance(np.ones(K))
    g_a, g_b = low.gradient(fit, J.gradient(fit.theta))
    for g, which in ((g_a, 0), (g_b, 1)):
        for i in (0, 17, 59):
            e = np.zeros(T)
            e[i] = 1e-6
            plus = low.fit(a + e, b) if which == 0 else low.fit(a, b + e)
            minus = low.fit(a - e, b) if which == 0 else low.fit(a, b - e)
            assert (J.value(plus.theta) - J.value(minus.theta)) / 2e-6 == pytest.approx(g[i], rel=1e-5, abs=1e-9)
    oracle = Oracle(low, J)
    np.testing.assert_allclose(oracle.gradient(oracle.evaluate(np.concatenate([a, b])))[0],
                               -np.concatenate([g_a, g_b]), rtol=1e-12)


def test_target_block_is_the_best_point_of_the_ball() -> None:
    low, w = fir_learner(2)
    J, radius, b = target_distance(3.0 * w), 0.5, np.zeros(T)
    x, fit, _ = TargetBlock(low, J, None, radius).solve(np.concatenate([np.zeros(T), b]))
    assert np.linalg.norm(x[:T]) == pytest.approx(radius, rel=1e-9)
    np.testing.assert_allclose(fit.theta, low.fit(x[:T], b).theta, rtol=1e-9, atol=1e-12)
    rng = np.random.default_rng(3)
    for z in rng.standard_normal((300, T)):
        assert J.value(low.fit(radius * z / np.linalg.norm(z), b).theta) <= J.value(fit.theta) + 1e-12


def test_rank_deficient_regressor_is_refused() -> None:
    low, _ = fir_learner()
    with pytest.raises(RankDeficientRegressor, match="no unique solution"):
        low.fit(np.zeros(T), -low.C0[:, 0])  # the poisoned inputs cancel the clean ones: C = 0


@pytest.mark.parametrize("batched", [False, True])
def test_thetas_are_the_fits_of_each_row(batched: bool) -> None:
    """thetas: fit's theta at every row (rows with a = 0 or b = 0 included), None where the regressor is singular;
    with a batched map of the regressors (maps.regressors) or row by row."""
    low, _ = fir_learner()
    if batched:
        low = AffineLeastSquares(low.C0, low.d0, AffineMaps(lagged, lagged_adjoint,
                                                            regressors=lambda B: np.stack([lagged(b) for b in B])),
                                 T, T)
    rng = np.random.default_rng(4)
    X = 0.1 * rng.standard_normal((5, 2 * T))
    X[1, :T] = 0.0
    X[2, T:] = 0.0
    X[3, T:] = -low.C0[:, 0]  # C = 0
    got = low.thetas(X)
    assert got[3] is None
    for i in (0, 1, 2, 4):
        np.testing.assert_array_equal(got[i], low.fit(X[i, :T], X[i, T:]).theta)
