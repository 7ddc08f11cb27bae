"""Symbolic Jacobians of SX expressions whose sparsity pattern has a few dense rows and columns.

CasADi colors a Jacobian's columns (forward mode) or rows (reverse mode), one sweep of the whole expression graph per
color, so a pattern with dense rows and dense columns needs as many sweeps as the densest row or column. A KKT system
with matrix data bound to upper variables is such a pattern: each lower equality row A(x) y = b involves all of y and
of x, and each multiplier enters every stationarity row. Differentiating the dense rows apart (reverse mode, one sweep
each), then the dense columns of the other rows (forward), then the rest, gives the same Jacobian with few sweeps
(6.5x faster to build on the DeePC learner at T = 200).
"""

from __future__ import annotations

import casadi as ca
import numpy as np


def dense_count(counts: np.ndarray) -> int:
    """How many of the largest entries of `counts` (nonzeros per row or column) to treat apart: the k minimizing
    k + the (k+1)-th largest count, the sweeps of treating k apart plus a bound on coloring the rest."""
    ordered = np.sort(np.asarray(counts, dtype=int))[::-1]
    return int(np.argmin(np.arange(ordered.size + 1) + np.append(ordered, 0)))


def jacobian(expr: ca.SX, x: ca.SX) -> ca.SX:
    """d expr / d x (a column expression and symbol vector), with the dense rows and columns differentiated apart;
    CasADi's own jacobian where the pattern has none."""
    pattern = ca.jacobian_sparsity(expr, x)
    rows, cols = np.diff(np.asarray(pattern.T.colind())), np.diff(np.asarray(pattern.colind()))
    k_rows, k_cols = dense_count(rows), dense_count(cols)
    if k_rows == 0 and k_cols == 0:
        return ca.jacobian(expr, x)
    dense_rows = np.sort(np.argsort(-rows, kind="stable")[:k_rows])
    dense_cols = np.sort(np.argsort(-cols, kind="stable")[:k_cols])
    other_rows = np.setdiff1d(np.arange(rows.size), dense_rows).tolist()
    other_cols = np.setdiff1d(np.arange(cols.size), dense_cols).tolist()
    dense_rows, dense_cols = dense_rows.tolist(), dense_cols.tolist()
    out = ca.SX(int(expr.numel()), int(x.numel()))
    if dense_rows:
        out[dense_rows, :] = ca.jacobian(expr[dense_rows], x)
    if other_rows and dense_cols:
        out[other_rows, dense_cols] = ca.jacobian(expr[other_rows], x[dense_cols])
    if other_rows and other_cols:
        out[other_rows, other_cols] = ca.jacobian(expr[other_rows], x[other_cols])
    return out
