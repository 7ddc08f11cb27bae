"""Half-vectorization of symmetric matrices, the one place for it: lower triangle column by column (vech),
and its isometric form with off-diagonals times sqrt(2) (svec, <X, Y> = svec(X)' svec(Y)); SX and numpy."""

from __future__ import annotations

import casadi as ca
import numpy as np


def lower_triangular(name: str, n: int) -> tuple[ca.SX, ca.SX]:
    """An n x n lower-triangular SX matrix of fresh symbols; returns (matrix, symbols)."""
    v = ca.SX.sym(name, n * (n + 1) // 2)
    m = ca.SX(n, n)
    k = 0
    for j in range(n):
        for i in range(j, n):
            m[i, j] = v[k]
            k += 1
    return m, v


def symmetric_sx(v: ca.SX, n: int) -> ca.SX:
    """The symmetric n x n SX matrix whose vech is v."""
    m = ca.SX(n, n)
    k = 0
    for j in range(n):
        for i in range(j, n):
            m[i, j] = v[k]
            m[j, i] = v[k]
            k += 1
    return m


def symmetric_from_vech(name: str, n: int) -> tuple[ca.SX, ca.SX]:
    """A symmetric n x n SX matrix built from n(n+1)/2 free symbols; returns (matrix, symbols)."""
    low, v = lower_triangular(name, n)
    return low + low.T - ca.diag(ca.diag(low)), v


def vech_sx(m: ca.SX) -> ca.SX:
    """Lower triangle of a symmetric SX matrix, column by column."""
    n = int(m.size1())
    return ca.vertcat(*[m[i, j] for j in range(n) for i in range(j, n)])


def vech(matrix: np.ndarray) -> np.ndarray:
    """Stack the lower triangle of a symmetric matrix column by column (inverse of unvech)."""
    n = matrix.shape[0]
    return np.concatenate([matrix[j:, j] for j in range(n)])


def unvech(values: np.ndarray, n: int) -> np.ndarray:
    """Rebuild the symmetric matrix from its vech."""
    m = np.zeros((n, n))
    k = 0
    for j in range(n):
        m[j:, j] = values[k:k + n - j]
        m[j, j:] = values[k:k + n - j]
        k += n - j
    return m


def svec(m: np.ndarray) -> np.ndarray:
    """Lower triangle of symmetric matrices (last two axes), off-diagonals times sqrt(2): <X, Y> = svec(X)'svec(Y)."""
    i, j = np.tril_indices(m.shape[-1])
    return m[..., i, j] * np.where(i == j, 1.0, np.sqrt(2.0))


def smat(v: np.ndarray, r: int) -> np.ndarray:
    """Inverse of svec for one r x r matrix (svec orders the lower triangle row by row, as np.tril_indices)."""
    i, j = np.tril_indices(r)
    m = np.zeros((r, r))
    m[i, j] = v / np.where(i == j, 1.0, np.sqrt(2.0))
    return m + np.tril(m, -1).T
