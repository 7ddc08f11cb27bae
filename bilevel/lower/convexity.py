"""Is the lower level convex in y? One test of its Hessians (of f and of the constraints nonlinear in y), used at
declaration (sampled), after set_value (the same samples, new values), by the certificate at the certified point,
and by method "global" for its whole upper box."""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING, Callable

import casadi as ca
import numpy as np

from ..defaults import param
from ..errors import NonConvexLowerLevel
from .curvature import convex_by_rules
from .interval import enclose

if TYPE_CHECKING:  # pragma: no cover
    from .base import LowerLevel


CONVEX_FIX = ("a convex lower level is required (minimize a convex function, or maximize a concave one, over a "
              "convex set)")


def _diagonal(sym: np.ndarray) -> np.ndarray | None:
    """The diagonal of a square matrix with nothing off it (its eigenvalues, exactly), else None."""
    diag = np.diagonal(sym)
    return diag if np.count_nonzero(sym) == np.count_nonzero(diag) else None


def symmetric_eigen(matrix: np.ndarray) -> tuple[np.ndarray, np.ndarray | None]:
    """Eigenvalues and eigenvectors of the symmetric part of matrix; (its diagonal, None) for a diagonal one (read,
    not factored)."""
    sym = 0.5 * (matrix + matrix.T)
    diag = _diagonal(sym)
    return (diag.copy(), None) if diag is not None else np.linalg.eigh(sym)


def psd_from_eigen(w: np.ndarray, v: np.ndarray | None) -> np.ndarray:
    """V max(w, 0) V' from symmetric_eigen's pair: the symmetric part's projection onto the PSD cone."""
    return np.diag(np.maximum(w, 0.0)) if v is None else (v * np.maximum(w, 0.0)) @ v.T


def min_eigenvalue(matrix: np.ndarray) -> float:
    """Smallest eigenvalue of the symmetric part of matrix (0 for an empty one; a diagonal one is read, not
    factored)."""
    matrix = np.atleast_2d(np.asarray(matrix, dtype=float))
    if not matrix.size:
        return 0.0
    sym = 0.5 * (matrix + matrix.T)
    diag = _diagonal(sym)
    return float((np.linalg.eigvalsh(sym) if diag is None else diag).min())


def psd_violation(matrix: np.ndarray) -> float:
    """How far the symmetric part of matrix is from PSD: max(-lambda_min, 0), 0 for an empty matrix."""
    return max(-min_eigenvalue(matrix), 0.0)


def scaled_violation(matrix: np.ndarray) -> tuple[float, float]:
    """(psd_violation / max(1, max |entry|), lambda_min): the relative distance from PSD, and the eigenvalue."""
    matrix = np.atleast_2d(np.asarray(matrix, dtype=float))
    lam = min_eigenvalue(matrix)
    return _relative(lam, matrix), lam


def _relative(lam: float, matrix: np.ndarray) -> float:
    """A smallest eigenvalue's distance from PSD relative to max(1, max |entry|)."""
    return max(-lam, 0.0) / max(1.0, float(np.abs(matrix).max(initial=0.0)))


def convexity_violation(low: "LowerLevel", x: np.ndarray, y: np.ndarray) -> tuple[float, str]:
    """The largest scaled_violation over the lower Hessians at (x, y), and a sentence naming that Hessian and its
    eigenvalue ('' when all are PSD)."""
    worst, text = 0.0, ""
    for what, hess in low.curvatures(x, y):
        value, lam = scaled_violation(hess)
        if value > worst:
            worst, text = value, f"the Hessian of {what} has eigenvalue {lam:.3g}"
    return worst, text


def require_psd(matrix: np.ndarray, what: str, where: str) -> np.ndarray:
    """matrix's symmetric part with its eigenvalues clipped at 0 (verified PSD up to rounding), or
    NonConvexLowerLevel naming the eigenvalue: what a convex solver may be told to trust."""
    w, v = symmetric_eigen(matrix)  # one factorization checks and clips
    lam = float(w.min()) if w.size else 0.0
    if _relative(lam, 0.5 * (matrix + matrix.T)) > param("convexity.psd_tol"):
        raise NonConvexLowerLevel(f"the lower level is not convex {where}: the Hessian of {what} has eigenvalue "
                                  f"{lam:.3g}; {CONVEX_FIX}")
    return psd_from_eigen(w, v)


