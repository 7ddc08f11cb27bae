"""The defender's tests of an identified linear model Y ~ Theta Z (outputs x samples), from its residuals E = Y - Theta Z.

- variance: V = ||E||_F^2 / sigma^2 with the known noise std sigma, chi-square with n (N - k) degrees of freedom
  (n outputs, N samples, k regressors); two-sided p-value (poisoning may inflate or deflate the residual).
- whiteness: the multivariate portmanteau statistic of the residual autocovariances R_j = (1/N) sum_t e_t e_{t-j}'
  over lags j = 1..s, Q = N^2 sum_j tr(R_j' R_0^-1 R_j R_0^-1) / (N - j) (Hosking 1980; for one output the Ljung-Box
  statistic with N^2 for N (N + 2), Ljung 1999 sec. 16.6), chi-square with n^2 s degrees of freedom; upper-tail
  p-value. Box and Pierce's reduction by the fitted output lags holds only once the model's impulse response has died
  out within s lags, which a lightly damped plant (the flexible transmission's poles have modulus 0.976) needs far
  more lags for: without it the test is calibrated on such data (tests/ddc/test_residual_tests.py).
- input: the F-test that the input rows of Z contribute, F = ((RSS_0 - RSS) / (n q)) / (RSS / (n (N - k))) with RSS_0
  the residual sum of squares of the least-squares refit without the q input rows; upper-tail p-value of F(nq, n(N-k)).

Each statistic is computed in the data's own units (residuals over sigma, each output's residuals over their RMS, Y
over its largest entry): the statistics are invariant to that scaling, and data at 1e-200 or 1e200 neither underflow
nor overflow. Limits: a zero residual is a variance statistic of 0 (p-value 0: far too small a residual for the
noise); an exact fit of the full model (residuals below EXACT of max|Y|) where the restricted one leaves a residual
is F = inf (p-value 0); where the statistic is undefined (an output whose residuals are all zero, linearly dependent
outputs so that R_0 is singular, both F models exact) the test raises InvalidData naming why, never a NaN p-value;
a negative or float count, duplicate or out-of-range input rows and an infinite noise_std are ModelError or
InvalidData naming the argument.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Callable

import numpy as np
from scipy import stats

from ..errors import InvalidData
from ..real_data import integer, real_array


def _two_sided_chi2(v: float, dof: int) -> float:
    """The two-sided chi-square p-value of v."""
    return float(min(1.0, 2 * min(stats.chi2.cdf(v, dof), stats.chi2.sf(v, dof))))


P_VALUES: dict[str, Callable[..., float]] = {
    "variance": _two_sided_chi2, "whiteness": lambda q, dof: float(stats.chi2.sf(q, dof)),
    "input": lambda f, d1, d2: float(stats.f.sf(f, d1, d2))}
"""Each test's p-value from its statistic and degrees of freedom (the module docstring's tails)."""


@dataclass(frozen=True)
class ResidualTest:
    """One test's statistic, its reference distribution's degrees of freedom and (computed when read) the p-value:
    the stealth constraints' clean values need the statistics alone."""

    name: str
    statistic: float
    dof: tuple[int, ...]

    def __post_init__(self) -> None:
        if np.isnan(self.statistic):
            raise InvalidData(f"{self.name} test: the statistic is NaN; check the residuals and the model")

    @property
    def p_value(self) -> float:
        """The p-value of the statistic under the test's reference distribution (P_VALUES)."""
        return P_VALUES[self.name](self.statistic, *self.dof)

    def rejects(self, level: float = 0.05) -> bool:
        """Whether the test rejects its null hypothesis (a well-fitted model) at significance `level`."""
        return self.p_value < level


def _matrix(a: np.ndarray, name: str) -> np.ndarray:
    a = real_array(a, name)
    a = a[None, :] if a.ndim == 1 else a
    if a.ndim != 2 or not np.all(np.isfinite(a)):
        raise InvalidData(f"{name} must be a finite vector or matrix (rows x samples), got shape {a.shape}")
    return a


def variance_test(residuals: np.ndarray, noise_std: float, n_regressors: int) -> ResidualTest:
    """Chi-square test of ||E||_F^2 / sigma^2 against n (N - k) degrees of freedom (two-sided)."""
    E = _matrix(residuals, "residuals")
    n, N = E.shape
    k = integer(n_regressors, "variance test: n_regressors", 0)
    if not (isinstance(noise_std, (int, float, np.integer, np.floating)) and not isinstance(noise_std, bool)
            and np.isfinite(noise_std) and noise_std > 0):
        raise InvalidData(f"variance test: noise_std={noise_std!r} is invalid: it must be a finite number > 0 (the "
                          "known noise standard deviation)")
    dof = n * (N - k)
    if dof < 1:
        raise InvalidData(f"variance test: needs N > k samples ({N} for {k} regressors)")
    return ResidualTest("variance", float(np.sum((E / noise_std) ** 2)), (dof,))


