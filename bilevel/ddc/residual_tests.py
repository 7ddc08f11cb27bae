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
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Callable

import numpy as np
from scipy import stats

from ..errors import InvalidData


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

    @property
    def p_value(self) -> float:
        """The p-value of the statistic under the test's reference distribution (P_VALUES)."""
        return P_VALUES[self.name](self.statistic, *self.dof)

    def rejects(self, level: float = 0.05) -> bool:
        """Whether the test rejects its null hypothesis (a well-fitted model) at significance `level`."""
        return self.p_value < level


def _matrix(a: np.ndarray, name: str) -> np.ndarray:
    a = np.asarray(a, dtype=float)
    a = a[None, :] if a.ndim == 1 else a
    if a.ndim != 2 or not np.all(np.isfinite(a)):
        raise InvalidData(f"{name} must be a finite vector or matrix (rows x samples), got shape {a.shape}")
    return a


def variance_test(residuals: np.ndarray, noise_std: float, n_regressors: int) -> ResidualTest:
    """Chi-square test of ||E||_F^2 / sigma^2 against n (N - k) degrees of freedom (two-sided)."""
    E = _matrix(residuals, "residuals")
    n, N = E.shape
    dof = n * (N - n_regressors)
    if dof < 1 or not noise_std > 0:
        raise InvalidData(f"variance test: needs N > k samples ({N} for {n_regressors} regressors) and noise_std > 0")
    return ResidualTest("variance", float(np.sum(E ** 2)) / noise_std ** 2, (dof,))


def autocovariances(residuals: np.ndarray, lags: int) -> list[np.ndarray]:
    """R_0 .. R_s, R_j = (1/N) sum_{t=j}^{N-1} e_t e_{t-j}' (n x n each)."""
    E = _matrix(residuals, "residuals")
    N = E.shape[1]
    return [E[:, j:] @ E[:, :N - j].T / N for j in range(lags + 1)]


def whiteness_test(residuals: np.ndarray, lags: int) -> ResidualTest:
    """Portmanteau test Q = N^2 sum_j tr(R_j' R_0^-1 R_j R_0^-1) / (N - j) against n^2 s degrees of freedom."""
    E = _matrix(residuals, "residuals")
    n, N = E.shape
    if not 0 < lags < N:
        raise InvalidData(f"whiteness test: needs 0 < lags < N, got lags={lags} for N={N} samples")
    R = autocovariances(E, lags)
    inv0 = np.linalg.inv(R[0])
    q = N ** 2 * sum(np.trace(R[j].T @ inv0 @ R[j] @ inv0) / (N - j) for j in range(1, lags + 1))
    return ResidualTest("whiteness", float(q), (n * n * lags,))


def input_test(Y: np.ndarray, Z: np.ndarray, Theta: np.ndarray, input_rows: list[int] | np.ndarray) -> ResidualTest:
    """F-test that the rows `input_rows` of Z contribute to Y ~ Theta Z (the restricted model refitted without them)."""
    Y, Z, Theta = _matrix(Y, "Y"), _matrix(Z, "Z"), _matrix(Theta, "Theta")
    (n, N), k = Y.shape, Z.shape[0]
    q = len(input_rows)
    if Z.shape[1] != N or Theta.shape != (n, k) or not 0 < q < k or N <= k:
        raise InvalidData(f"input test: shapes Y {Y.shape}, Z {Z.shape}, Theta {Theta.shape} and {q} input rows do "
                          "not fit Y ~ Theta Z with N > k samples and 0 < q < k")
    rss = float(np.sum((Y - Theta @ Z) ** 2))
    rest = np.delete(Z, input_rows, axis=0)
    theta0 = np.linalg.lstsq(rest.T, Y.T, rcond=None)[0].T
    rss0 = float(np.sum((Y - theta0 @ rest) ** 2))
    d1, d2 = n * q, n * (N - k)
    return ResidualTest("input", ((rss0 - rss) / d1) / (rss / d2), (d1, d2))


def regression_tests(Y: np.ndarray, Z: np.ndarray, Theta: np.ndarray, input_rows: list[int] | np.ndarray,
                     noise_std: float, lags: int) -> dict[str, ResidualTest]:
    """The three tests of the model Theta on data (Y, Z): variance, whiteness and input, by name."""
    Y, Z, Theta = _matrix(Y, "Y"), _matrix(Z, "Z"), _matrix(Theta, "Theta")
    E = Y - Theta @ Z
    return {"variance": variance_test(E, noise_std, Z.shape[0]), "whiteness": whiteness_test(E, lags),
            "input": input_test(Y, Z, Theta, input_rows)}
