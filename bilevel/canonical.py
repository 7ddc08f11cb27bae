"""Canonical (flattened) form of a declared bilevel problem, and the sense normalization (max -> min)."""

from __future__ import annotations

from dataclasses import dataclass, field, replace
from functools import cached_property
from typing import Callable

import casadi as ca
import numpy as np

from .errors import ModelError
from .lower import LowerLevel, LowerSolution, build_lower
from .linear_maps import Images
from .lower.images import ImageLower, Lift
from .lower.matrix import MatrixLower
from .lower.least_squares import sum_of_squares
from .lower.residual import NumericSquares, numeric_squares
from .model import BilevelProblem, LowerQP, MatrixFunction, Variable, check_constants, check_depends, unflatten_all
from .parameters import ParameterSet, scalar
from .reduction import KKTPoint, Reduction
from .sampling import default_start, sample_in_bounds
from .spectral_radius import rho_and_gradient


@dataclass
class CanonicalBilevel:
    """min/max F(x,y) s.t. G <= 0, H = 0 (upper); y solves min/max f s.t. g <= 0, h = 0, M_k >= 0.

    x and y are the flattened (column-major) upper and lower variables; lower bounds are rows of g.
    """

    x: ca.SX
    y: ca.SX
    x_lb: np.ndarray
    x_ub: np.ndarray
    x_start: np.ndarray
    F: ca.SX
    G: ca.SX
    H: ca.SX
    f: ca.SX
    g: ca.SX
    h: ca.SX
    psd: list[ca.SX]
    g_rows: list[tuple[str, int]]
    h_rows: list[tuple[str, int]]
    psd_names: list[str]
    upper_sense: str
    lower_sense: str
    upper_vars: list[Variable]
    lower_vars: list[Variable]
    y_start: np.ndarray | None = None
    G_names: list[str] = field(default_factory=list)
    x_suggested: list[np.ndarray] = field(default_factory=list)
    y_lb: np.ndarray | None = None
    y_ub: np.ndarray | None = None
    assume_convex: bool = False
    params: ParameterSet = field(default_factory=ParameterSet)
    """The problem's parameters: every function built from these expressions reads their current values."""
    lower_reference: Callable[[ca.SX, np.ndarray, np.ndarray], LowerSolution] | None = None
    """The declared problem's own independent lower solver, if any (BilevelProblem.lower_reference)."""
    matrices: LowerQP | None = None
    """A lower level given by matrices (lower_qp, bounds of y appended to A and b); f, g, h are then empty."""
    lifting: Lifting | None = None
    """The problem's definitions kept as variables, for the KKT reformulation (here they are substituted)."""
    images: Images | None = None
    """Products of linear maps (BilevelProblem.linear_map) used in the lower level: symbols z = A arg(x)."""
    spectral: ca.SX | None = None
    """A numeric upper objective's matrix M(x, y): F = spectral_sign * matrix_function(M) (the spectral radius of
    maximize_spectral_radius, or maximize_matrix_function's), and the expression F is NaN."""
    spectral_sign: float = 1.0
    matrix_function: MatrixFunction = rho_and_gradient
    """The numeric function of `spectral`: M -> (value, d value / dM)."""

    @cached_property
    def lower(self) -> LowerLevel:
        """The lower level as a classified kind (requires the minimization sense)."""
        if self.lower_sense != "min":
            raise ModelError("the lower level must be normalized to minimization first (NormalizeSense)")
        if self.matrices is not None:
            return MatrixLower(self.x, self.y, self.matrices, [f"{n}[{i}]" for n, i in self.g_rows],
                               [f"{n}[{i}]" for n, i in self.h_rows], self.params)
        rng = np.random.default_rng(0)
        samples = [self.x_start] + [sample_in_bounds(self.x_lb, self.x_ub, rng, 3.0) for _ in range(5)]
        x, lift = self.x, None
        if self.images is not None:  # the kind over [x; z]; ImageLower lifts x at every call
            lift = Lift(self.x, self.images, self.params)
            x, samples = ca.vertcat(self.x, self.images.sym), [lift(s) for s in samples]
        low = build_lower(x, self.y, self.f, self.g, self.h, self.psd,
                          [f"{n}[{i}]" for n, i in self.g_rows], [f"{n}[{i}]" for n, i in self.h_rows],
                          self.psd_names, samples, self.y_lb, self.y_ub, self.assume_convex, self.params,
                          matrices=lift is None)
        return low if lift is None else ImageLower(low, lift, self.x, self.params)

    @cached_property
    def G_ranges(self) -> tuple[np.ndarray, np.ndarray, Callable[[], np.ndarray] | None]:
        """The two-sided bounds among the rows of G: (upper, lower, width) with row upper[k] = e - b (e <= b) and row
        lower[k] = a - e (e >= a) for one expression node e of (x, y) and bounds a, b of the parameters alone (so
        G[upper[k]] + G[lower[k]] = a - b everywhere), and width(): the vector b - a at the parameters' current values
        (None without pairs). A solver may state each pair as one ranged row, G[upper[k]] in [a - b, 0], halving the
        rows a dense e brings (method reduced does)."""
        xy = ca.vertcat(self.x, self.y)
        upper_rows: dict[int, tuple[int, ca.SX]] = {}  # expression node -> (row, b) of `e - b`
        lower_rows: dict[int, tuple[int, ca.SX]] = {}  # expression node -> (row, a) of `a - e`
        free = lambda e: not ca.depends_on(e, xy)  # noqa: E731
        for i in range(int(self.G.numel())):
            row = self.G[i]
            if not row.is_op(ca.OP_SUB):
                continue
            left, right = row.dep(0), row.dep(1)
            if free(right) and not free(left):
                upper_rows.setdefault(left.element_hash(), (i, right))
            elif free(left) and not free(right):
                lower_rows.setdefault(right.element_hash(), (i, left))
        pairs = [(i, j, b - a) for node, (i, b) in upper_rows.items() if node in lower_rows
                 for j, a in [lower_rows[node]]]
        if not pairs:
            return np.zeros(0, dtype=int), np.zeros(0, dtype=int), None
        width = self.params.function("ranges", [], [ca.vertcat(*(w for _, _, w in pairs))])
        return (np.array([i for i, _, _ in pairs]), np.array([j for _, j, _ in pairs]),
                lambda: np.asarray(width(), dtype=float).ravel())

    @cached_property
    def squares(self) -> NumericSquares | None:
        """F as NumericSquares where it is a sum of squares of y alone with a numeric matrix written into it (value
        and y-gradient by BLAS; a sweep walks the matrix's entries), else None."""
        if self.spectral is not None:
            return None
        return numeric_squares(self.F, self.y, ca.vertcat(self.x, self.params.sym))

    @cached_property
    def functions(self) -> Callable[[np.ndarray, np.ndarray], list[np.ndarray]]:
        """F, G, H at (x, y) (F by `squares` where it is numeric)."""
        squares = self.squares
        sweep = self.params.function("canon", [self.x, self.y], [ca.SX(1, 1) if squares else self.F, self.G, self.H])
        if squares is None:
            return sweep
        return lambda x, y: [squares(np.asarray(y, dtype=float).ravel())[0], *sweep(x, y)[1:]]

    @cached_property
    def _upper(self) -> ca.Function:
        xy = ca.vertcat(self.x, self.y)
        return self.params.function("upper", [self.x, self.y], [self.F, self.G, self.H, ca.jacobian(self.G, xy),
                                                                ca.jacobian(self.H, xy)])

    @cached_property
    def _objective_y(self) -> ca.Function:
        return self.params.function("upper_objective_y", [self.x, self.y], [self.F, ca.gradient(self.F, self.y)])

    @cached_property
    def _spectral_matrix(self) -> ca.Function:
        return self.params.function("spectral", [self.x, self.y], [self.spectral])

    def upper_F(self, x: np.ndarray, y: np.ndarray, F: ca.DM) -> float:
        """F at (x, y) from the sweep's value F, or the spectral radius for a spectral objective."""
        if self.spectral is None:
            return scalar(F)
        return self.spectral_sign * float(self.matrix_function(np.asarray(self._spectral_matrix(x, y), dtype=float))[0])

    def upper_values(self, x: np.ndarray, y: np.ndarray) -> tuple[float, np.ndarray, np.ndarray, np.ndarray,
                                                                  np.ndarray]:
        """F, G, H and the Jacobians of G and H in (x, y) at (x, y)."""
        out = self._upper(x, y)
        return (self.upper_F(x, y, out[0]), np.asarray(out[1]).ravel(), np.asarray(out[2]).ravel(), np.asarray(out[3]),
                np.asarray(out[4]))

    def upper_objective_y(self, x: np.ndarray, y: np.ndarray) -> tuple[float, np.ndarray]:
        """F and grad_y F at (x, y), without the upper constraints."""
        F, grad = self._objective_y(x, y)
        return self.upper_F(x, y, F), np.asarray(grad).ravel()


