"""Global maximization of a quadratic over a Euclidean ball (the trust-region subproblem), any curvature.

maximize v'Av + 2 b'v  s.t. ||v|| <= delta, A symmetric (k x k, small). Global optimality
(Moré & Sorensen 1983): (mu I - A) v = b, mu I - A >= 0, mu >= 0, mu (delta - ||v||) = 0. Solved by
an eigendecomposition and the secular equation ||v(mu)|| = delta, with the hard case handled.
"""

from __future__ import annotations

import math

import numpy as np


def maximize_quadratic_on_ball(A: np.ndarray, b: np.ndarray, delta: float,
                               prefer: np.ndarray | None = None) -> np.ndarray:
    """Global maximizer of v'Av + 2b'v over ||v|| <= delta. In the hard case the maximizers are v_hat + t q for
    every unit q of A's top eigenspace: the one along prefer's part in that space is returned (the eigensolver's
    own choice only where prefer has none), so the answer does not depend on the sign a LAPACK kernel picks."""
    A = 0.5 * (np.asarray(A, dtype=float) + np.asarray(A, dtype=float).T)
    b = np.asarray(b, dtype=float)
    if delta <= 0:
        return np.zeros_like(b)
    lam, Q = np.linalg.eigh(A)
    beta = Q.T @ b
    top = lam[-1]
    scale = max(1.0, float(np.abs(lam).max()), float(np.linalg.norm(b)) / delta)
    tiny = 1e-13 * scale

    def v_of(mu: float) -> np.ndarray:
        return Q @ (beta / (mu - lam))

    if top < -tiny:  # strictly concave: the unconstrained maximizer may be inside the ball
        v0 = v_of(0.0)
        if np.linalg.norm(v0) <= delta:
            return v0
    lo = max(top, 0.0)
    on_top = np.abs(lam - top) <= tiny
    if np.linalg.norm(beta[on_top]) <= 1e-12 * max(1.0, float(np.linalg.norm(beta))):  # possible hard case
        rest = ~on_top
        v_hat = Q[:, rest] @ (beta[rest] / (lo - lam[rest])) if np.any(rest) else np.zeros_like(b)
        slack = delta ** 2 - float(v_hat @ v_hat)
        if slack >= 0 and top >= 0:
            q = Q[:, -1]
            if prefer is not None:
                along = Q[:, on_top] @ (Q[:, on_top].T @ np.asarray(prefer, dtype=float))
                if np.linalg.norm(along) > 1e-8 * np.linalg.norm(prefer):
                    q = along / np.linalg.norm(along)
            return v_hat + np.sqrt(slack) * q
    # Newton on psi(mu) = 1/delta - 1/||v(mu)||, concave and increasing on (lo, inf): from a point left of
    # the root the iterates increase monotonically to it (More & Sorensen 1983).
    c2 = beta ** 2
    mu = lo + max(tiny, 1e-300)
    if float(np.sqrt(c2 @ (1.0 / (mu - lam) ** 2))) < delta:  # root left of mu: only in the near-hard case
        return v_of(mu) * (delta / max(float(np.linalg.norm(v_of(mu))), 1e-300))
    pairs = list(zip(c2.tolist(), lam.tolist()))  # k is small: plain floats beat numpy calls here
    for _ in range(100):
        norm2 = dnorm2 = 0.0
        for c, l in pairs:
            inv = 1.0 / (mu - l)
            norm2 += c * inv * inv
            dnorm2 += c * inv * inv * inv
        norm = math.sqrt(norm2)
        psi = 1.0 / delta - 1.0 / norm
        step = psi * norm2 * norm / dnorm2  # -psi / psi' with psi' = -dnorm2 / norm^3
        mu += step
        if abs(step) <= 1e-15 * max(1.0, abs(mu)) or abs(psi) <= 1e-15 / delta:
            break
    v = v_of(mu)  # Newton approaches the root from the left, where ||v(mu)|| >= delta: land on the sphere
    return v * min(1.0, delta / max(float(np.linalg.norm(v)), 1e-300))
