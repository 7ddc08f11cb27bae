"""Small dense linear algebra over a batch (a leading axis of instances), as numpy operations on stacked arrays:
thin QR, triangular solves, the trust-region subproblem and the l2-ball projection, each the batched form of the
one-instance step (bilevel.lower.least_squares.thin_qr, bilevel.solvers.engine.trust_region, the l2 NormBall). The
arithmetic is the same up to rounding (stacked LAPACK calls and reductions sum in another order); rows whose
trust-region subproblem is in the hard or near-hard case are handed to the one-instance solver.

Besides einsum (each use a batched matmul or vecdot of the array-API standard), the operations on the batch are the
standard's (matmul, linalg.eigh, sum, sqrt, where), so a GPU array library could run the same code later; the QR is a
loop of LAPACK geqrf calls on the CPU (in place, no Q formed: 1.6x faster than Cholesky QR2 from matmuls at 32 rows of
512 x 6), for which such a library would call its batched linalg.qr of [C d].
"""

from __future__ import annotations

import numpy as np
import scipy.linalg

from .trust_region import maximize_quadratic_on_ball

_GEQRF = scipy.linalg.lapack.dgeqrf


def r_factor_batch(C: np.ndarray, d: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(R, R^{-1}, Q'd) of the thin QR of each tall C[i] (rows > k) with d[i]: Householder's (geqrf, as thin_qr) on
    [C d], whose top k x (k + 1) block is [R Q'd]; R^{-1} of the identity where R is singular or not finite."""
    m, rows, k = C.shape
    A = np.empty((m, k + 1, rows))  # each A[i].T a Fortran-ordered rows x (k + 1) matrix: geqrf works on it in place
    A[:, :k] = np.swapaxes(C, 1, 2)
    A[:, k] = d
    top = np.empty((m, k, k + 1))
    for i in range(m):
        top[i] = _GEQRF(A[i].T, overwrite_a=1)[0][:k]
    R = np.triu(top[:, :, :k])
    ok = np.all(np.diagonal(R, axis1=1, axis2=2) != 0, axis=1) & np.all(np.isfinite(R.reshape(m, -1)), axis=1)
    return R, inverse_upper(np.where(ok[:, None, None], R, np.eye(k))), top[:, :, k]


def solve_upper(R: np.ndarray, rhs: np.ndarray) -> np.ndarray:
    """R[i]^{-1} rhs[i] for upper-triangular R (m, k, k) and rhs (m, k) or (m, k, p), by back-substitution over k
    (vectorized across the batch)."""
    k = R.shape[-1]
    x = np.array(rhs, dtype=float, copy=True)
    vector = x.ndim == 2
    if vector:
        x = x[..., None]
    for i in range(k - 1, -1, -1):
        if i < k - 1:
            x[:, i] -= np.einsum("mj,mjp->mp", R[:, i, i + 1:], x[:, i + 1:])
        x[:, i] /= R[:, i, i, None]
    return x[..., 0] if vector else x


def inverse_upper(R: np.ndarray) -> np.ndarray:
    """R[i]^{-1} of each upper-triangular R (m, k, k)."""
    eye = np.broadcast_to(np.eye(R.shape[-1]), R.shape)
    return solve_upper(R, eye)


def project_l2_balls(D: np.ndarray, radius: np.ndarray) -> np.ndarray:
    """Each row of D projected on the l2 ball of its radius about 0 (NormBall(radius, 2) row by row)."""
    norm = np.sqrt(np.sum(D * D, axis=1))
    shrink = np.where(norm <= radius, 1.0, radius / np.where(norm > 0, norm, 1.0))
    return D * shrink[:, None]


def maximize_quadratics_on_balls(A: np.ndarray, b: np.ndarray, delta: np.ndarray) -> np.ndarray:
    """The global maximizer of v'A[i]v + 2 b[i]'v over ||v|| <= delta[i] for each i (trust_region's
    maximize_quadratic_on_ball, no `prefer`): one batched eigendecomposition, the interior maximizer of a strictly
    concave quadratic where it lies in the ball, else Newton on the secular equation for every row at once; rows in the
    hard or near-hard case go to the one-instance solver."""
    A = 0.5 * (A + np.swapaxes(A, 1, 2))
    out = np.zeros_like(b)
    lam, Q = np.linalg.eigh(A)
    beta = np.einsum("mji,mj->mi", Q, b)
    top = lam[:, -1]
    positive = delta > 0
    scale = np.maximum(np.maximum(1.0, np.abs(lam).max(axis=1)),
                       np.sqrt(np.sum(b * b, axis=1)) / np.where(positive, delta, 1.0))
    tiny = 1e-13 * scale
    done = ~positive  # delta 0: v = 0
    concave = positive & (top < -tiny)
    if concave.any():  # strictly concave: the unconstrained maximizer, where it lies inside the ball
        v0 = np.einsum("mij,mj->mi", Q, beta / (0.0 - np.where(concave[:, None], lam, -1.0)))
        inside = concave & (np.sqrt(np.sum(v0 * v0, axis=1)) <= delta)
        out[inside] = v0[inside]
        done |= inside
    on_top = np.abs(lam - top[:, None]) <= tiny[:, None]
    beta_norm = np.sqrt(np.sum(beta * beta, axis=1))
    hard = np.sqrt(np.sum(np.where(on_top, beta, 0.0) ** 2, axis=1)) <= 1e-12 * np.maximum(1.0, beta_norm)
    lo = np.maximum(top, 0.0)
    mu = lo + np.maximum(tiny, 1e-300)
    c2 = beta ** 2
    with np.errstate(divide="ignore", invalid="ignore"):
        norm0 = np.sqrt(np.sum(c2 / (mu[:, None] - lam) ** 2, axis=1))
    single = ~done & (hard | ~(norm0 >= delta))  # a possible hard case; the root left of mu (near-hard)
    easy = np.flatnonzero(~done & ~single)
    if easy.size:
        mu_e, lam_e, c2_e, d_e = mu[easy], lam[easy], c2[easy], delta[easy]
        live = np.ones(easy.size, dtype=bool)
        for _ in range(100):  # Newton on psi(mu) = 1/delta - 1/||v(mu)|| from the left of the root, per row
            inv = 1.0 / (mu_e[:, None] - lam_e)
            weighted = c2_e * inv * inv
            norm2, dnorm2 = weighted.sum(axis=1), (weighted * inv).sum(axis=1)
            norm = np.sqrt(norm2)
            psi = 1.0 / d_e - 1.0 / norm
            step = np.where(live, psi * norm2 * norm / dnorm2, 0.0)  # a row that stopped keeps its mu
            mu_e += step
            live &= (np.abs(step) > 1e-15 * np.maximum(1.0, np.abs(mu_e))) & (np.abs(psi) > 1e-15 / d_e)
            if not live.any():
                break
        v = np.einsum("mij,mj->mi", Q[easy], beta[easy] / (mu_e[:, None] - lam_e))
        vn = np.sqrt(np.sum(v * v, axis=1))
        out[easy] = v * np.minimum(1.0, d_e / np.maximum(vn, 1e-300))[:, None]
    for i in np.flatnonzero(single):
        out[i] = maximize_quadratic_on_ball(A[i], b[i], float(delta[i]))
    return out
