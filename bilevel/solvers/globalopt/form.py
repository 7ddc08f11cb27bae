"""The MPCC as numeric data when it is linear apart from complementarity (the scope of method="global").

min 1/2 w'Qw + c'w + c0  s.t.  A_eq w = b_eq,  A_in w <= b_in,  lb <= w <= ub,  0 <= G w + g ⟂ H w + h >= 0.
That holds for an LP or convex-QP lower level whose KKT stationarity is linear in (x, y, lam, mu) (constant
Hessian P and constraint matrices A, E in y; q, b, e affine in x), linear upper constraints, and a linear or
convex quadratic upper objective. With `nonconvex_leader` (algorithm "scip"), the upper objective may be any
expression SCIP takes (bilinear, polynomial, ...), and upper rows nonlinear in w, lower slacks nonlinear in x and
KKT stationarity rows nonlinear through an x-dependent lower Hessian (affine in x, convex on the upper box) are
kept apart (a Leader). Everything else is rejected with a ModelError naming the class and the fix.
"""

from __future__ import annotations

import itertools
from dataclasses import dataclass
from typing import TYPE_CHECKING

import casadi as ca
import numpy as np

from ...defaults import param
from ...errors import ModelError, NonConvexLowerLevel
from ...lower.convexity import convex_on_box, require_convex_everywhere
from ...mpcc import ScalarPair
from ...parameters import ParameterSet, scalar
from ..engine.prepared import Prepared

if TYPE_CHECKING:  # pragma: no cover
    from ...canonical import CanonicalBilevel
    from ...lower.base import LowerLevel

LOCAL_METHODS = "use a local method instead: method='relaxation' (most robust) or method='ipopt'"
SCIP_FIX = ("algorithm='scip' of method 'global' proves this class with SCIP's spatial branch-and-bound once pyscipopt is "
            "installed (pip install pyscipopt, or pip install 'bilevel[global]')")
NOT_IN_SCIP = "algorithm 'scip' does not cover this class yet"


@dataclass(frozen=True)
class Leader:
    """The upper level as SCIP takes it (algorithm "scip"): the objective F(w), and the upper rows nonlinear in w,
    inequalities(w) <= 0 and equalities(w) = 0, all with the parameters' values substituted; `slacks` holds the
    pairs whose slack G_i(w) = -g_i(x, y) is nonlinear in x (index, expression; their rows in G and g are zero).
    `nonconvex` names the class outside the convex algorithms' scope ("" when the upper level is convex quadratic
    with linear rows)."""

    w: ca.SX
    objective: ca.SX
    inequalities: ca.SX
    equalities: ca.SX
    nonconvex: str
    slacks: tuple[tuple[int, ca.SX], ...] = ()

    @property
    def nonlinear_rows(self) -> bool:
        """True when some constraint row is nonlinear (SCIP may then bound variables the LPs cannot)."""
        return bool(self.inequalities.numel() or self.equalities.numel() or self.slacks)


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
    leader: Leader | None = None
    """Set when built for algorithm "scip"; with a nonconvex leader, Q, c and c0 are zero (the objective is there)."""

    @property
    def n(self) -> int:
        return self.c.size

    @property
    def n_pairs(self) -> int:
        return self.g.size

    @property
    def nonlinear_pairs(self) -> set[int]:
        """Pairs whose slack is nonlinear in x (kept by the Leader; zero rows in G and g)."""
        return {i for i, _ in self.leader.slacks} if self.leader is not None else set()

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


def _split(expr: ca.SX, w: ca.SX) -> tuple[ca.SX, ca.SX]:
    """(rows affine in w, rows nonlinear in w) of expr."""
    affine, nonlinear = [], []
    for i in range(int(expr.numel())):
        (nonlinear if ca.depends_on(ca.jacobian(expr[i], w), w) else affine).append(expr[i])
    return tuple(ca.vertcat(*rows) if rows else ca.SX(0, 1) for rows in (affine, nonlinear))


