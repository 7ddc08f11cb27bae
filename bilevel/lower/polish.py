"""Polish an interior-point solution of a convex LP/QP/SDP lower level onto its optimal face.

An interior-point method stops at a duality gap eps; where strict complementarity fails (a constraint or
LMI eigenvalue active with a zero multiplier) y is then only accurate to ~sqrt(eps). Guessing the active
set from the solver's point and solving that face's KKT equations by Newton's method recovers y to
rounding. Only the lower level's data and the solver's point are used, and the result is kept only if
its KKT residual (stationarity, primal and dual feasibility, complementarity) is smaller than the solver's.
"""

from __future__ import annotations

from dataclasses import replace
from typing import TYPE_CHECKING

import numpy as np

from ..defaults import param
from ..threads import single_threaded_call
from ..vech import smat, svec
from .base import LowerSolution
from .convexity import psd_violation

if TYPE_CHECKING:  # pragma: no cover
    from .quadratic import QPData

Lmi = tuple[np.ndarray, np.ndarray]
"""(M0, d vec(M)/dy) of an LMI M(y) = M0 + sum_j y_j M_j >= 0 (column-major vec)."""


def _split(lmi: Lmi, n: int) -> tuple[np.ndarray, np.ndarray]:
    """(M0, M) with M[j] = dM/dy_j, both symmetrized, from (M0, d vec(M)/dy) (column-major vec)."""
    m0, jac = lmi
    s = m0.shape[0]
    mj = np.asarray(jac).reshape(s, s, n, order="F").transpose(2, 0, 1)
    return 0.5 * (m0 + m0.T), 0.5 * (mj + mj.transpose(0, 2, 1))


def _at(mat: tuple[np.ndarray, np.ndarray], y: np.ndarray) -> np.ndarray:
    """M(y) from _split's (M0, M)."""
    return mat[0] + np.tensordot(y, mat[1], 1)


def kkt_residual(d: QPData, lmis: tuple[Lmi, ...], sol: LowerSolution) -> float:
    """Largest absolute stationarity, primal/dual infeasibility and complementarity violation of sol."""
    n, y = d.q.size, sol.y
    mats = [_split(lmi, n) for lmi in lmis]
    stat = d.P @ y + d.q + d.A.T @ sol.lam + d.E.T @ sol.mu
    g = d.A @ y + d.b
    parts = [np.abs(g * sol.lam), np.maximum(g, 0.0), np.maximum(-sol.lam, 0.0), np.abs(d.E @ y + d.e)]
    for mat, z in zip(mats, sol.Z):
        m = _at(mat, y)
        stat = stat - np.einsum("jab,ab->j", mat[1], z)
        parts.append(np.array([psd_violation(m), psd_violation(z), abs(float(np.sum(z * m)))]))
    return max((float(np.max(p)) for p in [np.abs(stat), *parts] if p.size), default=0.0)