@dataclass
class Lifting:
    """Definitions (BilevelProblem.define) as variables z: their values as expressions of x, and the problem over
    [x; z] with the expressions as declared and the definitions' equations appended to the upper equalities."""

    z: ca.SX
    value: ca.SX
    raw: CanonicalBilevel

    @cached_property
    def values(self) -> ca.Function:
        """x -> z, at the parameters' current values."""
        return self.raw.params.function("definitions", [self.raw.x[: self.raw.x.numel() - self.z.numel()]],
                                        [self.value])

    def lift(self, x: np.ndarray) -> np.ndarray:
        """[x; z(x)]."""
        return np.concatenate([x, np.asarray(self.values(x), dtype=float).ravel()])


def _eliminate(canon: CanonicalBilevel, problem: BilevelProblem) -> CanonicalBilevel:
    """The canonical problem with the problem's definitions substituted, keeping the declared form in its
    `lifting`."""
    definitions = problem.definitions
    z, value = problem.definition_values()
    equations = ca.vertcat(*[d.equation for d in definitions])
    check = canon.params.function("definition_check", [canon.x], [ca.substitute(equations, z, value), value])
    rng = np.random.default_rng(0)
    for x in [canon.x_start] + [sample_in_bounds(canon.x_lb, canon.x_ub, rng, 1.0) for _ in range(2)]:
        gap, val = (np.asarray(v, dtype=float).ravel() for v in check(x))
        if np.abs(gap).max(initial=0.0) > 1e-8 * (1.0 + np.abs(val).max(initial=0.0)):
            i = int(np.argmax(np.abs(gap)))
            owner = next(d.name for d, k in zip(definitions, np.cumsum([d.sym.numel() for d in definitions]))
                         if i < k)
            raise ModelError(f"define({owner!r}): its equation is {gap[i]:.3g} (not 0) at its value; the equation "
                             "must vanish exactly where the symbol equals the value")
    sub = lambda e: ca.substitute(e, z, value)  # noqa: E731
    n_z = int(z.numel())
    raw = replace(canon, x=ca.vertcat(canon.x, z), x_lb=np.concatenate([canon.x_lb, np.full(n_z, -np.inf)]),
                  x_ub=np.concatenate([canon.x_ub, np.full(n_z, np.inf)]),
                  x_start=np.concatenate([canon.x_start, np.asarray(check(canon.x_start)[1], dtype=float).ravel()]),
                  H=ca.vertcat(canon.H, equations), x_suggested=[], lower_reference=None)
    mats = canon.matrices
    if mats is not None:
        mats = replace(mats, d=sub(mats.d), q=sub(mats.q), b=sub(mats.b), e=sub(mats.e), r=sub(mats.r))
    return replace(canon, F=sub(canon.F), G=sub(canon.G), H=sub(canon.H), f=sub(canon.f), g=sub(canon.g),
                   h=sub(canon.h), psd=[sub(m) for m in canon.psd], matrices=mats, lifting=Lifting(z, value, raw),
                   spectral=None if canon.spectral is None else sub(canon.spectral))