def _objective(F: ca.SX, w: ca.SX, params: ParameterSet) -> tuple[np.ndarray, np.ndarray, float] | str:
    """(Q, c, c0) of a convex quadratic F, or the class of a nonconvex one (a phrase for the error messages)."""
    grad = ca.gradient(F, w)
    hess = ca.jacobian(grad, w)
    if ca.depends_on(hess, w):
        return "an upper objective of degree above 2 or not polynomial (the convex algorithms need it linear or convex " \
               "quadratic in (x, y))"
    fun = params.function("quad", [w], [ca.densify(hess), ca.densify(grad), F])
    Q, c, c0 = fun(np.zeros(int(w.numel())))
    Q = np.asarray(Q, dtype=float)
    Q = 0.5 * (Q + Q.T)
    if np.any(Q):
        low = float(np.linalg.eigvalsh(Q).min())
        if low < -param("global.convexity_tol") * max(1.0, float(np.abs(Q).max())):
            return ("a nonconvex upper objective (the convex algorithms need a convex upper objective in minimization "
                    f"form; its Hessian in (x, y) has eigenvalue {low:.3g}, e.g. a bilinear x*y term)")
    return Q, np.asarray(c, dtype=float).ravel(), scalar(c0)


def _nonlinear_slacks(G: ca.SX, w: ca.SX, first: int, slacks: list[tuple[int, ca.SX]]
                      ) -> tuple[np.ndarray, np.ndarray]:
    """(rows, constants) of a pair's slacks G (parameters substituted): affine rows as they are, rows nonlinear in w
    as zeros, appended to `slacks` with their pair index (first + row) for SCIP."""
    n = int(w.numel())
    J, r = np.zeros((int(G.numel()), n)), np.zeros(int(G.numel()))
    for k in range(int(G.numel())):
        jac = ca.jacobian(G[k], w)
        if ca.depends_on(jac, w):
            slacks.append((first + k, G[k]))
            continue
        fun = ca.Function("affine_row", [w], [ca.densify(jac), G[k]])
        Jk, rk = fun(np.zeros(n))
        J[k], r[k] = np.asarray(Jk, dtype=float).ravel(), float(rk)
    return J, r


def _require_convex_on_box(low: LowerLevel, x_lb: np.ndarray, x_ub: np.ndarray) -> None:
    """An x-dependent lower Hessian P(x) is PSD at every x of the declared box: proven when P is affine in x (its
    smallest eigenvalue is then concave in x, so its minimum over the box is at a vertex) and PSD at each vertex;
    a ModelError naming what is missing otherwise. The KKT reformulation is exact only where the lower level is
    convex."""
    hess = low.params.substitute(low.hess_f) if getattr(low, "hess_f", None) is not None else ca.SX(low.n_y, low.n_y)
    if ca.depends_on(ca.jacobian(ca.vec(hess), ca.vertcat(low.x, low.y)), ca.vertcat(low.x, low.y)):
        raise ModelError("method 'global' with an x-dependent lower Hessian needs it affine in x and constant in y "
                         "(class: x-dependent lower Hessian, nonlinear in x; algorithm 'scip' does not cover this "
                         f"class yet); {LOCAL_METHODS}")
    varying = np.flatnonzero([ca.depends_on(hess, low.x[i]) for i in range(low.n_x)])
    vertices = param("global.max_box_vertices")
    if not (np.all(np.isfinite(x_lb[varying])) and np.all(np.isfinite(x_ub[varying]))) or 2 ** varying.size > vertices:
        raise ModelError("method 'global' with an x-dependent lower Hessian proves the lower level convex on the box "
                         f"of the upper variables it depends on; declare finite bounds on them (at most "
                         f"{int(np.log2(vertices))} such variables); {LOCAL_METHODS}")
    fun = ca.Function("lower_hessian", [low.x], [hess])
    for corner in itertools.product(*[(x_lb[i], x_ub[i]) for i in varying]):
        x = np.clip(np.zeros(low.n_x), x_lb, x_ub)
        x[varying] = corner
        P = np.asarray(fun(x), dtype=float)
        low_eig = float(np.linalg.eigvalsh(0.5 * (P + P.T)).min()) if P.size else 0.0
        if low_eig < -param("global.convexity_tol") * max(1.0, float(np.abs(P).max(initial=0.0))):
            raise NonConvexLowerLevel(f"the lower level is not convex at x = {np.array2string(x, precision=4)} "
                                      f"(lower Hessian eigenvalue {low_eig:.3g}), a vertex of the upper box; method "
                                      "'global' proves nothing for it")


