"""Pick the lower-level kind from the structure of f, g, h in y, and reject detectably non-convex ones."""

from __future__ import annotations

import casadi as ca
import numpy as np

from ..defaults import param
from ..errors import ModelError, NonConvexLowerLevel
from ..parameters import CompiledFunction, ParameterSet
from ..sampling import sample_in_bounds
from .base import LowerLevel
from .convexity import ConvexityProbe
from .least_squares import LeastSquaresLower
from .nlp import ConvexNLPLower
from .qp_form import matrix_form
from .quadratic import LinearLower, QuadraticLower
from .residual import ResidualLeastSquares
from .sdp import SemidefiniteLower


def _probe(hessians: list[tuple[CompiledFunction, str]],
           points: list[tuple[np.ndarray, np.ndarray]]) -> tuple[ConvexityProbe, float]:
    """The sampled check of these Hessians (one y per x when they are constant in y, one point when constant in x and
    y), and its smallest eigenvalue now (NonConvexLowerLevel if negative)."""
    distinct_x = tuple({id(xs): (xs, ys) for xs, ys in points}.values())
    outputs = [(fun.call([fun.sx_in(i) for i in range(fun.n_in())])[0], fun) for fun, _ in hessians]
    on = lambda k: any(out.nnz() and ca.depends_on(out, fun.sx_in(k)) for out, fun in outputs)  # noqa: E731
    probe = ConvexityProbe(tuple(hessians), tuple(points) if on(1) else distinct_x if on(0) else distinct_x[:1])
    return probe, probe.run()


def build_lower(x: ca.SX, y: ca.SX, f: ca.SX, g: ca.SX, h: ca.SX, psd: list[ca.SX], g_names: list[str],
                h_names: list[str], psd_names: list[str], x_samples: list[np.ndarray],
                y_lb: np.ndarray | None = None, y_ub: np.ndarray | None = None,
                assume_convex: bool = False, params: ParameterSet | None = None,
                matrices: bool = True) -> LowerLevel:
    """Classify as least squares, LP, QP or convex NLP and build it; with matrices, an LP or QP with constraints whose
    matrices are numbers becomes lower_qp's matrix form (qp_form.matrix_form).

    Convexity in y is probed at the upper samples times defaults["classify.y_probes"] lower points inside the declared
    bounds [y_lb, y_ub] (a probe, not a proof: the certificate's re-solve is the second line of defence);
    assume_convex=True skips the probe for a nonlinear lower level (a quadratic one is checked exactly).
    """
    if not ca.depends_on(f, y):
        raise ModelError("the lower objective does not depend on the lower variables; "
                         "a bilevel problem needs a lower level that optimizes over y")
    args = (x, y, f, g, h, psd, g_names, h_names, psd_names)
    params = ParameterSet() if params is None else params
    function = params.function
    ny = int(y.numel())
    y_lb = np.full(ny, -np.inf) if y_lb is None else y_lb
    y_ub = np.full(ny, np.inf) if y_ub is None else y_ub
    if not g.numel() and not h.numel() and not psd and np.all(np.isinf(y_lb)) and np.all(np.isinf(y_ub)):
        residual = ResidualLeastSquares.recognize(x, y, f, x_samples, params)
        if residual is not None:  # a large least squares: its Hessian C'C formed numerically, never symbolically
            return residual
    rng = np.random.default_rng(0)
    probes = param("classify.y_probes")
    points = [(xs, sample_in_bounds(y_lb, y_ub, rng, 3.0)) for xs in x_samples for _ in range(probes)]
    hess_f = ca.hessian(f, y)[0]
    if matrices and not psd:
        low = matrix_form(x, y, f, g, h, hess_f, g_names, h_names, points[::probes], params)
        if low is not None:
            return low
    if h.numel() and ca.depends_on(ca.jacobian(h, y), y):
        raise NonConvexLowerLevel("a lower-level equality constraint is not affine in the lower variables; "
                                  "only affine equalities keep the lower level convex")
    nonlinear_f = np.asarray(ca.which_depends(f, y, 2, False), dtype=bool)  # sparsity propagation, no simplify
    affine_g = not (g.numel() and any(ca.which_depends(g, y, 2, False)))
    objective = [(function("hf", [x, y], [hess_f]), "the lower objective")]
    if psd:
        for name, m in zip(psd_names, psd):
            if any(ca.which_depends(ca.vec(m), y, 2, True)):  # an entry nonlinear in y, by sparsity: no Jacobian
                raise NonConvexLowerLevel(f"LMI {name!r} is not affine in the lower variables; an SDP lower level "
                                          "needs M(x, y) affine in y")
        if not affine_g or ca.depends_on(hess_f, y):  # hess_f is small (n_y x n_y) next to f
            raise ModelError("a lower level with LMIs must have a linear or convex quadratic objective and affine "
                             "scalar constraints in y (a conic program)")
        return _with_probe(SemidefiniteLower(*args, hess_f=hess_f, params=params), _probe(objective, points)[0])
    if affine_g and not ca.depends_on(hess_f, y):
        if not nonlinear_f.any():
            return LinearLower(*args, hess_f=hess_f, params=params)
        probe, worst = _probe(objective, points)
        if not g.numel() and not h.numel() and worst > param("convexity.psd_tol"):
            return _with_probe(LeastSquaresLower(*args, hess_f=hess_f, params=params), probe)
        return _with_probe(QuadraticLower(*args, hess_f=hess_f, params=params), probe)
    if assume_convex:  # a Hessian that varies with y: convexity is the user's claim, checked by the certificate
        return ConvexNLPLower(*args, hess_f=hess_f, params=params)
    curved = [(function("hg", [x, y], [ca.hessian(g[i], y)[0]]), f"lower constraint {g_names[i]!r}")
              for i in range(int(g.numel())) if ca.depends_on(ca.jacobian(g[i], y), y)]
    return _with_probe(ConvexNLPLower(*args, hess_f=hess_f, params=params), _probe(objective + curved, points)[0])


def _with_probe(low: LowerLevel, probe: ConvexityProbe) -> LowerLevel:
    """low, carrying the declaration's convexity check so that a set_value re-runs it."""
    low.convexity_probe = probe
    return low