@dataclass
class BilevelSolution:
    """A solution mapped back to the user's names: values, multipliers and objectives in declared senses."""

    point: KKTPoint
    upper_objective: float
    lower_objective: float
    x: dict[str, np.ndarray] = field(default_factory=dict)
    y: dict[str, np.ndarray] = field(default_factory=dict)
    multipliers: dict[str, np.ndarray] = field(default_factory=dict)


def _flat(vars_: list[Variable]) -> ca.SX:
    return ca.vertcat(*[ca.vec(v.sym) for v in vars_]) if vars_ else ca.SX(0, 1)


def _check_depends(expr: ca.SX, allowed: ca.SX, where: str,
                   pending: list[tuple[ca.SX, str]] | None = None) -> None:
    """check_depends for a declared expression: it may use the declared variables, definitions and parameters (and,
    in the lower level, products of linear maps); its constants are checked now, or with pending's (check_constants:
    the expressions' shared data read once)."""
    check_depends(expr, allowed, where, "are not variables declared on this problem (declare them with "
                  "upper_variable/lower_variable), or are products of a linear map outside the lower level (they "
                  "stand for data of the lower level: in the upper level write the product as an expression)",
                  constants=pending is None)
    if pending is not None:
        pending.append((expr, where))


def suggested_starts(problem: BilevelProblem, x_start: np.ndarray, x_lb: np.ndarray,
                     x_ub: np.ndarray) -> list[np.ndarray]:
    """The problem's suggested starts as flat upper points (unnamed variables at x_start), clipped to the box."""
    layout = problem.upper_layout()
    return [np.clip(np.concatenate([s.get(v.name, x_start[layout[v.name]]) for v in problem.upper_variables]),
                    x_lb, x_ub) for s in problem.suggested_starts]