def _require_proven_convex(low: LowerLevel, canon: CanonicalBilevel) -> None:
    """A convex NLP lower level is convex at every x of the declared upper box for every y of the declared lower
    box (a convex set holding its feasible set): interval bounds on its Hessians (lower/interval.py) with
    Gershgorin's discs, or composition rules on f and g (lower/curvature.py), prove it; a ModelError naming the class
    otherwise (not proven is not non-convex)."""
    n_y = low.n_y
    y_lb = np.full(n_y, -np.inf) if canon.y_lb is None else canon.y_lb
    y_ub = np.full(n_y, np.inf) if canon.y_ub is None else canon.y_ub
    if not convex_on_box(low, canon.x_lb, y_lb, y_ub, canon.x_ub):
        raise ModelError("method 'global' proves a convex NLP lower level convex on the declared box before trusting "
                         "its KKT conditions; interval bounds on the Hessians of its objective and nonlinear rows "
                         "over the upper box times the lower variables' bounds do not prove them positive "
                         "semidefinite, nor do composition rules prove them convex (class: lower level not provably "
                         f"convex on the box; declare tighter bounds on x and y, or {LOCAL_METHODS})")


def _refuse(nonconvex: str) -> ModelError:
    """The error for a leader outside the convex algorithms' scope when SCIP is not used."""
    return ModelError(f"method 'global' was given {nonconvex} (class: nonconvex leader); {SCIP_FIX}; or "
                      f"{LOCAL_METHODS}")


