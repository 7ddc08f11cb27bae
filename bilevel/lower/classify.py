"""Pick the lower-level kind from the structure of f, g, h in y, and reject detectably non-convex ones."""

from __future__ import annotations

from typing import Callable

import casadi as ca
import numpy as np

from ..errors import ModelError, NonConvexLowerLevel
from ..parameters import ParameterSet
from ..sampling import sample_in_bounds
from .base import LowerLevel
from .least_squares import LeastSquaresLower
from .nlp import ConvexNLPLower
from .quadratic import LinearLower, QuadraticLower
from .sdp import SemidefiniteLower

_PSD_TOL = 1e-9
Y_PROBES = 16
"""Lower points drawn (inside the declared bounds of y) per upper sample when a Hessian depends on y."""


def _min_eig(matrix: np.ndarray) -> float:
    matrix = np.atleast_2d(matrix)
    return float(np.linalg.eigvalsh(0.5 * (matrix + matrix.T)).min()) if matrix.size else 0.0


def _check_psd(fun: Callable, points: list[tuple[np.ndarray, np.ndarray]], what: str) -> float:
    """Smallest eigenvalue of fun(x, y) over the sample points; raise NonConvexLowerLevel if negative."""
    worst = np.inf
    if not fun.sparsity_out(0).nnz() or not ca.depends_on(fun.sx_out(0), fun.sx_in(1)):
        points = list({id(xs): (xs, ys) for xs, ys in points}.values())  # constant in y: one y per x
    for xs, ys in points:
        hess = np.asarray(fun(xs, ys))
        lam = _min_eig(hess)
        scale = max(1.0, float(np.abs(hess).max()))
        if lam < -_PSD_TOL * scale:
            raise NonConvexLowerLevel(
                f"the lower level is not convex in the lower variables: the Hessian of {what} has eigenvalue "
                f"{lam:.3g} at x = {np.array2string(xs, precision=3)}, y = {np.array2string(ys, precision=3)} "
                "(inside the declared bounds of y); a convex lower level is required (minimize a convex "
                "function, or maximize a concave one, over a convex set); if it is convex on a domain that "
                "constraints rather than bounds define, pass assume_convex=True (the certificate still checks)"
            )
        worst = min(worst, lam)
    return worst


def build_lower(x: ca.SX, y: ca.SX, f: ca.SX, g: ca.SX, h: ca.SX, psd: list[ca.SX], g_names: list[str],
                h_names: list[str], psd_names: list[str], x_samples: list[np.ndarray],
                y_lb: np.ndarray | None = None, y_ub: np.ndarray | None = None,
                assume_convex: bool = False, params: ParameterSet | None = None) -> LowerLevel:
    """Classify as least squares, LP, QP or convex NLP and build it.

    Convexity in y is probed at the upper samples times Y_PROBES lower points inside the declared bounds
    [y_lb, y_ub] (a probe, not a proof: the certificate's re-solve is the second line of defence);
    assume_convex=True skips the probe for a nonlinear lower level (a quadratic one is checked exactly).
    """
    if not ca.depends_on(f, y):
        raise ModelError("the lower objective does not depend on the lower variables; "
                         "a bilevel problem needs a lower level that optimizes over y")
    if h.numel() and ca.depends_on(ca.jacobian(h, y), y):
        raise NonConvexLowerLevel("a lower-level equality constraint is not affine in the lower variables; "
                                  "only affine equalities keep the lower level convex")
    args = (x, y, f, g, h, psd, g_names, h_names, psd_names)
    params = ParameterSet() if params is None else params
    function = params.function
    ny = int(y.numel())
    y_lb = np.full(ny, -np.inf) if y_lb is None else y_lb
    y_ub = np.full(ny, np.inf) if y_ub is None else y_ub
    rng = np.random.default_rng(0)
    points = [(xs, sample_in_bounds(y_lb, y_ub, rng, 3.0)) for xs in x_samples for _ in range(Y_PROBES)]
    hess_f = ca.hessian(f, y)[0]
    nonlinear_f = np.asarray(ca.which_depends(f, y, 2, False), dtype=bool)  # sparsity propagation, no simplify
    affine_g = not (g.numel() and any(ca.which_depends(g, y, 2, False)))
    if psd:
        for name, m in zip(psd_names, psd):
            if ca.depends_on(ca.jacobian(ca.vec(m), y), y):
                raise NonConvexLowerLevel(f"LMI {name!r} is not affine in the lower variables; an SDP lower level "
                                          "needs M(x, y) affine in y")
        if not affine_g or ca.depends_on(hess_f, y):  # hess_f is small (n_y x n_y) next to f
            raise ModelError("a lower level with LMIs must have a linear or convex quadratic objective and affine "
                             "scalar constraints in y (a conic program)")
        _check_psd(function("hf", [x, y], [hess_f]), points, "the lower objective")
        return SemidefiniteLower(*args, hess_f=hess_f, params=params)
    if affine_g and not ca.depends_on(hess_f, y):
        if not nonlinear_f.any():
            return LinearLower(*args, hess_f=hess_f, params=params)
        worst = _check_psd(function("hf", [x, y], [hess_f]), points, "the lower objective")
        if not g.numel() and not h.numel() and worst > _PSD_TOL:
            return LeastSquaresLower(*args, hess_f=hess_f, params=params)
        return QuadraticLower(*args, hess_f=hess_f, params=params)
    if assume_convex:  # a Hessian that varies with y: convexity is the user's claim, checked by the certificate
        return ConvexNLPLower(*args, hess_f=hess_f, params=params)
    _check_psd(function("hf", [x, y], [hess_f]), points, "the lower objective")
    for i in range(int(g.numel())):
        if ca.depends_on(ca.jacobian(g[i], y), y):
            _check_psd(function("hg", [x, y], [ca.hessian(g[i], y)[0]]), points,
                       f"lower constraint {g_names[i]!r}")
    return ConvexNLPLower(*args, hess_f=hess_f, params=params)