def _least_squares_matrices(problem: BilevelProblem, allowed: ca.SX) -> LowerQP:
    """A lower level written with linear maps of the lower variable, min_y sum_i w_i r_i(x, y, z)^2 with z = A_j L_j y
    and r affine in (y, z) with constant coefficients, as the matrix form 1/2 ||C y - d(x)||^2 (lower_qp's)."""
    where = "a lower level with products of linear maps of the lower variable"
    lows = problem.lower_variables
    if len(lows) != 1 or lows[0].matrix is not None or lows[0].shape[1] != 1:
        raise ModelError(f"{where} must have one vector lower variable (y = p.lower_variable('y', n)); got "
                         f"{', '.join(v.name for v in lows)}")
    if problem.lower_objective is None or problem.lower_constraints or problem.lower_psd_constraints \
            or problem.lower_objective.sense != "min":
        raise ModelError(f"{where} is a least squares: minimize a sum of squares, with bounds on the variable only "
                         "(for constraints use lower_qp with numeric matrices)")
    if any(i.level == "upper" for i in problem.images):
        raise ModelError(f"{where} cannot also use linear maps of upper variables; write one of them as an expression")
    y, imgs = lows[0].sym, [i for i in problem.images if i.level == "lower"]
    expr = problem.lower_objective.expr
    _check_depends(expr, ca.vertcat(allowed, *[ca.vec(i.sym) for i in imgs]), "the lower objective")
    yz = ca.vertcat(y, *[ca.vec(i.sym) for i in imgs])
    form = sum_of_squares(expr, yz)
    if form is None:
        raise ModelError(f"{where} must be a least squares: a sum of squares of expressions affine in the lower "
                         "variable and the products (e.g. ca.sumsqr(A @ y - b)); use lower_qp for other quadratics")
    if not ca.simplify(form[1]).is_zero():
        raise ModelError(f"{where}: the objective has terms without the lower variable ({form[1]}); drop them "
                         "(they do not change the learner's solution)")
    r = form[0]
    jac = ca.jacobian(r, yz)
    if ca.depends_on(jac, ca.vertcat(*[ca.vec(v.sym) for v in problem.upper_variables], problem.parameters.sym)):
        raise ModelError(f"{where}: the coefficients of the lower variable and the products depend on upper "
                         "variables or parameters; with a linear map of the lower variable they must be numbers")
    jac = ca.evalf(jac).sparse()  # scipy.sparse: a residual r = A y - b has the identity in z
    n = y.numel()
    C, k = jac[:, :n].toarray(), n
    for img in imgs:
        offset = ca.substitute(img.arg, y, ca.DM.zeros(n))
        if img.arg.size2() != 1 or not offset.is_constant() or np.any(np.asarray(ca.evalf(offset))) or \
                any(ca.which_depends(img.arg, y, 2, False)):
            raise ModelError(f"{where}: {img.name} maps an expression that is not a linear function of the lower "
                             "variable alone; apply the map to the variable itself (A @ y)")
        L = np.asarray(ca.evalf(ca.jacobian(img.arg, y)), dtype=float)
        m = int(img.sym.numel())
        C += np.asarray(jac[:, k:k + m] @ np.asarray(img.operator.apply(L), dtype=float))
        k += m
    d = -ca.substitute(r, yz, ca.DM.zeros(int(yz.numel())))
    zeros = np.zeros((0, n))
    return LowerQP(lows[0], C, np.zeros((n, n)), zeros, zeros, d, ca.SX.zeros(n), ca.SX(0, 1), ca.SX(0, 1))