def autocovariances(residuals: np.ndarray, lags: int) -> list[np.ndarray]:
    """R_0 .. R_s, R_j = (1/N) sum_{t=j}^{N-1} e_t e_{t-j}' (n x n each)."""
    E = _matrix(residuals, "residuals")
    N = E.shape[1]
    return [E[:, j:] @ E[:, :N - j].T / N for j in range(lags + 1)]


SINGULAR = 2.0 ** -40
"""R_0 of outputs scaled to unit RMS (a correlation matrix) counts as singular below this smallest eigenvalue."""


def whiteness_test(residuals: np.ndarray, lags: int) -> ResidualTest:
    """Portmanteau test Q = N^2 sum_j tr(R_j' R_0^-1 R_j R_0^-1) / (N - j) against n^2 s degrees of freedom."""
    E = _matrix(residuals, "residuals")
    n, N = E.shape
    lags = integer(lags, "whiteness test: lags", 1)
    if not lags < N:
        raise InvalidData(f"whiteness test: needs 0 < lags < N, got lags={lags} for N={N} samples")
    peak = np.abs(E).max(axis=1)
    if np.any(peak == 0):
        raise InvalidData(f"whiteness test: the residuals of output(s) {np.flatnonzero(peak == 0).tolist()} are all "
                          "zero (an exact fit): their autocorrelation is undefined")
    scaled = E / peak[:, None]
    R = autocovariances(scaled / np.sqrt(np.mean(scaled ** 2, axis=1))[:, None], lags)  # Q is invariant to scaling
    if np.linalg.eigvalsh(R[0]).min() <= SINGULAR:
        raise InvalidData("whiteness test: R_0, the residuals' covariance, is singular (the outputs' residuals are "
                          "linearly dependent, e.g. a duplicated output): the portmanteau statistic is undefined; "
                          "test independent outputs")
    inv0 = np.linalg.inv(R[0])
    q = N ** 2 * sum(np.trace(R[j].T @ inv0 @ R[j] @ inv0) / (N - j) for j in range(1, lags + 1))
    return ResidualTest("whiteness", float(q), (n * n * lags,))


EXACT = 2.0 ** -40
"""A model whose residuals are below this fraction of max|Y| (in RMS) fits exactly (the input test's limits)."""


def input_test(Y: np.ndarray, Z: np.ndarray, Theta: np.ndarray, input_rows: list[int] | np.ndarray) -> ResidualTest:
    """F-test that the rows `input_rows` of Z contribute to Y ~ Theta Z (the restricted model refitted without them)."""
    Y, Z, Theta = _matrix(Y, "Y"), _matrix(Z, "Z"), _matrix(Theta, "Theta")
    (n, N), k = Y.shape, Z.shape[0]
    rows = [integer(i, "input test: an input row", 0) for i in np.ravel(np.asarray(input_rows, dtype=object))]
    if len(set(rows)) != len(rows) or any(i >= k for i in rows):
        raise InvalidData(f"input test: input_rows {rows} must be distinct rows of Z, each in 0 .. {k - 1}")
    q = len(rows)
    if Z.shape[1] != N or Theta.shape != (n, k) or not 0 < q < k or N <= k:
        raise InvalidData(f"input test: shapes Y {Y.shape}, Z {Z.shape}, Theta {Theta.shape} and {q} input rows do "
                          "not fit Y ~ Theta Z with N > k samples and 0 < q < k")
    scale = float(np.abs(Y).max()) or 1.0  # F is a ratio of sums of squares of Y's units: computed in units of max|Y|
    rss = float(np.sum(((Y - Theta @ Z) / scale) ** 2))
    rest = np.delete(Z, rows, axis=0)
    theta0 = np.linalg.lstsq(rest.T, (Y / scale).T, rcond=None)[0].T
    rss0 = float(np.sum((Y / scale - theta0 @ rest) ** 2))
    d1, d2 = n * q, n * (N - k)
    if rss <= EXACT ** 2 * n * N:  # a residual at rounding level: an exact fit
        if rss0 <= EXACT ** 2 * n * N:
            raise InvalidData("input test: both the model and its restriction without the input rows fit Y exactly: "
                              "the F statistic is 0 / 0")
        return ResidualTest("input", float("inf"), (d1, d2))
    return ResidualTest("input", ((rss0 - rss) / d1) / (rss / d2), (d1, d2))


def regression_tests(Y: np.ndarray, Z: np.ndarray, Theta: np.ndarray, input_rows: list[int] | np.ndarray,
                     noise_std: float, lags: int) -> dict[str, ResidualTest]:
    """The three tests of the model Theta on data (Y, Z): variance, whiteness and input, by name."""
    Y, Z, Theta = _matrix(Y, "Y"), _matrix(Z, "Z"), _matrix(Theta, "Theta")
    if Z.shape[1] != Y.shape[1] or Theta.shape != (Y.shape[0], Z.shape[0]):
        raise InvalidData(f"residual tests: shapes Y {Y.shape}, Z {Z.shape}, Theta {Theta.shape} do not fit "
                          "Y ~ Theta Z")
    E = Y - Theta @ Z
    return {"variance": variance_test(E, noise_std, Z.shape[0]), "whiteness": whiteness_test(E, lags),
            "input": input_test(Y, Z, Theta, input_rows)}
