"""Symmetric matrices stored by their lower triangle (vech): symbols, stacking and unstacking."""

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


def symmetric_from_vech(name: str, n: int) -> tuple[ca.SX, ca.SX]:
    """A symmetric n x n SX matrix built from n(n+1)/2 free symbols; returns (matrix, symbols)."""
    low, v = lower_triangular(name, n)
    return low + low.T - ca.diag(ca.diag(low)), v


def vech(matrix: np.ndarray) -> np.ndarray:
    """Stack the lower triangle of a symmetric matrix column by column (inverse of symmetric_from_vech)."""
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