class Canonicalize(Reduction):
    """BilevelProblem -> CanonicalBilevel: flatten variables, split constraints, move lower bounds into g."""

    def apply(self, problem: BilevelProblem) -> tuple[CanonicalBilevel, CanonicalBilevel]:
        if problem.upper_objective is None:
            raise ModelError(f"{problem.name}: no upper objective; call minimize_upper or maximize_upper")
        if problem.lower_objective is None and problem.lower_matrices is None:
            raise ModelError(f"{problem.name}: no lower objective; call minimize_lower or maximize_lower")
        if not problem.lower_variables:
            raise ModelError(f"{problem.name}: no lower variables; declare them with lower_variable")
        ups, lows = problem.upper_variables, problem.lower_variables
        x, y = _flat(ups), _flat(lows)
        defined = [ca.vec(d.sym) for d in problem.definitions]
        upper_images = tuple(i for i in problem.images if i.level == "upper")
        images = Images(upper_images) if upper_images else None
        upper_allowed = ca.vertcat(x, y, *defined, problem.parameters.sym)  # the symbols an expression may use
        allowed = upper_allowed if images is None else ca.vertcat(upper_allowed, ca.vec(images.sym))
        pending: list[tuple[ca.SX, str]] = []  # expressions whose constants are checked together
        spectral = problem.upper_objective.matrix  # F is then NaN: the objective is function(matrix)
        if spectral is None:
            _check_depends(problem.upper_objective.expr, upper_allowed, "the upper objective", pending)
        else:
            _check_depends(spectral, upper_allowed, "the upper objective's matrix", pending)
        mats = problem.lower_matrices
        if any(i.level == "lower" for i in problem.images):
            mats = _least_squares_matrices(problem, allowed)
        for what, expr in ([] if mats is None else [("d", mats.d), ("q", mats.q), ("b", mats.b), ("e", mats.e)]):
            _check_depends(expr, upper_allowed, f"lower_qp's {what}", pending)
            if ca.depends_on(expr, y):
                raise ModelError(f"lower_qp's {what} depends on the lower variable; d, q, b, e are data: expressions "
                                 "of upper variables and parameters only")
        if mats is None:
            _check_depends(problem.lower_objective.expr, allowed, "the lower objective", pending)
        G, H, G_names = [], [], []
        for c in problem.upper_constraints:
            _check_depends(c.body, upper_allowed, f"upper constraint {c.name!r}", pending)
            (G if c.kind == "<=" else H).append(c.body)
            if c.kind == "<=":
                G_names += [f"{c.name}[{i}]" for i in range(int(c.body.numel()))]
        g, h, g_rows, h_rows = [], [], [], []
        for c in problem.lower_constraints:
            _check_depends(c.body, allowed, f"lower constraint {c.name!r}", pending)
            if not ca.depends_on(c.body, y):
                raise ModelError(f"lower constraint {c.name!r} does not involve lower variables; "
                                 "declare it with upper_constraint if it constrains the leader")
            rows = [(c.name, i) for i in range(int(c.body.numel()))]
            if c.kind == "<=":
                g.append(c.body)
                g_rows += rows
            else:
                h.append(c.body)
                h_rows += rows
        for v in lows:
            flat = ca.vec(v.sym)
            for side, bound, sign in (("lb", v.lb, -1.0), ("ub", v.ub, 1.0)):
                idx = np.flatnonzero(np.isfinite(bound))
                for i in idx:
                    g.append(sign * (flat[int(i)] - bound[i]))
                    g_rows.append((f"{v.name}.{side}", int(i)))
        if mats is not None:  # the bound rows (already in g_rows) become rows of A y <= b: [A; -I; I], [b; -lb; ub]
            var, eye = mats.variable, np.eye(mats.variable.size)
            lb_rows, ub_rows = np.flatnonzero(np.isfinite(var.lb)), np.flatnonzero(np.isfinite(var.ub))
            g_rows = [("A", i) for i in range(mats.A.shape[0])] + g_rows
            h_rows, g, h = [("E", i) for i in range(mats.E.shape[0])], [], []
            mats = replace(mats, A=np.vstack([mats.A, -eye[lb_rows], eye[ub_rows]]),
                           b=ca.vertcat(mats.b, ca.DM(-var.lb[lb_rows]), ca.DM(var.ub[ub_rows])))
        for m in problem.lower_psd_constraints:
            _check_depends(m.matrix, allowed, f"LMI {m.name!r}", pending)
        check_constants(pending)
        y_lb, y_ub = (np.concatenate([getattr(v, side) for v in lows]) for side in ("lb", "ub"))
        x_lb = np.concatenate([v.lb for v in ups]) if ups else np.zeros(0)
        x_ub = np.concatenate([v.ub for v in ups]) if ups else np.zeros(0)
        x_start = default_start(x_lb, x_ub, np.concatenate([v.start if v.start is not None else
                                                            np.clip(np.zeros(v.size), v.lb, v.ub) for v in ups])
                                if ups else None)
        y_start = (np.concatenate([v.start if v.start is not None else np.zeros(v.size) for v in lows])
                   if any(v.start is not None for v in lows) else None)
        vert = lambda parts: ca.vertcat(*parts) if parts else ca.SX(0, 1)  # noqa: E731
        canon = CanonicalBilevel(
            x=x, y=y, x_lb=x_lb, x_ub=x_ub, x_start=x_start, F=problem.upper_objective.expr, G=vert(G), H=vert(H),
            f=ca.SX(0, 1) if mats is not None else problem.lower_objective.expr, g=vert(g), h=vert(h),
            psd=[m.matrix for m in problem.lower_psd_constraints], g_rows=g_rows, h_rows=h_rows,
            psd_names=[m.name for m in problem.lower_psd_constraints], upper_sense=problem.upper_objective.sense,
            lower_sense="min" if mats is not None else problem.lower_objective.sense, upper_vars=ups, lower_vars=lows,
            y_start=y_start,
            G_names=G_names, x_suggested=suggested_starts(problem, x_start, x_lb, x_ub), y_lb=y_lb, y_ub=y_ub,
            assume_convex=mats is None and problem.lower_objective.assume_convex, params=problem.parameters,
            lower_reference=problem.lower_reference, matrices=mats, images=images, spectral=spectral,
            matrix_function=problem.upper_objective.function or rho_and_gradient,
        )
        if problem.definitions:
            canon = _eliminate(canon, problem)
        return canon, canon

    def invert(self, solution: BilevelSolution, canon: CanonicalBilevel) -> BilevelSolution:
        """Split flat x, y into the declared variables and multipliers into the declared constraints."""
        p = solution.point
        solution.x.update(unflatten_all(canon.upper_vars, p.x))
        solution.y.update(unflatten_all(canon.lower_vars, p.y))
        mult: dict[str, np.ndarray] = {}
        for rows, values in ((canon.g_rows, p.lam), (canon.h_rows, p.mu)):
            for (name, i), value in zip(rows, values):
                mult.setdefault(name, []).append((i, value))
        solution.multipliers = {name: self._dense(entries) for name, entries in mult.items()}
        solution.multipliers.update(zip(canon.psd_names, p.Z))
        return solution

    @staticmethod
    def _dense(entries: list[tuple[int, float]]) -> np.ndarray:
        out = np.zeros(max(i for i, _ in entries) + 1)
        for i, value in entries:
            out[i] = value
        return out


