"""The MPCC as numeric data when it is linear apart from complementarity (the scope of method="global").

min 1/2 w'Qw + c'w + c0  s.t.  A_eq w = b_eq,  A_in w <= b_in,  lb <= w <= ub,  0 <= G w + g ⟂ H w + h >= 0.
That holds for an LP or convex-QP lower level whose KKT stationarity is linear in (x, y, lam, mu) (constant
Hessian P and constraint matrices A, E in y; q, b, e affine in x), linear upper constraints, and a linear or
convex quadratic upper objective. Everything else is rejected with a ModelError saying why.
"""

from __future__ import annotations

from dataclasses import dataclass

import casadi as ca
import numpy as np

from ..errors import ModelError
from ..lower.convexity import require_convex_everywhere
from ..mpcc import ScalarPair
from ..parameters import ParameterSet, scalar
from .base import Prepared

LOCAL_METHODS = "use a local method instead: method='relaxation' (most robust) or method='ipopt'"
CONVEXITY_TOL = 1e-9


@dataclass(frozen=True)
class LinearMPCC:
    """An MPCC with linear constraints, a convex quadratic objective and complementarity pairs of affine forms."""

    Q: np.ndarray
    c: np.ndarray
    c0: float
    A_eq: np.ndarray
    b_eq: np.ndarray
    A_in: np.ndarray
    b_in: np.ndarray
    lb: np.ndarray
    ub: np.ndarray
    G: np.ndarray
    g: np.ndarray
    H: np.ndarray
    h: np.ndarray
    labels: tuple[str, ...]

    @property
    def n(self) -> int:
        return self.c.size

    @property
    def n_pairs(self) -> int:
        return self.g.size

    @property
    def linear(self) -> bool:
        """True when the objective is linear (the MILP path applies)."""
        return not np.any(self.Q)

    def objective(self, w: np.ndarray) -> float:
        return float(0.5 * w @ self.Q @ w + self.c @ w + self.c0)


def _affine(expr: ca.SX, w: ca.SX, what: str, why: str, params: ParameterSet) -> tuple[np.ndarray, np.ndarray]:
    """(J, r) with expr = J w + r; ModelError naming `what` and `why` if expr is not affine in w."""
    n_rows = int(expr.numel())
    if n_rows == 0:
        return np.zeros((0, int(w.numel()))), np.zeros(0)
    jac = ca.jacobian(expr, w)
    if ca.depends_on(jac, w):
        raise ModelError(f"method 'global' needs {what} to be affine: {why}; {LOCAL_METHODS}")
    fun = params.function("affine", [w], [ca.densify(jac), ca.densify(expr)])
    J, r = fun(np.zeros(int(w.numel())))
    return np.asarray(J, dtype=float).reshape(n_rows, -1), np.asarray(r, dtype=float).ravel()


def _objective(F: ca.SX, w: ca.SX, params: ParameterSet) -> tuple[np.ndarray, np.ndarray, float]:
    """(Q, c, c0) of a convex quadratic F; ModelError if F is not quadratic or not convex."""
    grad = ca.gradient(F, w)
    hess = ca.jacobian(grad, w)
    if ca.depends_on(hess, w):
        raise ModelError("method 'global' needs an upper objective that is linear or convex quadratic in (x, y); "
                         f"this one is of higher degree; {LOCAL_METHODS}")
    fun = params.function("quad", [w], [ca.densify(hess), ca.densify(grad), F])
    Q, c, c0 = fun(np.zeros(int(w.numel())))
    Q = np.asarray(Q, dtype=float)
    Q = 0.5 * (Q + Q.T)
    if np.any(Q):
        low = float(np.linalg.eigvalsh(Q).min())
        if low < -CONVEXITY_TOL * max(1.0, float(np.abs(Q).max())):
            raise ModelError("method 'global' needs a convex upper objective (in minimization form): its Hessian in "
                             f"(x, y) has eigenvalue {low:.3g} (e.g. a bilinear x*y term); {LOCAL_METHODS}")
    return Q, np.asarray(c, dtype=float).ravel(), scalar(c0)


def linear_mpcc(prep: Prepared) -> LinearMPCC:
    """The prepared problem's MPCC as a LinearMPCC, or a ModelError naming what is out of scope and why."""
    low = prep.canon.lower
    if low.kind not in ("lp", "qp", "least-squares"):
        raise ModelError(f"method 'global' handles LP and convex-QP lower levels with affine constraints; this lower "
                         f"level is of kind {low.kind!r}; {LOCAL_METHODS}")
    mpcc = prep.mpcc
    w = mpcc.w
    canon = prep.canon
    n_H, n_y = int(canon.H.numel()), low.n_y
    eq = mpcc.equalities
    A_H, r_H = _affine(eq[:n_H] if n_H else ca.SX(0, 1), w, "the upper equality constraints",
                       "they must be linear in (x, y)", mpcc.params)
    A_s, r_s = _affine(eq[n_H:n_H + n_y], w, "the lower-level KKT stationarity",
                       "the lower objective's Hessian in y and the constraint matrices in y must not depend on x "
                       "(an x*y term in a lower constraint or an x-dependent quadratic term breaks this)", mpcc.params)
    require_convex_everywhere(low, np.clip(np.zeros(low.n_x), canon.x_lb, canon.x_ub))  # after the affinity check
    A_h, r_h = _affine(eq[n_H + n_y:], w, "the lower equality constraints", "they must be affine in (x, y)",
                       mpcc.params)
    A_in, r_in = _affine(mpcc.inequalities, w, "the upper inequality constraints", "they must be linear in (x, y)",
                         mpcc.params)
    G_rows, g, H_rows, h, labels = [], [], [], [], []
    for pair in mpcc.pairs:
        if not isinstance(pair, ScalarPair):
            raise ModelError(f"method 'global' does not handle LMI (PSD) pairs such as {pair.name!r}; {LOCAL_METHODS}")
        Gi, gi = _affine(pair.G, w, "the lower inequality constraints",
                         "g(x, y) = A y + b(x) with A constant and b affine in x", mpcc.params)
        Hi, hi = _affine(pair.H, w, "the multipliers of the pairs", "they are variables of the MPCC", mpcc.params)
        G_rows.append(Gi)
        g.append(gi)
        H_rows.append(Hi)
        h.append(hi)
        labels += list(pair.labels) or [f"{pair.name}[{i}]" for i in range(gi.size)]
    Q, c, c0 = _objective(mpcc.objective, w, mpcc.params)
    n = int(w.numel())
    stack = lambda parts: np.vstack(parts) if parts else np.zeros((0, n))  # noqa: E731
    flat = lambda parts: np.concatenate(parts) if parts else np.zeros(0)  # noqa: E731
    return LinearMPCC(Q, c, c0, np.vstack([A_H, A_s, A_h]), -np.concatenate([r_H, r_s, r_h]), A_in, -r_in,
                      mpcc.lbw.astype(float), mpcc.ubw.astype(float), stack(G_rows), flat(g), stack(H_rows),
                      flat(h), tuple(labels))
