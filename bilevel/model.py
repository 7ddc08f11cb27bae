"""Declaring a bilevel problem: upper/lower variables, objectives and constraints, read like the maths.

    p = BilevelProblem("bard")
    x = p.upper_variable("x", lb=0)
    y = p.lower_variable("y", lb=0)
    p.minimize_upper(x - 4 * y)
    p.minimize_lower(y)
    p.lower_constraint(-x - y <= -3)
    res = p.solve()

Expressions are CasADi SX expressions of the declared variables.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any, Callable, Literal

import casadi as ca
import numpy as np

from .errors import InvalidData, ModelError, UnknownName, did_you_mean, renamed
from .linear_maps import Image, LinearMap, Operator
from .parameters import ParameterSet
from .real_data import refuse_complex
from .spectral_radius import rho_and_gradient
from .vech import symmetric_from_vech, unvech, vech

if TYPE_CHECKING:  # pragma: no cover
    import cvxpy as cp

    from .frontends.cvxpy_lower import CvxpyLower
    from .lower.base import LowerSolution
    from .result import BilevelResult

Level = Literal["upper", "lower"]
Sense = Literal["min", "max"]
MatrixFunction = Callable[[np.ndarray], tuple[float, np.ndarray]]
"""A numeric upper objective of a matrix M: M -> (value, d value / dM with M's shape), e.g. the spectral radius."""


@dataclass(frozen=True)
class Variable:
    """A declared block of variables: its symbol, shape, bounds (flattened column-major) and start.

    A symmetric n x n variable has n(n+1)/2 free symbols `sym` (its vech: lower triangle, column by
    column), the symmetric matrix built from them in `matrix`, and bounds/start per vech entry.
    """

    name: str
    level: Level
    sym: ca.SX
    lb: np.ndarray
    ub: np.ndarray
    start: np.ndarray | None = None
    matrix: ca.SX | None = None

    @property
    def expr(self) -> ca.SX:
        """What the user writes with: the symbol, or the symmetric matrix of a symmetric variable."""
        return self.sym if self.matrix is None else self.matrix

    @property
    def shape(self) -> tuple[int, int]:
        return (int(self.expr.size1()), int(self.expr.size2()))

    @property
    def size(self) -> int:
        return int(self.sym.numel())

    def unflatten(self, values: np.ndarray) -> np.ndarray:
        """Turn a flat (column-major) slice back into this variable's shape (1-D for vectors)."""
        rows, cols = self.shape
        values = np.asarray(values, dtype=float)
        if self.matrix is not None:
            return unvech(values, rows)
        return values.reshape(rows) if cols == 1 else values.reshape((rows, cols), order="F")


def unflatten_all(variables: list[Variable], flat: np.ndarray) -> dict[str, np.ndarray]:
    """A flat vector over `variables` (their flattened values in order) split into each variable's shape."""
    out, k = {}, 0
    for v in variables:
        out[v.name] = v.unflatten(flat[k:k + v.size])
        k += v.size
    return out


@dataclass(frozen=True)
class Constraint:
    """`body <= 0` (kind "<=") or `body == 0` (kind "=="), with a name for its multipliers."""

    name: str
    body: ca.SX
    kind: Literal["<=", "=="]


@dataclass(frozen=True)
class Definition:
    """A named expression of the upper variables (BilevelProblem.define): its symbol, its value, and the equation
    (zero exactly where the symbol equals the value) that the KKT reformulation imposes on it."""

    name: str
    sym: ca.SX
    value: ca.SX
    equation: ca.SX


@dataclass(frozen=True)
class PSDConstraint:
    """A linear matrix inequality `matrix >= 0` (positive semidefinite), symmetric by declaration."""

    name: str
    matrix: ca.SX


@dataclass(frozen=True)
class LowerQP:
    """A lower level given by matrices (BilevelProblem.lower_qp): numeric C, P, A, E and vector expressions d, q,
    b, e of the upper variables and parameters, and a constant term r of theirs (0 for lower_qp)."""

    variable: Variable | None
    """The declared lower variable; None for a form recognized from expressions (bilevel.lower.qp_form)."""
    C: np.ndarray
    P: np.ndarray
    A: np.ndarray
    E: np.ndarray
    d: ca.SX
    q: ca.SX
    b: ca.SX
    e: ca.SX
    r: ca.SX = field(default_factory=lambda: ca.SX.zeros(1))


@dataclass
class Objective:
    """An objective and its sense; assume_convex (lower level only) skips the convexity probe. An upper objective
    with a `matrix` is the numeric `function` of that matrix (expr is then NaN: it has no CasADi expression)."""

    expr: ca.SX
    sense: Sense
    assume_convex: bool = False
    matrix: ca.SX | None = None
    function: MatrixFunction | None = None


def _bounds(name: str, size: int, lb: Any, ub: Any, symmetric: bool) -> tuple[np.ndarray, np.ndarray]:
    """A variable's bounds as flat arrays, checked: lb <= ub, no lb of +inf or ub of -inf."""
    lbv = _bound_array(lb, size, f"lower bound of {name!r}", symmetric)
    ubv = _bound_array(ub, size, f"upper bound of {name!r}", symmetric)
    if np.any(lbv > ubv):
        raise ModelError(f"variable {name!r}: a lower bound exceeds its upper bound")
    if np.any(lbv == np.inf) or np.any(ubv == -np.inf):
        raise ModelError(f"variable {name!r}: a lower bound of +inf or an upper bound of -inf leaves no "
                         "feasible value; use lb=-inf / ub=inf for a free variable")
    return lbv, ubv


def _bound_array(value: Any, size: int, what: str, symmetric: bool = False) -> np.ndarray:
    try:
        arr = np.asarray(value, dtype=float)
    except (TypeError, ValueError):
        raise ModelError(f"{what} must be a number or an array of numbers, got {type(value).__name__}") from None
    if arr.ndim == 2:
        if symmetric and arr.shape[0] == arr.shape[1]:
            if not np.allclose(arr, arr.T, equal_nan=True):
                raise ModelError(f"{what} is not symmetric; a symmetric variable takes a symmetric matrix")
            arr = vech(arr)
        else:
            arr = arr.reshape(-1, order="F")
    if arr.ndim == 0:
        arr = np.full(size, float(arr))
    if arr.shape != (size,):
        raise ModelError(f"{what} has {arr.size} entries but the variable has {size}; pass a scalar or {size} values")
    if np.isnan(arr).any():
        raise ModelError(f"{what} contains NaN; use -inf/inf for a missing bound")
    return arr


def _shape_of(value: Any, where: str) -> tuple[int, int]:
    if not isinstance(value, (ca.SX, ca.MX, ca.DM)):
        refuse_complex(value, where)
    try:
        return tuple(ca.SX(value).shape)
    except (NotImplementedError, TypeError, RuntimeError):
        raise ModelError(f"{where}: expected a CasADi expression, got {type(value).__name__}") from None


def _expression(value: Any, where: str, want: str = "a CasADi expression or numbers") -> ca.SX:
    """value (a CasADi expression, a number or an array of numbers) as an SX; ModelError naming `where` otherwise."""
    if not isinstance(value, (ca.SX, ca.MX, ca.DM)):
        refuse_complex(value, where)
    try:
        return value if isinstance(value, ca.SX) else ca.SX(value)
    except (NotImplementedError, TypeError, RuntimeError):
        raise ModelError(f"{where}: expected {want}, got {type(value).__name__}") from None


def check_depends(expr: ca.SX, allowed: ca.SX, where: str, fix: str, constants: bool = True) -> None:
    """Raise if expr uses symbols outside `allowed` (a column of the distinct symbols it may use; `fix` says which
    those are and what to do), or, with constants, if its data (the constants in it) contain NaN or inf (callers
    checking several expressions pass constants=False and call check_constants on them all once)."""
    free = ca.Function("uses", [allowed], [expr], {"allow_free": True}).free_sx()  # no per-symbol Python objects
    if free:
        names = ", ".join(str(s) for s in free[:5]) + (f", ... ({len(free)} in all)" if len(free) > 5 else "")
        raise ModelError(f"{where} uses symbols {names} that {fix}")
    if constants:
        check_constants([(expr, where)])


def check_constants(exprs: list[tuple[ca.SX, str]]) -> None:
    """InvalidData naming the first of these (expression, where) whose data (the constants in it) hold NaN or inf;
    their shared subexpressions are read once."""
    if not exprs or _bad_constant(ca.vertcat(*[ca.vec(e) for e, _ in exprs])) is None:
        return
    for expr, where in exprs:
        bad = _bad_constant(expr)
        if bad is not None:
            raise InvalidData(f"{where} contains the constant {bad} (NaN/inf in the data); "
                              "clean or impute the data before building the problem")


def _bad_constant(expr: ca.SX) -> float | None:
    """A constant of expr's graph that is NaN or inf, or None."""
    fun = ca.Function("data", [], [expr], {"allow_free": True})  # its symbols stay free: no list of them is built
    is_constant, constant = fun.instruction_id, fun.instruction_constant
    for k in range(fun.n_instructions()):
        if is_constant(k) == ca.OP_CONST and not math.isfinite(constant(k)):
            return constant(k)
    return None


DEFINITION_USES = ("are not upper variables, parameters or earlier definitions of this problem; a definition "
                   "depends on the leader's choices only")


def split_comparison(expr: Any, where: str) -> tuple[ca.SX, Literal["<=", "=="]]:
    """Turn `a <= b`, `a >= b` or `a == b` (CasADi SX) into (`a - b`, kind) so that body <= 0 or == 0."""
    if not isinstance(expr, ca.SX):
        raise ModelError(
            f"{where} expects a CasADi comparison such as `g <= 0` or `h == 0`, got {type(expr).__name__}; "
            "write the constraint with the declared variables"
        )
    if expr.is_constant():
        raise ModelError(f"{where}: the comparison contains no variables (it evaluates to {expr}); check the expression")
    bodies, kinds = [], set()
    for i in range(expr.numel()):
        e = expr[i]
        if e.is_op(ca.OP_LE) or e.is_op(ca.OP_LT):
            kinds.add("<=")
        elif e.is_op(ca.OP_EQ):
            kinds.add("==")
        else:
            raise ModelError(
                f"{where}: entry {i} is `{e}`, not a comparison; write `g <= h`, `g >= h` or `g == h`"
            )
        for side in (e.dep(0), e.dep(1)):
            if side.is_constant() and not np.isfinite(float(side)):
                raise ModelError(f"{where}: entry {i} compares with {float(side)}; a bound at infinity is no "
                                 "constraint: drop it, or use lb/ub of the variable for finite bounds")
        bodies.append(e.dep(0) - e.dep(1))
    if len(kinds) != 1:
        raise ModelError(f"{where}: mixes equalities and inequalities; declare them separately")
    return ca.vertcat(*bodies), kinds.pop()


class BilevelProblem:
    """min_x F(x, y) s.t. G(x, y) <= 0, y in argmin_y { f(x, y) : g(x, y) <= 0, h(x, y) = 0, M(x, y) >= 0 }.

    The lower level must be convex in y for every fixed x (this is checked where detectable).
    Bounds of lower variables belong to the lower level; bounds of upper variables to the upper level.
    """

    def __init__(self, name: str = "bilevel") -> None:
        if not isinstance(name, str):
            raise ModelError(f"BilevelProblem: name {name!r} must be a string")
        self.name = name
        self.variables: list[Variable] = []
        self.upper_objective: Objective | None = None
        self.lower_objective: Objective | None = None
        self.upper_constraints: list[Constraint] = []
        self.lower_constraints: list[Constraint] = []
        self.lower_psd_constraints: list[PSDConstraint] = []
        self.definitions: list[Definition] = []
        self.suggested_starts: list[dict[str, np.ndarray]] = []
        self.parameters = ParameterSet()
        self.revision = 0
        """Incremented by every declaration (not by set_value, set_bounds or suggest_start): solves reuse their
        preparation while it is unchanged."""
        self.bounds_revision = 0
        """Incremented by set_bounds: a prepared problem reads the new box of the upper variables at its next solve."""
        self.lower_matrices: LowerQP | None = None
        """The lower level given by matrices (lower_qp), if it was declared that way."""
        self.images: list[Image] = []
        """Products `T @ expr` of declared linear maps (linear_map), kept as symbols."""
        self.lower_reference: Callable[[ca.SX, np.ndarray, np.ndarray], LowerSolution] | None = None
        """An independent solver of the lower level that the certificate re-solves with instead of the engine's,
        (x symbols, x, y) -> LowerSolution; set by a front end that has the user's own model (lower_cvxpy)."""

    # -- variables -----------------------------------------------------------------------------
    def _variable(self, level: Level, name: str, shape: int | tuple[int, int], lb: Any, ub: Any, start: Any,
                  symmetric: bool = False) -> ca.SX:
        rows, cols = self._new_shape("variable", name, shape)
        matrix = None
        if symmetric:
            if rows != cols:
                raise ModelError(f"variable {name!r}: a symmetric variable must be square, got shape {shape}")
            matrix, sym = symmetric_from_vech(name, int(rows))
        else:
            sym = ca.SX.sym(name, int(rows), int(cols))
        size = int(sym.numel())
        lbv, ubv = _bounds(name, size, lb, ub, symmetric)
        st = None if start is None else _bound_array(start, size, f"start of {name!r}", symmetric)
        if st is not None and not np.all(np.isfinite(st)):
            raise ModelError(f"start of {name!r} contains inf; give finite start values")
        self.variables.append(Variable(name, level, sym, lbv, ubv, st, matrix))
        self.revision += 1
        return sym if matrix is None else matrix

    def _new_shape(self, what: str, name: str, shape: Any) -> tuple[int, int]:
        """Check a new name and its shape (an int or a pair of positive ints); (rows, cols)."""
        self._check_new_name(name)
        try:
            rows, cols = (shape, 1) if isinstance(shape, (int, np.integer)) else tuple(int(n) for n in shape)
        except (TypeError, ValueError):
            raise ModelError(f"{what} {name!r}: shape {shape!r} must be an int or a pair (rows, cols)") from None
        if rows < 1 or cols < 1:
            raise ModelError(f"{what} {name!r}: shape {shape} must be positive")
        return int(rows), int(cols)

    def _check_new_name(self, name: str) -> None:
        if not isinstance(name, str) or not name.isidentifier():
            raise ModelError(f"name {name!r} must be a Python identifier")
        if self._taken(name):
            raise ModelError(f"a variable, parameter or definition named {name!r} is already declared; names must "
                             "be unique")

    def _taken(self, name: str) -> bool:
        """Whether a variable, parameter, definition or linear-map product already has this name."""
        return (any(v.name == name for v in self.variables) or any(p.name == name for p in self.parameters.items)
                or any(d.name == name for d in self.definitions) or any(i.name == name for i in self.images))

    def parameter(self, name: str, shape: int | tuple[int, int] = 1, value: Any = None) -> ca.SX:
        """Declare data that can be re-set without rebuilding (set_value); returns its CasADi symbol.

        Solving again after set_value reuses the canonical form, classification, reduction and compiled functions.
        """
        rows, cols = self._new_shape("parameter", name, shape)
        sym = ca.SX.sym(name, rows, cols)
        self.parameters.add(name, sym, value)
        self.revision += 1
        return sym

    def set_value(self, name: str, value: Any) -> None:
        """Set the value of parameter `name` (its declared shape, or flattened column-major)."""
        self.parameters.set(name, value)

    def set_bounds(self, name: str, lb: Any = None, ub: Any = None) -> None:
        """Re-set the box of upper variable `name` (a budget) without rebuilding, like set_value for data: the next
        solve keeps the preparation and uses the new box (and a start clipped into it). None keeps that side."""
        var = next((v for v in self.variables if v.name == name), None)
        if var is None:
            raise UnknownName(f"no variable named {name!r}; {did_you_mean(name, [v.name for v in self.variables])}"
                              f"the upper variables are {', '.join(v.name for v in self.upper_variables) or 'none'}")
        if var.level != "upper":
            raise ModelError(f"set_bounds: {name!r} is a lower variable, whose bounds are lower-level constraints "
                             "(part of the declaration); declare them as data instead (a parameter in a constraint)")
        symmetric = var.matrix is not None
        lbv, ubv = _bounds(name, var.size, var.lb if lb is None else lb, var.ub if ub is None else ub, symmetric)
        var.lb[:], var.ub[:] = lbv, ubv  # in place: the prepared problem holds these arrays
        self.bounds_revision += 1

    def upper_variable(self, name: str, shape: int | tuple[int, int] = 1, lb: Any = -np.inf,
                       ub: Any = np.inf, start: Any = None, symmetric: bool = False) -> ca.SX:
        """Declare upper-level (leader) variables; returns their CasADi symbol (see lower_variable)."""
        return self._variable("upper", name, shape, lb, ub, start, symmetric)

    def lower_variable(self, name: str, shape: int | tuple[int, int] = 1, lb: Any = -np.inf,
                       ub: Any = np.inf, start: Any = None, symmetric: bool = False) -> ca.SX:
        """Declare lower-level (follower) variables; their bounds are lower-level constraints.

        symmetric=True (shape (n, n)) returns a symmetric n x n matrix of n(n+1)/2 free variables;
        lb, ub and start are then scalars, symmetric n x n matrices or n(n+1)/2 vech values, and the
        result reports the full matrix.
        """
        self._check_lower_open("lower_variable")
        return self._variable("lower", name, shape, lb, ub, start, symmetric)

    def define(self, name: str, value: Any, equation: Callable[[ca.SX], Any] | None = None) -> ca.SX:
        """Name an expression of the upper variables and parameters (a filtered signal, a regressor); returns its
        symbol, to write with as with the expression itself.

        Methods that eliminate the lower level substitute `value`. The KKT reformulation (ipopt, relaxation) keeps
        the symbol z as a variable bound by `equation(z) == 0` (default z - value): given as a recursion (e.g. a
        difference equation) it keeps the NLP's derivatives sparse where the explicit value would make them dense.
        """
        rows, cols = self._new_shape("definition", name, _shape_of(value, f"define({name!r})"))
        value = ca.SX(value)
        earlier = [ca.vec(v.sym) for v in self.upper_variables] + [ca.vec(d.sym) for d in self.definitions]
        allowed = ca.vertcat(*earlier, self.parameters.sym)
        check_depends(value, allowed, f"define({name!r}): the value", DEFINITION_USES)
        sym = ca.SX.sym(name, rows, cols)
        body = sym - value if equation is None else _expression(equation(sym), f"define({name!r}): the equation")
        if body.numel() != sym.numel():
            raise ModelError(f"define({name!r}): the equation has {body.numel()} entries for {sym.numel()} defined "
                             "ones; it must give one equation per entry")
        check_depends(body, ca.vertcat(allowed, ca.vec(sym)), f"define({name!r}): the equation", DEFINITION_USES)
        self.definitions.append(Definition(name, sym, value, ca.vec(body)))
        self.revision += 1
        return sym

    def linear_map(self, matrix: Any, name: str = "A") -> LinearMap:
        """A numeric matrix (numpy, scipy.sparse) or scipy LinearOperator kept as data: `T @ expr` is a symbol for the
        product, to use in the lower level, with expr an expression of the upper variables (data the attacker moves)
        or a linear one of the lower variables (a least squares min ||T @ y - d(x)||^2); the engine computes products
        numerically instead of expanding the matrix into the expressions."""
        if not isinstance(name, str) or not name.isidentifier():
            raise ModelError(f"linear_map: name {name!r} must be a Python identifier")
        return LinearMap(self, matrix, name)

    def _image(self, name: str, operator: Operator, arg: ca.SX) -> ca.SX:
        """Register the product operator @ arg (LinearMap.__matmul__) and return its symbol."""
        while self._taken(name):
            name += "_"
        lower = [ca.vec(v.sym) for v in self.lower_variables]
        level = "lower" if lower and ca.depends_on(arg, ca.vertcat(*lower)) else "upper"
        allowed = ca.vertcat(*[ca.vec(v.sym) for v in self.variables if v.level == level], self.parameters.sym)
        check_depends(arg, allowed, f"{name} = linear map @ expression: the expression",
                      "are not variables or parameters of this problem, or mix upper and lower variables: a linear "
                      "map applies to an expression of the upper variables (data the leader moves) or to a linear "
                      "one of the lower variables (a learner's regressor)")
        sym = ca.SX.sym(name, operator.shape[0], int(arg.size2()))
        self.images.append(Image(name, sym, operator, arg, level))
        self.revision += 1
        return sym

    def definition_values(self) -> tuple[ca.SX, ca.SX]:
        """The definitions' symbols stacked, and their values as expressions of upper variables and parameters only."""
        syms: list[ca.SX] = []
        values: list[ca.SX] = []
        for d in self.definitions:  # a value may use earlier definitions, already explicit
            values.append(ca.substitute(ca.vec(d.value), ca.vertcat(*syms), ca.vertcat(*values)) if syms
                          else ca.vec(d.value))
            syms.append(ca.vec(d.sym))
        return (ca.vertcat(*syms), ca.vertcat(*values)) if syms else (ca.SX(0, 1), ca.SX(0, 1))

    def explicit(self, expr: Any) -> ca.SX:
        """expr with every definition replaced by its value (an expression of the declared variables and parameters)."""
        z, value = self.definition_values()
        return ca.substitute(ca.SX(expr), z, value) if self.definitions else ca.SX(expr)

    def suggest_start(self, **values: Any) -> None:
        """Add an upper-level start for the multistart methods (tried before random ones): values by upper-variable
        name; unnamed upper variables take their declared start."""
        upper = {v.name: v for v in self.upper_variables}
        if not values:
            raise ModelError("suggest_start needs values for at least one upper variable, e.g. suggest_start(x=1.0)")
        start = {}
        for name, value in values.items():
            if name not in upper:
                raise ModelError(f"suggest_start: {name!r} is not an upper variable; upper variables: "
                                 f"{', '.join(upper) or 'none'}")
            arr = _bound_array(value, upper[name].size, f"suggested start of {name!r}")
            if not np.all(np.isfinite(arr)):
                raise ModelError(f"suggested start of {name!r} contains inf; give finite values")
            start[name] = arr
        self.suggested_starts.append(start)

    @property
    def starts(self) -> None:
        """Renamed: the starts given by suggest_start are suggested_starts (`starts` is the methods' count option)."""
        raise AttributeError(renamed("BilevelProblem.starts", "suggested_starts (the starts given by suggest_start; the "
                                     "option starts is the number of multistart starts)"))

    def upper_layout(self) -> dict[str, slice]:
        """Where each upper variable sits in the flat upper vector x (declaration order, column-major)."""
        layout, start = {}, 0
        for var in self.upper_variables:
            layout[var.name] = slice(start, start + var.size)
            start += var.size
        return layout

    @property
    def upper_variables(self) -> list[Variable]:
        return [v for v in self.variables if v.level == "upper"]

    @property
    def lower_variables(self) -> list[Variable]:
        return [v for v in self.variables if v.level == "lower"]

    # -- objectives ------------------------------------------------------------------------------
    def _objective(self, expr: Any, sense: Sense, where: str, assume_convex: bool = False) -> Objective:
        if not isinstance(expr, (ca.SX, ca.MX, ca.DM)):
            refuse_complex(expr, where)
        try:
            expr = ca.SX(expr) if not isinstance(expr, ca.SX) else expr
        except (NotImplementedError, TypeError, RuntimeError):
            raise ModelError(f"{where}: expected a CasADi expression of the declared variables, "
                             f"got {type(expr).__name__}") from None
        if expr.numel() != 1:
            raise ModelError(f"{where}: the objective must be scalar, got shape {expr.shape}")
        return Objective(expr, sense, bool(assume_convex))

    def minimize_upper(self, expr: Any) -> None:
        """Set the upper-level objective F(x, y) to minimize."""
        self.upper_objective = self._objective(expr, "min", "minimize_upper")
        self.revision += 1

    def maximize_upper(self, expr: Any) -> None:
        """Set the upper-level objective F(x, y) to maximize."""
        self.upper_objective = self._objective(expr, "max", "maximize_upper")
        self.revision += 1

    def maximize_spectral_radius(self, matrix: Any) -> None:
        """Set the upper objective to rho(M) = max |eig(M)| of a square matrix expression M(x, y), evaluated and
        differentiated exactly (eigenvectors); methods hypergradient and differential-evolution solve it."""
        matrix = _expression(matrix, "maximize_spectral_radius", "a square CasADi matrix expression")
        if matrix.size1() != matrix.size2() or matrix.numel() == 0:
            raise ModelError(f"maximize_spectral_radius: the matrix must be square, got shape {matrix.shape}")
        self.maximize_matrix_function(matrix, rho_and_gradient)

    def maximize_matrix_function(self, matrix: Any, function: MatrixFunction) -> None:
        """Set the upper objective to function(M) of a matrix expression M(x, y): a numeric function returning its
        value and its gradient in M (e.g. an implicit map such as a Riccati solution, differentiated by the user).
        Methods hypergradient and differential-evolution solve it; the KKT methods refuse it."""
        matrix = _expression(matrix, "maximize_matrix_function", "a CasADi matrix expression")
        if matrix.numel() == 0 or not callable(function):
            raise ModelError("maximize_matrix_function: give a nonempty matrix expression and a callable M -> (value, "
                             f"gradient), got shape {matrix.shape} and {type(function).__name__}")
        self.upper_objective = Objective(ca.SX(np.nan), "max", matrix=matrix, function=function)
        self.revision += 1

    def minimize_lower(self, expr: Any, assume_convex: bool = False) -> None:
        """Set the lower-level objective f(x, y) to minimize (convex in y on the declared bounds of y).

        Convexity is probed at sample points inside the bounds; assume_convex=True skips the probe (for
        a function convex on a domain set by constraints rather than bounds). The certificate still
        re-solves the lower level independently (multistart for a nonlinear one) and fails if a better
        lower-level point exists.
        """
        self._check_lower_open("minimize_lower")
        self.lower_objective = self._objective(expr, "min", "minimize_lower", assume_convex)
        self.revision += 1

    def maximize_lower(self, expr: Any, assume_convex: bool = False) -> None:
        """Set the lower-level objective f(x, y) to maximize (concave in y); see minimize_lower."""
        self._check_lower_open("maximize_lower")
        self.lower_objective = self._objective(expr, "max", "maximize_lower", assume_convex)
        self.revision += 1

    # -- constraints ---------------------------------------------------------------------------
    def upper_constraint(self, comparison: Any, name: str | None = None) -> None:
        """Add an upper-level constraint `G(x, y) <= 0` / `== 0` (any comparison of expressions)."""
        body, kind = split_comparison(comparison, "upper_constraint")
        name = self._constraint_name(name, f"G{len(self.upper_constraints)}", "upper_constraint")
        self.upper_constraints.append(Constraint(name, body, kind))
        self.revision += 1

    def lower_constraint(self, comparison: Any, name: str | None = None) -> None:
        """Add a lower-level constraint `g(x, y) <= 0` (convex in y) or `h(x, y) == 0` (affine in y)."""
        self._check_lower_open("lower_constraint")
        body, kind = split_comparison(comparison, "lower_constraint")
        name = self._constraint_name(name, f"g{len(self.lower_constraints)}", "lower_constraint")
        self.lower_constraints.append(Constraint(name, body, kind))
        self.revision += 1

    def lower_psd_constraint(self, matrix: Any, name: str | None = None) -> None:
        """Add a lower-level linear matrix inequality `M(x, y) >= 0` (M symmetric, affine in y)."""
        self._check_lower_open("lower_psd_constraint")
        name = self._constraint_name(name, f"M{len(self.lower_psd_constraints)}", "lower_psd_constraint")
        matrix = _expression(matrix, "lower_psd_constraint", "a square CasADi matrix")
        if matrix.numel() == 0:
            raise ModelError("lower_psd_constraint: the matrix is empty; an LMI needs a square matrix of size >= 1")
        if matrix.size1() != matrix.size2():
            raise ModelError(f"lower_psd_constraint: matrix must be square, got shape {matrix.shape}")
        asym = ca.simplify(matrix - matrix.T)
        if not asym.is_zero():
            syms = self._all_syms()
            probe = ca.Function("asym", [syms], [asym])(np.random.default_rng(0).standard_normal(syms.numel()))
            if float(ca.norm_inf(probe)) > 1e-12:
                raise ModelError("lower_psd_constraint: matrix is not symmetric; pass (M + M.T) / 2 if that is meant")
        self.lower_psd_constraints.append(PSDConstraint(name, matrix))
        self.revision += 1

    def _constraint_name(self, name: str | None, default: str, where: str) -> str:
        """A constraint's name: the given one, checked unique among all constraints and LMIs (results report their
        multipliers by name), else `default` (primed until free); names ending in .lb/.ub are the bounds'."""
        taken = {c.name: kind for kind, items in (("upper constraint", self.upper_constraints),
                                                  ("lower constraint", self.lower_constraints),
                                                  ("LMI", self.lower_psd_constraints)) for c in items}
        if name is None:
            while default in taken:
                default += "_"
            return default
        if not isinstance(name, str) or not name:
            raise ModelError(f"{where}: name {name!r} must be a non-empty string")
        if name in taken:
            raise ModelError(f"{where}: name {name!r} is already used by the {taken[name]} {name!r}; constraint names "
                             "must be unique (multipliers are reported by name): choose another name")
        if name.endswith((".lb", ".ub")):
            raise ModelError(f"{where}: name {name!r} ends in {name[-3:]!r}, which names the multipliers of a "
                             f"variable's bounds (e.g. 'y.lb', 'y.ub'); choose another name")
        return name

    def lower_cvxpy(self, learner: "cp.Problem", parameters: dict[Any, Any] | None = None,
                    name: str = "cvxpy") -> "CvxpyLower":
        """Declare the whole lower level as a cvxpy Problem (DCP, and DPP in its Parameters).

        parameters maps cvxpy Parameters to CasADi expressions of upper variables (any expression: the lower
        level stays conic in its own variables); unbound Parameters keep their current value. Returns `ll`,
        with `ll[v]` the cvxpy Variable v as a CasADi expression for the upper level. See docs/cvxpy.md.
        """
        if self.lower_variables or self.lower_objective is not None:
            raise ModelError(f"{self.name}: lower_cvxpy declares the whole lower level, but lower variables or a "
                             "lower objective are already declared; use one or the other")
        from .frontends.cvxpy_lower import CvxpyLower

        lower = CvxpyLower(self, learner, dict(parameters or {}), name)
        self.lower_reference = lower.reference
        return lower

    def lower_qp(self, y: Any, *, C: Any = None, d: Any = None, P: Any = None, q: Any = None, A: Any = None,
                 b: Any = None, E: Any = None, e: Any = None) -> None:
        """Declare the whole lower level as min_y 1/2 ||C y - d||^2 + 1/2 y'Py + q'y s.t. A y <= b, E y = e.

        y is one declared lower variable (its bounds are kept); P, A, E are numeric matrices (numpy or scipy.sparse),
        d, q, b, e numbers or CasADi expressions of upper variables and parameters. A numeric C is kept as a matrix
        (nothing of size C x y is built symbolically: least squares on 2,000 features stay fast); C may also be an
        expression of the upper variables (a regressor the leader moves, e.g. built with linear_map products).
        """
        from .lower.matrix import as_dense

        var = next((v for v in self.lower_variables if v.sym.shape == ca.SX(y).shape
                    and ca.is_equal(v.sym, ca.SX(y))), None) if isinstance(y, ca.SX) else None
        if var is None or var.matrix is not None or var.shape[1] != 1:
            raise ModelError("lower_qp: y must be a vector lower variable declared on this problem "
                             "(y = p.lower_variable('y', n))")
        if len(self.lower_variables) > 1 or self.lower_objective is not None or self.lower_constraints \
                or self.lower_psd_constraints or self.lower_matrices is not None:
            raise ModelError(f"lower_qp: it declares the whole lower level of {self.name!r} (objective and "
                             "constraints) over one lower variable; declare nothing else on the lower level")
        n = var.size
        if isinstance(C, ca.SX) and not C.is_constant():  # a regressor the leader moves: declared as expressions
            self._lower_qp_expressions(var, _expression(C, "lower_qp: C"), d, P, q, A, b, E, e)
            return
        mats = {k: as_dense(m, n, k) for k, m in (("C", C), ("P", P), ("A", A), ("E", E))}
        if P is None:
            mats["P"] = np.zeros((n, n))
        elif mats["P"].shape != (n, n) or not np.allclose(mats["P"], mats["P"].T):
            raise ModelError(f"lower_qp: P must be a symmetric {n} x {n} matrix")
        elif np.linalg.eigvalsh(mats["P"]).min() < -1e-9 * max(1.0, float(np.abs(mats["P"]).max())):
            raise ModelError("lower_qp: P is not positive semidefinite, so the lower level is not convex")
        sizes = {"d": mats["C"].shape[0], "q": n, "b": mats["A"].shape[0], "e": mats["E"].shape[0]}
        vecs = {}
        for k, v in (("d", d), ("q", q), ("b", b), ("e", e)):
            expr = ca.SX.zeros(sizes[k]) if v is None else _expression(v, f"lower_qp: {k}")
            if expr.numel() != sizes[k] or min(expr.shape) > 1:
                raise ModelError(f"lower_qp: {k} has {expr.numel()} entries; it needs {sizes[k]} "
                                 f"(rows of {dict(d='C', q='y', b='A', e='E')[k]})")
            vecs[k] = ca.vec(expr)
        if mats["C"].shape[0] == 0 and P is None and q is None:
            raise ModelError("lower_qp: no objective; give C (least squares), P or q")
        self.lower_matrices = LowerQP(var, mats["C"], mats["P"], mats["A"], mats["E"], **vecs)
        self.revision += 1

    def _lower_qp_expressions(self, var: Variable, C: ca.SX, d: Any, P: Any, q: Any, A: Any, b: Any, E: Any,
                              e: Any) -> None:
        """lower_qp with C an expression of the upper variables (or of linear-map products): the same objective and
        constraints declared as expressions, so the lower level is classified (and kept in residual form when large)
        like any least squares or QP."""
        from .lower.matrix import as_dense

        y, n = var.sym, var.size
        if C.size2() != n:
            raise ModelError(f"lower_qp: C has {C.size2()} columns; it needs {n} (one per lower variable)")
        rows = {"d": C.size1(), "q": n}
        vec = {}
        for k, v in (("d", d), ("q", q)):
            vec[k] = ca.SX.zeros(rows[k]) if v is None else ca.vec(_expression(v, f"lower_qp: {k}"))
            if vec[k].numel() != rows[k]:
                raise ModelError(f"lower_qp: {k} has {vec[k].numel()} entries; it needs {rows[k]}")
        objective = 0.5 * ca.sumsqr(ca.mtimes(C, y) - vec["d"]) + ca.dot(vec["q"], y)
        if P is not None:
            objective += 0.5 * ca.mtimes([y.T, ca.DM(as_dense(P, n, "P")), y])
        self.minimize_lower(objective)
        for name, M, rhs, kind in (("A", A, b, "<="), ("E", E, e, "==")):
            if M is None:
                continue
            lhs = ca.mtimes(ca.DM(as_dense(M, n, name)), y)
            rhs = ca.SX.zeros(lhs.numel()) if rhs is None else ca.vec(_expression(rhs, f"lower_qp: {name.lower()}"))
            self.lower_constraint(lhs <= rhs if kind == "<=" else lhs == rhs, name=name)

    def _check_lower_open(self, where: str) -> None:
        if self.lower_matrices is not None:
            raise ModelError(f"{where}: the lower level of {self.name!r} is declared by lower_qp, complete as "
                             "declared; put the term or constraint into its matrices instead")
        if self.lower_reference is not None:
            raise ModelError(f"{where}: the lower level of {self.name!r} is a cvxpy problem (lower_cvxpy), complete as "
                             "declared; add the variable, objective or constraint to the cvxpy problem instead")

    def _all_syms(self) -> ca.SX:
        return ca.vertcat(*[ca.vec(v.sym) for v in self.variables], *[ca.vec(d.sym) for d in self.definitions],
                          *[ca.vec(i.sym) for i in self.images], self.parameters.sym)

    def __getstate__(self) -> dict[str, Any]:  # the cached preparation (compiled functions) is not pickled
        return {k: v for k, v in self.__dict__.items() if k != "_prepared"}

    # -- solving ---------------------------------------------------------------------------------
    def solve(self, method: Any = "auto", **options: Any) -> "BilevelResult":
        """Solve with a method chosen by structure ("auto", bilevel.solvers.registry.choose_method), a registered
        method (bilevel.METHODS) or a callable(prepared, **options) -> MethodRun. The registered methods:

        - "ipopt": IPOPT on the KKT reformulation (an MPCC), multistart, polished on the active branch;
        - "relaxation": the same MPCC along a relaxation path t -> 0 (Scholtes, Kanzow-Schwartz), warm started;
        - "hypergradient": projected descent on F(x, y*(x)), the lower level re-solved exactly at every step;
        - "block-exact": hypergradient that optimizes a ball-constrained block globally at every step;
        - "global": a proven global optimum (bounds and gap) for LP and convex-QP lower levels;
        - "differential-evolution": a search of the boxed upper level on the same implicit map, then descent;
        - "reduced": IPOPT over x alone on F(x, y*(x)), every upper constraint kept (a unique lower solution).

        Options are the method's keyword arguments: bilevel.show_options(method) (or help() on its function,
        bilevel.METHODS[method]) lists them with their defaults, an option left None taking the registry's value
        (bilevel.defaults, docs/options.md); a misspelt one raises UnknownOption naming the accepted ones."""
        from .solvers.registry import solve

        return solve(self, method=method, **options)

    def __repr__(self) -> str:
        nx = sum(v.size for v in self.upper_variables)
        ny = sum(v.size for v in self.lower_variables)
        return (f"BilevelProblem({self.name!r}: {nx} upper, {ny} lower variables, "
                f"{len(self.upper_constraints)} upper / {len(self.lower_constraints)} lower constraints, "
                f"{len(self.lower_psd_constraints)} LMIs)")
