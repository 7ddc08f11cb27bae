"""Expressions that are a matrix QP: f quadratic and g, h affine in y, with numeric Hessian and constraint matrices,
recognized exactly and handed to MatrixLower (lower_qp's form), so that both declarations share one path. No
Jacobian of the constraints is built symbolically: at 1,000 rows by 100 variables that took 8-10 s (and the QP
coefficients' function as much again), where reading the matrix as below takes well under a second."""

from __future__ import annotations

import casadi as ca
import numpy as np

from ..defaults import param
from ..model import LowerQP
from ..parameters import ParameterSet
from .convexity import scaled_violation
from .matrix import MatrixLower


def matrix_form(x: ca.SX, y: ca.SX, f: ca.SX, g: ca.SX, h: ca.SX, hess_f: ca.SX, g_names: list[str],
                h_names: list[str], points: list[tuple[np.ndarray, np.ndarray]],
                params: ParameterSet) -> MatrixLower | None:
    """The lower level min f s.t. g <= 0, h = 0 as min 1/2 y'Py + q(x)'y + r(x) s.t. A y <= b(x), E y = e(x), or None
    (the expression kinds take it) unless all of this holds:

    - [A; E] has between defaults["classify.matrix_min_entries"] and defaults["classify.matrix_entries"] entries, and
      P (hess_f) is numeric (free of x, y and the parameters) and PSD;
    - the derivative of [g; h] along a symbolic direction v of y (one forward sweep) is free of x, y and the
      parameters, and depends on the same entries of v as [g; h] does on y: then [g; h] = J y + c(x) exactly, with no
      dependence on y that the derivative does not see (as in floor(y));
    - the form reproduces f, g and h at the sample points (x, y) to defaults["classify.matrix_rtol"] of each entry's
      scale (the sum of the magnitudes of its terms).

    J is read by evaluating the derivative at sums of unit vectors grouped by a column coloring of its sparsity
    (columns in a group share no row): each entry is read alone, as the expression computes it.
    """
    n, rows = int(y.numel()), int(g.numel() + h.numel())
    data = ca.vertcat(x, params.sym)
    if not rows or not param("classify.matrix_min_entries") <= rows * n <= param("classify.matrix_entries") \
            or ca.depends_on(hess_f, ca.vertcat(data, y)):
        return None
    P = np.asarray(ca.evalf(hess_f), dtype=float).reshape(n, n)
    P = 0.5 * (P + P.T)
    if not np.all(np.isfinite(P)) or scaled_violation(P)[0] > param("convexity.psd_tol"):
        return None  # the expression kinds name the non-convexity
    gh = ca.vertcat(g, h)
    v = ca.SX.sym("v", n)
    slope = ca.jtimes(gh, y, v)
    if ca.depends_on(slope, ca.vertcat(data, y)):
        return None
    pattern = ca.jacobian_sparsity(slope, v)
    if pattern != ca.jacobian_sparsity(gh, y):
        return None
    J = _read(slope, v, pattern)
    if not np.all(np.isfinite(J)):
        return None
    ng = int(g.numel())
    offsets = ca.substitute(ca.vertcat(gh, ca.gradient(f, y), f), y, ca.DM.zeros(n))
    c, q, r = offsets[:rows], offsets[rows:rows + n], offsets[rows + n]
    b, e = ca.vec(-c[:ng]), ca.vec(-c[ng:])  # 0 x 1 where empty (a slice of no entries is 1 x 0)
    low = MatrixLower(x, y, LowerQP(None, np.zeros((0, n)), P, J[:ng], J[ng:], ca.SX(0, 1), ca.vec(q), b, e, r),
                      g_names, h_names, params)
    return low if _reproduces(low, params.function("qp_form_check", [x, y], [f, gh]), points) else None


def _read(slope: ca.SX, v: ca.SX, pattern: ca.Sparsity) -> np.ndarray:
    """The dense matrix J of slope = J v (J numeric, of this sparsity), read from one evaluation per column color."""
    colors = pattern.uni_coloring()  # n x k, one nonzero a row: column j of J is in group color[j]
    color = np.zeros(pattern.size2(), dtype=int)
    members, groups = (np.asarray(k, dtype=int) for k in colors.get_triplet())
    color[members] = groups
    out = np.asarray(ca.Function("slope", [v], [slope]).map(colors.size2())(ca.DM(colors)), dtype=float)
    rows, cols = (np.asarray(k, dtype=int) for k in pattern.get_triplet())
    J = np.zeros((pattern.size1(), pattern.size2()))
    J[rows, cols] = out.reshape(pattern.size1(), colors.size2())[rows, color[cols]]
    return J


def _reproduces(low: MatrixLower, check: object, points: list[tuple[np.ndarray, np.ndarray]]) -> bool:
    """Whether the matrix form's f and [g; h] equal the expressions' at each point (x, y), to
    defaults["classify.matrix_rtol"] of each entry's scale."""
    rtol = param("classify.matrix_rtol")
    for xs, ys in points:
        f, gh = (np.asarray(v, dtype=float).ravel() for v in check(xs, ys))
        f_m, g_m, h_m, _ = low.evaluate(xs, ys)
        _, q, b, e, r = low.values(xs)
        M, ay = np.vstack([low.A, low.E]), np.abs(ys)
        scale_g = np.abs(M) @ ay + np.abs(np.concatenate([b, e])) + np.abs(gh)
        scale_f = 0.5 * ay @ np.abs(low.P) @ ay + np.abs(q) @ ay + abs(r[0]) + abs(f[0])
        if np.any(np.abs(np.concatenate([g_m, h_m]) - gh) > rtol * scale_g) or abs(f_m - f[0]) > rtol * scale_f:
            return False
    return True
