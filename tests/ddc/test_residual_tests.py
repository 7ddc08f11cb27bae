"""The defender's residual tests: statistics equal their textbook formulas computed here independently (loops,
Kronecker forms, normal equations), p-values equal the incomplete gamma/beta functions, and on clean simulated data
the tests reject at 5% in 5% of data sets (within a binomial interval)."""

from __future__ import annotations

import numpy as np
import pytest
from scipy import special, stats

from bilevel.ddc.data import state_trajectory
from bilevel.ddc.residual_tests import input_test, regression_tests, variance_test, whiteness_test
from bilevel.errors import InvalidData
from bilevel.problems.identification_instance import IdentificationSetting, flexible_transmission_setting


def ljung_box(e: np.ndarray, lags: int) -> float:
    """Ljung & Box (1978), eq. (2.3): N (N + 2) sum_k r_k^2 / (N - k), r_k = sum_{t>k} e_t e_{t-k} / sum_t e_t^2."""
    N = e.size
    r = [sum(e[t] * e[t - k] for t in range(k, N)) / sum(v * v for v in e) for k in range(1, lags + 1)]
    return N * (N + 2) * sum(r[k - 1] ** 2 / (N - k) for k in range(1, lags + 1))


def hosking(E: np.ndarray, lags: int) -> float:
    """Hosking (1980), eq. (1.4) in its vec form: N^2 sum_j vec(C_j)' (C_0^-1 kron C_0^-1) vec(C_j) / (N - j), with
    C_j = (1/N) sum_{t=j}^{N-1} e_t e_{t-j}' summed sample by sample."""
    N = E.shape[1]
    C = [sum(np.outer(E[:, t], E[:, t - j]) for t in range(j, N)) / N for j in range(lags + 1)]
    W = np.kron(np.linalg.inv(C[0]), np.linalg.inv(C[0]))
    return N ** 2 * sum(C[j].ravel("F") @ W @ C[j].ravel("F") / (N - j) for j in range(1, lags + 1))


def test_whiteness_statistic_is_hosking_and_ljung_box() -> None:
    rng = np.random.default_rng(0)
    E = rng.standard_normal((3, 80))
    t = whiteness_test(E, 6)
    assert t.statistic == pytest.approx(hosking(E, 6), rel=1e-12)
    assert t.dof == (3 * 3 * 6,)
    assert t.p_value == pytest.approx(special.gammaincc(t.dof[0] / 2, t.statistic / 2), rel=1e-10)
    e = E[0]
    one = whiteness_test(e, 6)
    assert one.statistic * (e.size + 2) / e.size == pytest.approx(ljung_box(e, 6), rel=1e-12)


def test_variance_statistic_and_two_sided_p_value() -> None:
    rng = np.random.default_rng(1)
    E = 0.1 * rng.standard_normal((2, 50))
    t = variance_test(E, 0.1, n_regressors=3)
    assert t.statistic == pytest.approx(sum(v * v for v in E.ravel()) / 0.01, rel=1e-12)
    assert t.dof == (2 * (50 - 3),)
    lower = special.gammainc(t.dof[0] / 2, t.statistic / 2)  # chi-square cdf
    assert t.p_value == pytest.approx(2 * min(lower, 1 - lower), rel=1e-10)
    assert variance_test(3 * E, 0.1, 3).p_value < 1e-10  # an inflated residual is rejected
    assert variance_test(E / 3, 0.1, 3).p_value < 1e-10  # and a deflated one


def test_input_f_statistic_by_normal_equations() -> None:
    rng = np.random.default_rng(2)
    Z = rng.standard_normal((4, 60))
    Y = np.array([[1.0, -0.5, 0.2, 0.05], [0.3, 0.1, -0.2, 0.0]]) @ Z + 0.3 * rng.standard_normal((2, 60))
    theta = np.linalg.solve(Z @ Z.T, Z @ Y.T).T
    t = input_test(Y, Z, theta, [2, 3])
    Zr = Z[:2]
    theta_r = np.linalg.solve(Zr @ Zr.T, Zr @ Y.T).T
    rss, rss0 = np.sum((Y - theta @ Z) ** 2), np.sum((Y - theta_r @ Zr) ** 2)
    f = ((rss0 - rss) / 4) / (rss / (2 * (60 - 4)))
    assert t.statistic == pytest.approx(f, rel=1e-10) and t.dof == (4, 112)
    d1, d2 = t.dof
    assert t.p_value == pytest.approx(special.betainc(d2 / 2, d1 / 2, d2 / (d2 + d1 * f)), rel=1e-8)


def test_bad_inputs_are_refused() -> None:
    with pytest.raises(InvalidData, match="lags"):
        whiteness_test(np.ones((1, 5)), 5)
    with pytest.raises(InvalidData, match="finite"):
        variance_test(np.array([1.0, np.nan]), 0.1, 0)
    with pytest.raises(InvalidData, match="input test"):
        input_test(np.ones((1, 10)), np.ones((2, 10)), np.ones((1, 3)), [1])