def _face(d: QPData, mats: list[tuple[np.ndarray, np.ndarray]], sol: LowerSolution, rows: np.ndarray,
          ranks: list[int]) -> LowerSolution:
    """Newton's method from sol on the KKT equations of one face: rows active, LMI k singular of rank deficit r_k.

    LMI k is held at U_k' M_k(y) U_k = 0, U_k the eigenvectors of the r_k smallest eigenvalues of the current
    M_k, with multiplier Z_k = U_k Lambda_k U_k'. Each step is a sequential-QP step: its Hessian adds the
    curvature of the null-space block (a Schur complement) to P, so convergence is quadratic also when
    Lambda_k != 0. Steps are increments solved by least squares, so a face with dependent constraints keeps
    the multipliers nearest to sol's.
    """
    n, y, mu, zs = d.q.size, sol.y.copy(), sol.mu.copy(), [0.5 * (z + z.T) for z in sol.Z]
    lam_a, na, ne = sol.lam[rows].copy(), rows.size, d.e.size
    cuts = np.cumsum([n, na, ne] + [r * (r + 1) // 2 for r in ranks])[:-1]
    size = np.inf
    for _ in range(param("polish.max_steps")):
        H, blocks, rhs, bases, lams = d.P.copy(), [], [], [], []
        for mat, r, z in zip(mats, ranks, zs):
            mj = mat[1]
            w, v = np.linalg.eigh(_at(mat, y))
            u = v[:, :r]
            lams.append(u.T @ z @ u)
            blocks.append(svec(u.T @ mj @ u).T)
            rhs.append(-svec(np.diag(w[:r])))
            bases.append(u)
            if 0 < r < w.size:  # second derivative of the Schur complement onto span(U) along M_j, M_l
                G = v[:, r:].T @ mj @ u
                H = H + 2.0 * G.reshape(n, -1) @ (G / w[r:, None] @ lams[-1]).reshape(n, -1).T
        C = np.vstack([d.A[rows], d.E, *blocks])
        signs = np.concatenate([np.ones(na + ne), -np.ones(C.shape[0] - na - ne)])
        mult = np.concatenate([lam_a, mu, *(svec(lam) for lam in lams)])
        K = np.block([[H, C.T * signs], [C, np.zeros((C.shape[0], C.shape[0]))]])
        b = np.concatenate([-(d.P @ y + d.q + C.T @ (signs * mult)), -(d.A[rows] @ y + d.b[rows]),
                            -(d.E @ y + d.e), *rhs])
        step = np.linalg.lstsq(K, b, rcond=None)[0]
        size, last = np.abs(step).max(initial=0.0), size
        if size > 0.5 * last:
            break  # down to rounding noise: quadratic convergence shrinks steps far faster
        dy, dlam, dmu, *dlams = np.split(step, cuts)
        y, lam_a, mu = y + dy, lam_a + dlam, mu + dmu
        zs = [u @ (lam + smat(dl, r)) @ u.T for u, lam, dl, r in zip(bases, lams, dlams, ranks)]
        if size <= 1e-15 * (1.0 + np.abs(np.concatenate([y, mult])).max()):
            break
    lam = np.zeros_like(sol.lam)
    lam[rows] = lam_a
    return replace(sol, y=y, objective=d.objective(y), lam=lam, mu=mu, Z=zs,
                   solver=sol.solver + "+polish")


def _flip(d: QPData, mats: list[tuple[np.ndarray, np.ndarray]], cand: LowerSolution, rows: np.ndarray,
          ranks: list[int]) -> tuple[np.ndarray, list[int]]:
    """The next face guess: add rows/LMI eigenvalues cand violates, drop those whose multiplier came out < 0."""
    g, scale = d.A @ cand.y + d.b, 1.0 + np.abs(d.A) @ np.abs(cand.y) + np.abs(d.b)
    active = np.zeros(d.b.size, dtype=bool)
    active[rows] = cand.lam[rows] >= -param("polish.flip_tol") * (1.0 + np.abs(cand.lam).max(initial=0.0))
    active |= g > param("polish.flip_tol") * scale
    new_ranks = []
    for mat, r, z in zip(mats, ranks, cand.Z):
        w, wz = np.linalg.eigvalsh(_at(mat, cand.y)), np.linalg.eigvalsh(z)
        grow = r < w.size and w[r] < -param("polish.flip_tol") * (1.0 + np.abs(w).max())
        shrink = r > 0 and wz[0] < -param("polish.flip_tol") * (1.0 + np.abs(wz).max())
        new_ranks.append(r + int(grow) - int(shrink and not grow))
    return np.flatnonzero(active), new_ranks


@single_threaded_call  # small dense linear algebra: threaded BLAS only adds overhead
def polish(d: QPData, lmis: tuple[Lmi, ...], sol: LowerSolution, tol: float | None = None) -> LowerSolution:
    """The lowest-KKT-residual point among sol and Newton solutions on up to defaults["polish.max_faces"] guessed faces.

    First guess: rows with a_i'y + b_i >= -tol (1 + |a_i||y| + |b_i|) and, per LMI, its eigenvalues <= tol (1 + |M_k|)
    at sol. Then constraints the face's solution violates join it and those with negative multipliers leave
    (a primal-dual active-set step), which settles solutions Clarabel leaves ambiguous (slack ~ multiplier). tol: None
    takes defaults["polish.active_tol"].
    """
    tol = param("polish.active_tol", tol)
    mats = [_split(lmi, d.q.size) for lmi in lmis]
    y = sol.y
    rows = np.flatnonzero(d.A @ y + d.b >= -tol * (1.0 + np.abs(d.A) @ np.abs(y) + np.abs(d.b)))
    ranks = []
    for mat in mats:
        w = np.linalg.eigvalsh(_at(mat, y))
        ranks.append(int(np.sum(w <= tol * (1.0 + np.abs(w).max()))))
    best, best_res = sol, kkt_residual(d, lmis, sol)
    for _ in range(param("polish.max_faces")):
        cand = _face(d, mats, sol, rows, ranks)
        res = kkt_residual(d, lmis, cand)
        if res < best_res:
            best, best_res = cand, res
        new_rows, new_ranks = _flip(d, mats, cand, rows, ranks)
        if np.array_equal(new_rows, rows) and new_ranks == ranks:
            break
        rows, ranks = new_rows, new_ranks
    return best