def in_sense(value: float, sense: str) -> float:
    """A value of a normalized (minimized) objective in its declared sense: negated where it was maximized."""
    return -value if sense == "max" else value


class NormalizeSense(Reduction):
    """max F -> min -F and max f -> min -f, so nothing downstream reasons about signs; invert restores them.

    Multipliers need no change: with L = -f + lam' g, stationarity of the max problem reads grad f = J' lam.
    """

    def apply(self, canon: CanonicalBilevel) -> tuple[CanonicalBilevel, tuple[str, str]]:
        senses = (canon.upper_sense, canon.lower_sense)
        out = replace(canon, F=-canon.F if senses[0] == "max" else canon.F,
                      spectral_sign=-canon.spectral_sign if senses[0] == "max" else canon.spectral_sign,
                      f=-canon.f if senses[1] == "max" else canon.f, upper_sense="min", lower_sense="min")
        if canon.lifting is not None:
            out.lifting = replace(canon.lifting, raw=self.apply(canon.lifting.raw)[0])
        return out, senses

    def invert(self, solution: BilevelSolution, senses: tuple[str, str]) -> BilevelSolution:
        solution.upper_objective = in_sense(solution.upper_objective, senses[0])
        solution.lower_objective = in_sense(solution.lower_objective, senses[1])
        return solution


def objectives(canon: CanonicalBilevel, point: KKTPoint) -> tuple[float, float]:
    """(F, f) at a point, in the canonical problem's senses."""
    return (canon.upper_F(point.x, point.y, canon.functions(point.x, point.y)[0]),
            canon.lower.evaluate(point.x, point.y)[0])


def kkt_solution(canon: CanonicalBilevel, point: KKTPoint) -> BilevelSolution:
    """Wrap a canonical point with its objective values, ready to be inverted to user names."""
    F, f = objectives(canon, point)
    return BilevelSolution(point, F, f)