def rejection_rates(learner: str, data_sets: int, T: int = 200, lags: int = 10) -> dict[str, float]:
    """Share of clean data sets on which each test rejects at 5%: the flexible transmission's own model for the
    variance and whiteness tests; for the input test, data whose outputs do not depend on the input (its null)."""
    rng = np.random.default_rng(7)
    setting = flexible_transmission_setting()
    null = IdentificationSetting(np.zeros(1), setting.den)
    A, _ = setting.state_space
    counts = dict.fromkeys(("variance", "whiteness", "input"), 0)
    for _ in range(data_sets):
        if learner == "ss":
            X, U = setting.state_data(T, rng)
            Y, Z, rows = X[:, 1:], np.vstack([X[:, :-1], U]), [4]
            X0 = state_trajectory(A, np.eye(4), 0.1 * rng.standard_normal((4, T)))
            Y0, Z0 = X0[:, 1:], np.vstack([X0[:, :-1], rng.standard_normal((1, T))])
        else:
            (u, y), (u0, y0) = setting.arx_data(T, rng), null.arx_data(T, rng)
            lagged = lambda u, y: np.array([[-y[t - i] for i in range(1, 5)] + [u[t - j] for j in range(1, 5)]  # noqa: E731
                                            for t in range(4, T)]).T
            Y, Z, Y0, Z0, rows = y[None, 4:], lagged(u, y), y0[None, 4:], lagged(u0, y0), [4, 5, 6, 7]
        fit = lambda Y, Z: np.linalg.lstsq(Z.T, Y.T, rcond=None)[0].T  # noqa: E731
        tests = regression_tests(Y, Z, fit(Y, Z), rows, 0.1, lags)
        counts["variance"] += tests["variance"].rejects()
        counts["whiteness"] += tests["whiteness"].rejects()
        counts["input"] += input_test(Y0, Z0, fit(Y0, Z0), rows).rejects()
    return {k: v / data_sets for k, v in counts.items()}


@pytest.mark.parametrize("learner", ["ss", "arx"])
def test_p_values_are_calibrated_on_clean_data(learner: str) -> None:
    """400 clean data sets (T = 200): each test's rejection rate at 5% lies in the 99.9% binomial interval of 5%."""
    data_sets = 400
    low, high = stats.binom.interval(0.999, data_sets, 0.05)
    rates = rejection_rates(learner, data_sets)
    for name, rate in rates.items():
        assert low / data_sets <= rate <= high / data_sets, (name, rates)


# -- degenerate inputs (issue 44, item 4): a correct limit or a named error, never NaN or a traceback ------------------
@pytest.mark.parametrize("scale", [1e-200, 1e200])
def test_statistics_do_not_depend_on_the_data_scale(scale: float) -> None:
    """At 1e-200 the squares underflowed (ZeroDivisionError, a singular R_0), at 1e200 they overflowed (NaN p-values):
    the statistics are invariant to the scale and are now computed in the data's own units."""
    rng = np.random.default_rng(5)
    Z = rng.standard_normal((4, 90))
    Theta = np.array([[0.5, -0.2, 1.0, 0.3], [0.1, 0.4, -0.3, 0.2]])
    Y = Theta @ Z + 0.2 * rng.standard_normal((2, 90))
    Theta = np.linalg.lstsq(Z.T, Y.T, rcond=None)[0].T
    base = regression_tests(Y, Z, Theta, [2, 3], 0.2, 5)
    scaled = regression_tests(scale * Y, Z, scale * Theta, [2, 3], 0.2 * scale, 5)
    for name, test in base.items():
        assert scaled[name].statistic == pytest.approx(test.statistic, rel=1e-10)
        assert 0.0 <= scaled[name].p_value <= 1.0


def test_exact_fits_give_the_tests_limits() -> None:
    """Zero residuals: the variance statistic is 0 (p-value 0, a residual far too small for the noise); the input
    test's full model exact and its restriction not: F = inf (p-value 0); both exact, or a zero output for the
    whiteness test: a named error."""
    rng = np.random.default_rng(6)
    Z = rng.standard_normal((3, 40))
    Theta = np.array([[1.0, -0.5, 2.0]])
    Y = Theta @ Z
    variance = variance_test(Y - Theta @ Z, 0.1, 3)
    assert variance.statistic == 0.0 and variance.p_value == 0.0
    f = input_test(Y, Z, Theta, [2])
    assert f.statistic == np.inf and f.p_value == 0.0
    with pytest.raises(InvalidData, match="both the model and its restriction"):
        input_test(Theta[:, :2] @ Z[:2], Z, np.array([[1.0, -0.5, 0.0]]), [2])
    with pytest.raises(InvalidData, match="all zero"):
        whiteness_test(np.zeros((1, 40)), 3)
