"""A least squares whose regressor and target are affine in the leader's signals, given as linear maps:

    theta*(a, b) = argmin_theta ||d0 + T a - (C0 + R(b)) theta||^2,   x = (a, b),

T (a -> target rows) and R (b -> regressor, rows x k) linear maps known by their products and adjoints (filters,
Toeplitz banks: O(rows k) per product, no rows x n matrix). The VRFT learner (T the prefilter on the regression rows,
R its filter bank) and ARX identification (T a slice of the outputs, R the lagged signals) are of this kind.

Solved by a thin QR of C = C0 + R(b); the implicit derivative of theta* by the adjoints of T and R; and for fixed b
the target block in closed form: theta*(B v, b) = theta_c + S v with ||B v|| = ||v||, so an upper objective quadratic
in theta over a ball on a is a trust-region subproblem in v of dimension k (bilevel.solvers.engine.affine_ls).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Callable

import numpy as np
import scipy.linalg
import scipy.linalg.lapack

from ..errors import RankDeficientRegressor
from .least_squares import factor_solve, thin_qr

Map = Callable[[np.ndarray], np.ndarray]


@dataclass(frozen=True)
class AffineMaps:
    """R, its adjoint G (rows x k) -> R'G, T and its adjoint (g a vector or columns); target None: T a = a[:rows];
    regressors: R of each row of a matrix of b's in one call, stacked (None: R row by row)."""

    regressor: Map
    regressor_adjoint: Map
    target: Map | None = None
    target_adjoint: Map | None = None
    regressors: Map | None = None


@dataclass
class Fit:
    """The learner's fit at x = (a, b): regressor C, target d, theta and the thin QR of C."""

    a: np.ndarray
    b: np.ndarray
    C: np.ndarray
    d: np.ndarray
    theta: np.ndarray
    R: np.ndarray
    Q: np.ndarray


@dataclass
class AffineLeastSquares:
    """theta*(a, b) of the module docstring, for n_a target signals and n_b regressor signals."""

    C0: np.ndarray
    d0: np.ndarray
    maps: AffineMaps
    n_a: int
    n_b: int

    def target(self, a: np.ndarray) -> np.ndarray:
        """T a."""
        return a[: self.d0.size] if self.maps.target is None else self.maps.target(a)

    def target_adjoint(self, g: np.ndarray) -> np.ndarray:
        """T'g for g a vector or columns (rows long)."""
        if self.maps.target is None:
            return np.concatenate([g, np.zeros((self.n_a - g.shape[0],) + g.shape[1:])])
        return self.maps.target_adjoint(g)

    def fit(self, a: np.ndarray, b: np.ndarray, d: np.ndarray | None = None,
            regressor: np.ndarray | None = None) -> Fit:
        """theta* at (a, b) (d: the target d0 + T a, regressor: R b, where known); RankDeficientRegressor if C has
        lower rank."""
        if d is None:
            d = self.d0 + self.target(a) if np.any(a) else self.d0
        if regressor is None and np.any(b):
            regressor = self.maps.regressor(b)
        C = self.C0 if regressor is None else self.C0 + regressor
        Q, R = thin_qr(C)
        theta, info = scipy.linalg.lapack.dtrtrs(R, Q.T @ d)  # R theta = Q'd (LAPACK directly: once per step)
        if info != 0:
            raise RankDeficientRegressor(f"the poisoned regressor has rank below {R.shape[1]} (R[{info - 1}, "
                                         f"{info - 1}] = 0): the least squares has no unique solution")
        return Fit(a, b, C, d, theta, R, Q)

    def thetas(self, X: np.ndarray) -> list[np.ndarray | None]:
        """theta* at each row x = (a, b) of X, as fit finds it (None where the regressor is rank deficient), the
        regressors of all rows by one call of maps.regressors where given."""
        X = np.atleast_2d(np.asarray(X, dtype=float))
        A, B = X[:, : self.n_a], X[:, self.n_a:]
        moving = [i for i, b in enumerate(B) if np.any(b)]
        known = dict(zip(moving, self.maps.regressors(B[moving]))) if self.maps.regressors is not None and moving \
            else {}
        out: list[np.ndarray | None] = []
        for i, (a, b) in enumerate(zip(A, B)):
            try:
                out.append(self.fit(a, b, regressor=known.get(i)).theta)
            except RankDeficientRegressor:
                out.append(None)
        return out

    def gradient(self, s: Fit, g_theta: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(dJ/da, dJ/db) at fit s for dJ/dtheta = g_theta, by implicit differentiation of the normal equations: with
        w = (C'C)^{-1} g_theta and r = d - C theta, dJ/da = T'(C w), dJ/db = R'(r w' - (C w) theta')."""
        w = factor_solve(s.R, g_theta)  # R'R = C'C
        cw = s.C @ w
        residual = s.d - s.C @ s.theta
        g_b = self.maps.regressor_adjoint(residual[:, None] * w - cw[:, None] * s.theta)
        return self.target_adjoint(cw), g_b

    def target_block(self, b: np.ndarray) -> tuple[Fit, np.ndarray, np.ndarray | None]:
        """(fit at (0, b), S, B): theta*(B v, b) = theta_c + S v with ||B v|| = ||v||, from W = T'Q:
        S = R^{-1} (W'W)^{1/2}, B = W (W'W)^{-1/2}; B None when T is a slice (W = [Q; 0], S = R^{-1}, a = [Q v; 0])."""
        s0 = self.fit(np.zeros(self.n_a), b, self.d0)
        if self.maps.target is None:
            return s0, scipy.linalg.lapack.dtrtri(s0.R)[0], None
        W = self.target_adjoint(s0.Q)
        lam, V = np.linalg.eigh(W.T @ W)
        lam = np.maximum(lam, 1e-14 * lam.max())
        return s0, scipy.linalg.solve_triangular(s0.R, (V * np.sqrt(lam)) @ V.T), W @ ((V / np.sqrt(lam)) @ V.T)

    def moved(self, s0: Fit, S: np.ndarray, B: np.ndarray | None, v: np.ndarray) -> Fit:
        """The fit at a = B v of the target block (s0, S, B) = target_block(b)."""
        if B is None:  # a = [Q v; 0] and T a = Q v
            qv = s0.Q @ v
            a = np.zeros(self.n_a)
            a[: qv.size] = qv
            d = s0.d + qv
        else:
            a = B @ v
            d = s0.d + self.target(a)
        return Fit(a, s0.b, s0.C, d, s0.theta + S @ v, s0.R, s0.Q)

    def gram_adjoint(self, b: np.ndarray, C: np.ndarray, v: np.ndarray) -> np.ndarray:
        """d(v'C'C v)/db at regressor C = C0 + R(b)."""
        return 2.0 * self.maps.regressor_adjoint(np.outer(C @ v, v))