@dataclass(frozen=True)
class ConvexityProbe:
    """The declaration's sampled convexity check, kept so that it re-runs on new parameter values (set_value):
    Hessian functions (x, y) -> matrix with what they are of, and the sample points (x, y)."""

    hessians: tuple[tuple[Callable, str], ...]
    points: tuple[tuple[np.ndarray, np.ndarray], ...]

    def run(self) -> float:
        """Smallest eigenvalue over all Hessians and points; NonConvexLowerLevel at the first non-PSD one."""
        worst = np.inf
        for fun, what in self.hessians:
            for xs, ys in self.points:
                hess = np.asarray(fun(xs, ys))
                value, lam = scaled_violation(hess)
                if value > param("convexity.psd_tol"):
                    raise NonConvexLowerLevel(
                        f"the lower level is not convex in the lower variables: the Hessian of {what} has eigenvalue "
                        f"{lam:.3g} at x = {np.array2string(xs, precision=3)}, y = "
                        f"{np.array2string(ys, precision=3)} (inside the declared bounds of y) at the parameters' "
                        f"current values; {CONVEX_FIX}; if it is convex on a domain that constraints rather than "
                        "bounds define, pass assume_convex=True (the certificate still checks)")
                worst = min(worst, lam)
        return worst


def require_convex_everywhere(low: "LowerLevel", x: np.ndarray) -> None:
    """Method "global": the lower level must be convex at every upper point of the box. Its scope (a KKT
    stationarity affine in (x, y), checked first) makes the Hessians constant in x and y, so one evaluation at any
    x proves it for the whole box; NonConvexLowerLevel naming the eigenvalue otherwise."""
    value, text = convexity_violation(low, x, np.zeros(low.n_y))
    if value > param("convexity.psd_tol"):
        raise NonConvexLowerLevel(f"the lower level is not convex at the parameters' current values ({text}, the "
                                  f"same at every upper point); method 'global' proves nothing for it; {CONVEX_FIX}")


def _dense(fun: ca.Function, k: int, nonzeros: np.ndarray) -> np.ndarray:
    sp = fun.sparsity_out(k)
    out = np.zeros((sp.size1(), sp.size2()))
    rows, cols = sp.get_triplet()
    out[np.asarray(rows, dtype=int), np.asarray(cols, dtype=int)] = nonzeros
    return out


def _interval_psd(lo: np.ndarray, hi: np.ndarray) -> bool:
    """Every symmetric matrix with entries in [lo, hi] is PSD (up to defaults["convexity.psd_tol"]): by Gershgorin's
    discs (each diagonal lower bound covers the row's largest possible off-diagonal sum), or by Weyl's inequality
    (the midpoint's smallest eigenvalue is at least the spectral norm of the radius, here bounded by its Frobenius
    norm), which is exact for a constant matrix."""
    size = np.maximum(np.abs(lo), np.abs(hi))
    off = np.where(np.eye(size.shape[0], dtype=bool), 0.0, size).sum(axis=1)
    finite = size[np.isfinite(size)]
    tol = param("convexity.psd_tol") * max(1.0, float(finite.max(initial=0.0)))
    if np.all(np.diag(lo) - off >= -tol):
        return True
    if not (np.all(np.isfinite(lo)) and np.all(np.isfinite(hi))):
        return False
    return min_eigenvalue(0.5 * (lo + hi)) - float(np.linalg.norm(0.5 * (hi - lo))) >= -tol


def convex_on_box(low: "LowerLevel", x: np.ndarray, y_lb: np.ndarray, y_ub: np.ndarray,
                  x_ub: np.ndarray | None = None) -> bool:
    """True when the lower level is proven convex in y at x (or on the upper box [x, x_ub]) for all y in [y_lb, y_ub]:
    by interval bounds on its Hessians (proven_convex) or by composition rules on f and g (curvature.py)."""
    if proven_convex(low, x, y_lb, y_ub, x_ub):
        return True
    expr = low.symbolic()
    functions = expr.params.substitute(ca.vertcat(expr.f, expr.g))
    return convex_by_rules(expr.x, expr.y, functions, (x, x if x_ub is None else x_ub), (y_lb, y_ub))


def proven_convex(low: "LowerLevel", x: np.ndarray, y_lb: np.ndarray, y_ub: np.ndarray,
                  x_ub: np.ndarray | None = None) -> bool:
    """True when interval bounds (interval.py) prove every lower Hessian PSD at upper point x (or, given x_ub, at
    every point of the upper box [x, x_ub]) for all y in the box [y_lb, y_ub]: then the lower level there is convex
    on a convex set containing its feasible set, and a local lower solution is global. False means not proven (not
    that it is non-convex)."""
    for compiled in low.curvature_functions():
        fun = compiled.fun
        boxes = [(x, x if x_ub is None else x_ub), (y_lb, y_ub)] + ([(compiled.params.value,) * 2]
                                                                   if compiled.params is not None else [])
        enclosures = enclose(fun, boxes)
        if enclosures is None:
            return False
        for k, (lo, hi) in enumerate(enclosures):
            if not _interval_psd(_dense(fun, k, lo), _dense(fun, k, hi)):
                return False
    return True
