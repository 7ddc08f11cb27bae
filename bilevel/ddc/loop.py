"""Closed-loop characteristic polynomial of plant + linearly parametrized controller, affine in theta.

p(z; theta) = den_G D + num_G (theta' N): its roots are the closed-loop poles. Gives the spectral
radius, a smooth surrogate (log-sum-exp of pole moduli) with its theta-gradient, and an ARX
least-squares fit that an attacker who does not know the plant can use as its model.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..errors import InvalidData, RankDeficientRegressor
from .bases import Basis, basis_polynomials
from .systems import SystemLike, num_den


@dataclass(frozen=True)
class LoopPolynomial:
    """p(theta) = base + theta' slopes (coefficients, highest power first) of the closed loop."""

    base: np.ndarray
    slopes: np.ndarray

    @classmethod
    def of(cls, plant: SystemLike, basis: Basis) -> "LoopPolynomial":
        """The closed loop of `plant` with K = beta' theta (unit negative feedback)."""
        num_g, den_g = num_den(plant)
        nums, common = basis_polynomials(basis)
        base = np.polymul(den_g, common)
        slopes = [np.polymul(num_g, n) for n in nums]
        width = max(base.size, max(s.size for s in slopes))
        pad = lambda p: np.concatenate([np.zeros(width - p.size), p])  # noqa: E731
        return cls(pad(base), np.array([pad(s) for s in slopes]))

    def coefficients(self, theta: np.ndarray) -> np.ndarray:
        return self.base + np.asarray(theta, dtype=float) @ self.slopes

    def poles(self, theta: np.ndarray) -> np.ndarray:
        """Closed-loop poles (roots of p)."""
        c = self.coefficients(theta)
        return np.roots(c) if abs(c[0]) > 0 else np.roots(np.trim_zeros(c, "f"))

    def spectral_radius(self, theta: np.ndarray) -> float:
        """max |pole|; the loop is stable iff it is < 1."""
        return float(np.max(np.abs(self.poles(theta))))

    def surrogate(self, theta: np.ndarray, beta: float = 50.0) -> tuple[float, np.ndarray]:
        """Smooth max of pole moduli, (1/beta) log sum exp(beta |lambda_i|), and its gradient in theta."""
        c = self.coefficients(theta)
        lam = np.roots(c)
        mod = np.abs(lam)
        w = np.exp(beta * (mod - mod.max()))
        value = float(mod.max() + np.log(w.sum()) / beta)
        w /= w.sum()
        denom = _horner(np.polyder(c)[None, :], lam)[0]
        keep = (np.abs(denom) >= 1e-14) & (mod != 0)  # a multiple or zero root: no derivative, left out
        lam, mod, w, denom = lam[keep], mod[keep], w[keep], denom[keep]
        dlam = -_horner(self.slopes, lam) / denom  # d lambda_j / d theta_i, shape (n_theta, roots)
        return value, (np.real(np.conj(lam) * dlam) / mod) @ w


def _horner(polys: np.ndarray, x: np.ndarray) -> np.ndarray:
    """Every row of `polys` (coefficients, highest power first) at every point of x, shape (rows, points): Horner's
    rule as np.polyval evaluates it."""
    out = np.zeros((polys.shape[0], x.size), dtype=np.result_type(polys, x))
    for k in range(polys.shape[1]):
        out = out * x + polys[:, k:k + 1]
    return out


def fit_arx(u: np.ndarray, y: np.ndarray, na: int, nb: int, delay: int) -> tuple[np.ndarray, np.ndarray]:
    """Least-squares ARX model y_t + a_1 y_{t-1} + .. = b_0 u_{t-delay} + .. + b_{nb-1} u_{t-delay-nb+1}.

    Returns (num, den) in powers of z with den = z^na + a_1 z^(na-1) + ... (proper when delay >= 0 and
    na >= delay + nb - 1), fitted on zero initial conditions.
    """
    u, y = np.asarray(u, dtype=float), np.asarray(y, dtype=float)
    if u.shape != y.shape or u.ndim != 1:
        raise InvalidData(f"ARX data must be two 1-D signals of equal length, got {u.shape} and {y.shape}")
    if not all(isinstance(k, (int, np.integer)) and not isinstance(k, bool) for k in (na, nb, delay)) \
            or na < 0 or nb < 1 or delay < 0:
        raise InvalidData(f"ARX orders must be integers na >= 0, nb >= 1, delay >= 0, got {(na, nb, delay)}")
    if na < delay + nb - 1:
        raise InvalidData(f"ARX orders give an improper model: need na >= delay + nb - 1, got na={na}")
    n = u.size
    if n < na + nb or n <= delay + nb - 1:
        raise RankDeficientRegressor(f"{n} samples are too few for an ARX model with na={na}, nb={nb}, "
                                     f"delay={delay} ({na + nb} parameters); record a longer experiment")
    shift = lambda x, k: np.concatenate([np.zeros(k), x[: n - k]])  # noqa: E731
    cols = [-shift(y, i) for i in range(1, na + 1)] + [shift(u, delay + j) for j in range(nb)]
    X = np.column_stack(cols)
    sol, _, rank, _ = np.linalg.lstsq(X, y, rcond=None)
    if rank < X.shape[1]:
        raise RankDeficientRegressor(f"ARX regressor has rank {rank} < {X.shape[1]}: the data do not excite "
                                     "the model orders; lower na/nb or use a richer input")
    den = np.concatenate([[1.0], sol[:na]])
    num_shifted = np.zeros(na + 1)
    for j in range(nb):  # b_j u_{t-delay-j}  ->  b_j z^(na - delay - j)
        num_shifted[delay + j] += sol[na + j]
    return np.trim_zeros(num_shifted, "f"), den


def arx_orders_for(u: np.ndarray, y: np.ndarray, max_order: int = 6) -> tuple[int, int, int]:
    """(na, nb, delay) with na <= max_order whose ARX fit has full rank and the least AIC, N log(rss/N) + 2 k.

    rss is floored at 1e-10 ||y||^2 so that on noise-free data the smallest exact model wins.
    """
    u, y = np.asarray(u, dtype=float), np.asarray(y, dtype=float)
    floor = 1e-10 * float(y @ y) + 1e-300
    best: tuple[float, tuple[int, int, int]] | None = None
    for na in range(1, max_order + 1):
        for delay in range(na + 1):
            for nb in range(1, na - delay + 2):
                try:
                    num, den = fit_arx(u, y, na, nb, delay)
                except RankDeficientRegressor:
                    continue
                rss = float(np.sum((y - _arx_prediction(u, y, num, den)) ** 2))
                aic = u.size * np.log(max(rss, floor) / u.size) + 2 * (na + nb)
                if best is None or aic < best[0] - 1e-9:
                    best = (aic, (na, nb, delay))
    if best is None:
        raise RankDeficientRegressor(f"no ARX orders up to na = {max_order} have a full-rank regressor on these "
                                     "data; use a richer input")
    return best[1]


def _arx_prediction(u: np.ndarray, y: np.ndarray, num: np.ndarray, den: np.ndarray) -> np.ndarray:
    """One-step-ahead ARX prediction of y (zero initial conditions)."""
    na = den.size - 1
    b = np.concatenate([np.zeros(na + 1 - num.size), num])  # b[k] multiplies u_{t-k}
    return np.convolve(u, b)[: u.size] - np.convolve(y, np.concatenate([[0.0], den[1:]]))[: y.size]
