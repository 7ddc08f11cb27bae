"""Model-based control from an identified model (A, B), as numeric matrix functions with exact gradients for
BilevelProblem.maximize_matrix_function: the model's H2 norm, and the certainty-equivalence LQR gain (from the
discrete Riccati equation, differentiated implicitly) judged on a true plant by its closed loop's spectral radius.
Each takes the matrix M its problem declares and returns (value, d value / dM)."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import scipy.linalg

from bilevel.errors import InvalidData
from bilevel.spectral_radius import radius, spectral_radius


def _split(m: np.ndarray, blocks: int) -> tuple[int, int]:
    """(n, inputs) of M = [A B] (blocks = 1) or [A B A_true B_true] (blocks = 2), n = M's rows."""
    n, cols = m.shape
    inputs = cols // blocks - n
    if cols % blocks or inputs < 1:
        raise InvalidData(f"expected M = [A B]{' [A_true B_true]' if blocks == 2 else ''} with A n x n and B n x m, "
                          f"got shape {m.shape}")
    return n, inputs


def lqr_gain(a: np.ndarray, b: np.ndarray, q: np.ndarray, r: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(K, P): u = K x minimizes sum x'Qx + u'Ru on x+ = A x + B u; P the stabilizing solution of the discrete
    Riccati equation (scipy.linalg.solve_discrete_are), K = -(R + B'PB)^-1 B'PA."""
    p = scipy.linalg.solve_discrete_are(a, b, q, r)
    return -np.linalg.solve(r + b.T @ p @ b, b.T @ p @ a), p


@dataclass(frozen=True)
class H2Norm:
    """M = [A B] -> the H2 norm of x+ = A x + B u from u to x, sqrt(trace P) with P = A P A' + B B', and its
    gradient (one more Lyapunov solve, the adjoint's); inf with a NaN gradient where A is not Schur stable."""

    infinite = ("the identified model became unstable at the poisoning reached (A is not Schur stable): its H2 norm "
                "is infinite")
    """What an infinite value means, for the engine's message when an attack reaches one."""

    def __call__(self, m: np.ndarray) -> tuple[float, np.ndarray]:
        n, _ = _split(m, 1)
        a, b = m[:, :n], m[:, n:]
        if radius(a) >= 1:
            return float("inf"), np.full(m.shape, np.nan)
        p = scipy.linalg.solve_discrete_lyapunov(a, b @ b.T)
        y = scipy.linalg.solve_discrete_lyapunov(a.T, np.eye(n))  # d trace P = <Y, dA P A' + A P dA' + dB B' + B dB'>
        h2 = float(np.sqrt(np.trace(p)))
        return h2, np.hstack([y @ a @ p, y @ b]) / h2


@dataclass(frozen=True)
class CertaintyEquivalenceRadius:
    """M = [A B A_true B_true] -> rho(A_true + B_true K), K the LQR gain (weights Q, R) of the model (A, B), and its
    gradient in M. dK comes from the implicit function theorem on the Riccati equation: with Acl = A + B K,
    dP = Acl' dP Acl + dE' P Acl + Acl' P dE (dE = dA + dB K) and (R + B'PB) dK = -(dB' P Acl + B' dP Acl + B' P dE);
    the adjoint needs one discrete Lyapunov solve. NaN (value and gradient) where the Riccati equation has no
    stabilizing solution."""

    q: np.ndarray
    r: np.ndarray

    def __call__(self, m: np.ndarray) -> tuple[float, np.ndarray]:
        n, k = _split(m, 2)
        a, b, a_true, b_true = m[:, :n], m[:, n:n + k], m[:, n + k:2 * n + k], m[:, 2 * n + k:]
        try:
            gain, p = lqr_gain(a, b, self.q, self.r)
        except (np.linalg.LinAlgError, ValueError):
            return float("nan"), np.full(m.shape, np.nan)
        top = spectral_radius(a_true + b_true @ gain)
        g_gain = b_true.T @ top.gradient
        acl = a + b @ gain
        w = np.linalg.solve(self.r + b.T @ p @ b, g_gain)
        v = b @ w @ acl.T
        y = scipy.linalg.solve_discrete_lyapunov(acl, (v + v.T) / 2)  # the adjoint of dP's Stein equation
        g_e = -(p @ b @ w + 2 * p @ acl @ y)
        grad = np.hstack([g_e, -p @ acl @ w.T + g_e @ gain.T, top.gradient, top.gradient @ gain.T])
        return float(top.value), grad