def linear_mpcc(prep: Prepared, nonconvex_leader: bool = False) -> LinearMPCC:
    """The prepared problem's MPCC as a LinearMPCC, or a ModelError naming what is out of scope and why.

    With nonconvex_leader (algorithm "scip"), a nonconvex upper objective and nonlinear upper rows are kept in
    the form's Leader instead of refused."""
    low = prep.canon.lower
    nlp = low.nonlinear
    if not low.affine_kkt and not (nlp and nonconvex_leader):
        fix = SCIP_FIX if nlp else NOT_IN_SCIP
        raise ModelError(f"method 'global' handles LP and convex-QP lower levels with affine constraints, and convex "
                         f"NLP ones with algorithm 'scip'; this lower level is of kind {low.kind!r} (class: nonlinear "
                         f"lower level; {fix}); {LOCAL_METHODS}")
    mpcc = prep.mpcc
    w = mpcc.w
    canon = prep.canon
    n_H, n_y = int(canon.H.numel()), low.n_y
    eq = mpcc.equalities
    upper_eq, upper_eq_nl = _split(mpcc.params.substitute(eq[:n_H] if n_H else ca.SX(0, 1)), w)
    upper_in, upper_in_nl = _split(mpcc.params.substitute(mpcc.inequalities), w)
    A_H, r_H = _affine(upper_eq, w, "the upper equality constraints", "they must be linear in (x, y)", mpcc.params)
    stationarity, stationarity_nl = eq[n_H:n_H + n_y], ca.SX(0, 1)
    if nonconvex_leader and ca.depends_on(ca.jacobian(stationarity, w), w):
        stationarity, stationarity_nl = _split(mpcc.params.substitute(stationarity), w)
    A_s, r_s = _affine(stationarity, w, "the lower-level KKT stationarity",
                       "the lower objective's Hessian in y and the constraint matrices in y must not depend on x "
                       "(an x*y term in a lower constraint or an x-dependent quadratic term breaks this; class: "
                       f"x-dependent lower Hessian or constraint matrix; {SCIP_FIX})", mpcc.params)
    if nlp:
        _require_proven_convex(low, canon)
    elif stationarity_nl.numel():
        _require_convex_on_box(low, canon.x_lb, canon.x_ub)
    else:
        require_convex_everywhere(low, np.clip(np.zeros(low.n_x), canon.x_lb, canon.x_ub))  # after the affinity check
    A_h, r_h = _affine(eq[n_H + n_y:], w, "the lower equality constraints", "they must be affine in (x, y)",
                       mpcc.params)
    A_in, r_in = _affine(upper_in, w, "the upper inequality constraints", "they must be linear in (x, y)",
                         mpcc.params)
    G_rows, g, H_rows, h, labels = [], [], [], [], []
    slacks: list[tuple[int, ca.SX]] = []
    for pair in mpcc.pairs:
        if not isinstance(pair, ScalarPair):
            raise ModelError(f"method 'global' does not handle LMI (PSD) pairs such as {pair.name!r}; {LOCAL_METHODS}")
        try:
            Gi, gi = _affine(pair.G, w, "the lower inequality constraints", "g(x, y) = A y + b(x) with A constant "
                             f"and b affine in x (class: lower constraints nonlinear in x; {SCIP_FIX})", mpcc.params)
        except ModelError:
            if not nonconvex_leader:
                raise
            Gi, gi = _nonlinear_slacks(mpcc.params.substitute(pair.G), w, sum(v.size for v in g), slacks)
        Hi, hi = _affine(pair.H, w, "the multipliers of the pairs", "they are variables of the MPCC", mpcc.params)
        G_rows.append(Gi)
        g.append(gi)
        H_rows.append(Hi)
        h.append(hi)
        labels += list(pair.labels) or [f"{pair.name}[{i}]" for i in range(gi.size)]
    quadratic = _objective(mpcc.objective, w, mpcc.params)
    rows_nl = int(upper_eq_nl.numel()) + int(upper_in_nl.numel())
    classes = [quadratic] if isinstance(quadratic, str) else []
    if rows_nl:
        classes.append(f"{rows_nl} upper constraint row(s) nonlinear in (x, y) (the convex algorithms need the upper "
                       "inequality constraints to be affine)")
    if nlp:
        classes.append("a convex NLP lower level (constraints or objective nonlinear in y)")
    elif slacks:
        classes.append(f"{len(slacks)} lower constraint row(s) nonlinear in x")
    if stationarity_nl.numel():
        classes.append(f"an x-dependent lower Hessian or constraint matrix ({int(stationarity_nl.numel())} KKT "
                       "stationarity row(s) nonlinear)")
    nonconvex = " and ".join(classes)
    if nonconvex and not nonconvex_leader:
        raise _refuse(nonconvex)
    leader = None
    if nonconvex_leader:
        leader = Leader(w, mpcc.params.substitute(mpcc.objective), upper_in_nl,
                        ca.vertcat(upper_eq_nl, stationarity_nl), nonconvex, tuple(slacks))
    n = int(w.numel())
    Q, c, c0 = (np.zeros((n, n)), np.zeros(n), 0.0) if isinstance(quadratic, str) else quadratic
    stack = lambda parts: np.vstack(parts) if parts else np.zeros((0, n))  # noqa: E731
    flat = lambda parts: np.concatenate(parts) if parts else np.zeros(0)  # noqa: E731
    return LinearMPCC(Q, c, c0, np.vstack([A_H, A_s, A_h]), -np.concatenate([r_H, r_s, r_h]), A_in, -r_in,
                      mpcc.lbw.astype(float), mpcc.ubw.astype(float), stack(G_rows), flat(g), stack(H_rows),
                      flat(h), tuple(labels), leader)
