"""The lower level in canonical form, min_y f(x, y) s.t. g <= 0, h = 0, M_k >= 0, and its KKT system."""

from __future__ import annotations

from abc import ABC, abstractmethod
from dataclasses import dataclass, field
from functools import cached_property
from typing import Callable, ClassVar, NamedTuple

import casadi as ca
import numpy as np

from ..errors import InvalidData
from ..parameters import CompiledFunction, ParameterSet, scalar
from ..vech import symmetric_from_vech
from .convexity import ConvexityProbe


@dataclass
class LowerSolution:
    """A lower-level solution at a fixed upper point, with multipliers in our sign convention.

    Convention: L = f + lam' g + mu' h - sum_k <Z_k, M_k>, lam >= 0, Z_k >= 0.
    """

    y: np.ndarray
    objective: float
    lam: np.ndarray
    mu: np.ndarray
    Z: list[np.ndarray] = field(default_factory=list)
    status: str = "optimal"
    solver: str = ""


class KKTValues(NamedTuple):
    """The implicit-derivative system of a lower level without LMIs at a solution: S the stationarity residual
    and g, h the constraints (column vectors); dS/dy, J_g, J_h (matrices, rows by constraint)."""

    stationarity: np.ndarray
    g: np.ndarray
    h: np.ndarray
    hessian: np.ndarray
    jac_g: np.ndarray
    jac_h: np.ndarray
    factor: np.ndarray | None = None
    """The Hessian's Cholesky factor (bilevel.lower.least_squares.hessian_factor) where the solve has it, else None."""

    @classmethod
    def unconstrained(cls, hessian: np.ndarray, factor: np.ndarray | None = None) -> "KKTValues":
        """At the exact minimizer of an unconstrained lower level with this Hessian (S = 0, no g or h) and, if known,
        its Cholesky factor."""
        n = hessian.shape[0]
        return cls(np.zeros((n, 1)), np.zeros((0, 1)), np.zeros((0, 1)), hessian, np.zeros((0, n)), np.zeros((0, n)),
                   factor)


@dataclass(frozen=True)
class KKTSystem:
    """Symbolic KKT conditions of the lower level: multiplier symbols and the stationarity residual."""

    lam: ca.SX
    mu: ca.SX
    Z: tuple[ca.SX, ...]
    Z_vech: tuple[ca.SX, ...]
    stationarity: ca.SX


class LowerLevel(ABC):
    """min_y f(x, y) s.t. g(x, y) <= 0, h(x, y) = 0, M_k(x, y) >= 0 (PSD), convex in y for fixed x: what every
    lower-level kind gives the methods (values, derivatives, its KKT system, an independent solve).

    Two families: ExpressionLower (f, g, h, M_k as CasADi expressions) and MatrixLower (a QP given by matrices).
    """

    kind: ClassVar[str] = "nlp"
    params: ParameterSet
    psd: list
    g_names: list[str]
    h_names: list[str]
    psd_names: list[str]
    convexity_probe: ConvexityProbe | None = None
    """The declaration's sampled convexity check (set by build_lower; None where nothing is sampled)."""

    @property
    def closed_form(self) -> bool:
        """True for a least-squares lower level: unconstrained and strictly convex quadratic in y, so y*(x) is unique,
        smooth in x and solved in closed form (no active set, nothing to polish)."""
        return self.kind == "least-squares"

    @property
    def nonlinear(self) -> bool:
        """True for a convex NLP lower level: its solves are local (IPOPT), evidence rather than proof."""
        return self.kind == "nlp"

    @property
    def affine_kkt(self) -> bool:
        """True where the KKT system is affine in y and the multipliers with scalar complementarity only (LP, QP,
        least squares): the class of method global's linear MPCC."""
        return self.kind in ("lp", "qp", "least-squares")

    @property
    def dual_bounded(self) -> bool:
        """True for LP, QP and SDP lower levels: constrained, with a Lagrangian quadratic in y, so multipliers bound
        f*(x) from below by weak duality (the certificate's check of a conic re-solve that stopped short)."""
        return self.kind in ("lp", "qp", "sdp")

    def nonunique_at(self, x: np.ndarray) -> str | None:
        """Why the lower solution at upper point x may not be unique, or None where it is (a least-squares lower level;
        a QP with a positive definite Hessian at x)."""
        return None if self.closed_form else f"a lower level of class {self.kind!r} (its solution need not be unique)"

    @property
    def inner_kind(self) -> "LowerLevel":
        """The kind whose functions take lift_point(x) as their upper point: this one, or for a lower level with
        linear maps (ImageLower) the kind over [x; z]."""
        return self

    def lift_point(self, x: np.ndarray) -> np.ndarray:
        """The upper point inner_kind is called at: x itself, or [x; z(x)] for a lower level with linear maps."""
        return x

    def pullback(self, x: np.ndarray, g: np.ndarray) -> np.ndarray:
        """A gradient over inner_kind's upper point pulled back to x: g itself without linear maps."""
        return g

    @property
    def linear_map_arguments(self) -> list[ca.SX]:
        """The expressions of x that linear maps are applied to ([] without linear maps)."""
        return []

    @property
    def rows_solver(self) -> "Callable[[np.ndarray], list[np.ndarray | None]] | None":
        """X -> the lower solution y at each row of X (None where it cannot be solved) where the kind solves many
        points at once faster than one by one, else None."""
        return None

    def moving_hessian(self) -> tuple[Callable[[np.ndarray], np.ndarray],
                                      Callable[[np.ndarray, np.ndarray], np.ndarray]] | None:
        """(x -> P(x), (x, v) -> d(v'P(x)v)/dx) for a least-squares lower level whose Hessian P moves with x (up to a
        positive factor; the conditioning start's parts), else None."""
        return None

    def check_convexity(self) -> None:
        """Re-run the declaration's convexity check at the parameters' current values (after set_value)."""
        if self.convexity_probe is not None:
            self.convexity_probe.run()

    x: ca.SX
    """The upper variables' symbols (every kind's functions take x as their first input)."""
    y: ca.SX
    """The lower variables' symbols."""

    @cached_property
    def n_x(self) -> int:
        """Number of upper variables (read at every call of the methods: kept, not recounted)."""
        return int(self.x.numel())

    @cached_property
    def n_y(self) -> int:
        """Number of lower variables."""
        return int(self.y.numel())

    @property
    def n_g(self) -> int:
        return len(self.g_names)

    @property
    def n_h(self) -> int:
        return len(self.h_names)

    @property
    @abstractmethod
    def fixed(self) -> bool:
        """True when the lower level does not depend on x: y*(x) is then one point, solved once."""

    def check_point(self, x: np.ndarray) -> np.ndarray:
        """Validate an upper point (shape, finiteness) and return it as a float vector."""
        x = np.asarray(x, dtype=float).ravel()
        if x.shape != (self.n_x,):
            raise InvalidData(f"upper point has {x.size} entries, the problem has {self.n_x} upper variables")
        if not np.all(np.isfinite(x)):
            raise InvalidData("upper point contains NaN or inf")
        return x

    @abstractmethod
    def evaluate(self, x: np.ndarray, y: np.ndarray) -> tuple[float, np.ndarray, np.ndarray, list[np.ndarray]]:
        """f, g, h and the LMI matrices at (x, y)."""

    @abstractmethod
    def derivatives(self, x: np.ndarray, y: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, list[np.ndarray]]:
        """grad_y f, J_g, J_h (rows by constraint) and d vec(M_k) / dy at (x, y)."""

    @abstractmethod
    def hessian(self, x: np.ndarray, y: np.ndarray) -> np.ndarray:
        """Hessian of f in y at (x, y)."""

    def curvatures(self, x: np.ndarray, y: np.ndarray) -> list[tuple[str, np.ndarray]]:
        """The Hessians in y that must be PSD for the lower level to be convex at (x, y), with what they are of."""
        return [("the lower objective", self.hessian(x, y))]

    def curvature_functions(self) -> list[CompiledFunction]:
        """(x, y) -> the Hessians of `curvatures`, as compiled SX functions (for interval bounds); [] when the
        kind has none (its Hessian is then numeric data)."""
        return []

    def stationarity(self, x: np.ndarray, y: np.ndarray, lam: np.ndarray, mu: np.ndarray,
                     Z: list[np.ndarray]) -> tuple[np.ndarray, np.ndarray]:
        """The Lagrangian gradient in y at (x, y, multipliers), and grad_y f (for scaling)."""
        grad_f, jg, jh, jpsd = self.derivatives(x, y)
        res = grad_f + jg.T @ lam + jh.T @ mu
        for jac, z in zip(jpsd, Z):
            res = res - jac.T @ np.asarray(z).reshape(-1, order="F")
        return res, grad_f

    @abstractmethod
    def kkt_values(self, x: np.ndarray, sol: LowerSolution) -> KKTValues:
        """The implicit-derivative system (S, g, h, dS/dy, J_g, J_h) at a solution, for a lower level without LMIs."""

    @abstractmethod
    def kkt_x_adjoint(self, x: np.ndarray, sol: LowerSolution, v_s: np.ndarray, v_g: np.ndarray,
                      v_h: np.ndarray) -> np.ndarray:
        """R' v, R the x-derivative of (S, g, h) at a solution (one reverse sweep, R is never formed)."""

    def kkt_x_adjoint_columns(self, x: np.ndarray, sol: LowerSolution, V_s: np.ndarray, V_g: np.ndarray,
                              V_h: np.ndarray) -> np.ndarray:
        """R' [v_1 .. v_k] for the columns v_j of (V_s; V_g; V_h), n_x x k: one kkt_x_adjoint per column unless a kind
        has a batched product."""
        return np.column_stack([self.kkt_x_adjoint(x, sol, V_s[:, j], V_g[:, j], V_h[:, j])
                                for j in range(V_s.shape[1])]) if V_s.shape[1] else np.zeros((self.n_x, 0))

    def kkt_solve(self, x: np.ndarray, K: np.ndarray, rhs: np.ndarray) -> tuple[np.ndarray, int]:
        """Z with K' Z = rhs for the implicit-derivative system K at x, and the rank used: the least-squares
        (minimum-norm) solution, since K is singular where y* is not differentiable."""
        Z, _, rank, _ = np.linalg.lstsq(K.T, rhs, rcond=None)
        return Z, int(rank)

    @abstractmethod
    def solve(self, x: np.ndarray) -> LowerSolution:
        """Solve the lower level at upper point x, independently of the reduction (raises on failure)."""

    def reference_solve(self, x: np.ndarray) -> LowerSolution:
        """The certificate's independent re-solve at x (by default the kind's own solve)."""
        return self.solve(x)

    @abstractmethod
    def symbolic(self) -> "ExpressionLower":
        """The lower level as CasADi expressions, for the single-level (KKT) reduction."""


@dataclass
class ExpressionLower(LowerLevel):
    """A lower level given by CasADi expressions f, g, h, M_k of (x, y, parameters).

    Subclasses state their kind and solve themselves independently of the single-level reduction.
    """

    x: ca.SX
    y: ca.SX
    f: ca.SX
    g: ca.SX
    h: ca.SX
    psd: list[ca.SX]
    g_names: list[str]
    h_names: list[str]
    psd_names: list[str]
    hess_f: ca.SX | None = field(default=None, repr=False)
    """d^2 f / dy^2, symbolic; computed here unless the classification already did (one AD pass on f)."""
    params: ParameterSet = field(default_factory=ParameterSet, repr=False)
    """The problem's parameters (data symbols in f, g, h, M_k): functions built here read their current values."""

    def __post_init__(self) -> None:
        if self.hess_f is None:
            self.hess_f = ca.hessian(self.f, self.y)[0]
        self._eval = self.params.function("lower_eval", [self.x, self.y], [self.f, self.g, self.h, *self.psd])
        self._hess = self.params.function("lower_hess", [self.x, self.y], [self.hess_f])

    @cached_property
    def _derivs(self) -> CompiledFunction:
        """(x, y) -> grad_y f, J_g, J_h, built on first use."""
        return self.params.function("lower_derivs", [self.x, self.y], [ca.gradient(self.f, self.y),
                                    ca.jacobian(self.g, self.y), ca.jacobian(self.h, self.y)])

    def lmi_jacobians(self, x: np.ndarray) -> list[np.ndarray]:
        """d vec(M_k)/dy at x for every LMI (constant in y: LMIs are affine in y): none here; SemidefiniteLower, the
        kind with LMIs, reads them from its LMI coefficients."""
        return []

    @cached_property
    def fixed(self) -> bool:
        """True when f, g, h and the LMIs do not depend on x: y*(x) is then one point, solved once."""
        return not ca.depends_on(ca.vertcat(self.f, self.g, self.h, *[ca.vec(m) for m in self.psd]), self.x)

    def kkt(self) -> KKTSystem:
        """Multiplier symbols and stationarity grad_y f + J_g' lam + J_h' mu - grad_y sum <Z_k, M_k>."""
        lam = ca.SX.sym("lam", self.g.numel())
        mu = ca.SX.sym("mu", self.h.numel())
        lagrangian = self.f + ca.dot(lam, self.g) + ca.dot(mu, self.h)
        zs, zv = [], []
        for k, m in enumerate(self.psd):
            z, v = symmetric_from_vech(f"Z{k}", m.size1())
            zs.append(z)
            zv.append(v)
            lagrangian -= ca.trace(ca.mtimes(z, m))
        return KKTSystem(lam, mu, tuple(zs), tuple(zv), ca.gradient(lagrangian, self.y))

    def evaluate(self, x: np.ndarray, y: np.ndarray) -> tuple[float, np.ndarray, np.ndarray, list[np.ndarray]]:
        """f, g, h and the LMI matrices at (x, y)."""
        out = self._eval(x, y)
        return (scalar(out[0]), np.asarray(out[1]).ravel(), np.asarray(out[2]).ravel(),
                [np.asarray(m) for m in out[3:]])

    def derivatives(self, x: np.ndarray, y: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, list[np.ndarray]]:
        """grad_y f, J_g, J_h (rows by constraint) and d vec(M_k) / dy at (x, y)."""
        out = self._derivs(x, y)
        return (np.asarray(out[0]).ravel(), np.asarray(out[1]).reshape(-1, self.n_y),
                np.asarray(out[2]).reshape(-1, self.n_y), self.lmi_jacobians(x))

    def hessian(self, x: np.ndarray, y: np.ndarray) -> np.ndarray:
        """Hessian of f in y at (x, y)."""
        return np.asarray(self._hess(x, y))

    @cached_property
    def _curved_constraints(self) -> tuple[list[str], CompiledFunction | None]:
        """Names of the rows of g that are nonlinear in y, and (x, y) -> their Hessians in y (None if none)."""
        rows = [i for i in range(self.n_g) if ca.depends_on(ca.jacobian(self.g[i], self.y), self.y)]
        if not rows:
            return [], None
        hessians = [ca.hessian(self.g[i], self.y)[0] for i in rows]
        return [self.g_names[i] for i in rows], self.params.function("lower_hess_g", [self.x, self.y], hessians)

    def curvatures(self, x: np.ndarray, y: np.ndarray) -> list[tuple[str, np.ndarray]]:
        """The Hessians of f and of the rows of g nonlinear in y at (x, y)."""
        names, fun = self._curved_constraints
        out = [] if fun is None else fun(x, y)
        out = [out] if len(names) == 1 else list(out)
        return super().curvatures(x, y) + [(f"lower constraint {n!r}", np.asarray(h)) for n, h in zip(names, out)]

    def curvature_functions(self) -> list[CompiledFunction]:
        """The Hessian of f and, if any, those of the rows of g nonlinear in y."""
        fun = self._curved_constraints[1]
        return [self._hess] + ([] if fun is None else [fun])

    @cached_property
    def _kkt_functions(self) -> tuple:
        """The compiled KKT values and the adjoint R' v (built on first use)."""
        kkt = self.kkt()
        S, function = kkt.stationarity, self.params.function
        values = function("kkt", [self.x, self.y, kkt.lam, kkt.mu],
                          [S, self.g, self.h, ca.jacobian(S, self.y), ca.jacobian(self.g, self.y),
                           ca.jacobian(self.h, self.y)])
        v = [ca.SX.sym("v_S", self.n_y), ca.SX.sym("v_g", self.n_g), ca.SX.sym("v_h", self.n_h)]
        r_adj = sum((ca.jtimes(e, self.x, w, True) for e, w in zip((S, self.g, self.h), v) if e.numel()),
                    ca.SX.zeros(self.n_x))
        adjoint = function("kkt_x_adjoint", [self.x, self.y, kkt.lam, kkt.mu, *v], [r_adj])
        shapes = [(self.n_y, 1), (self.n_g, 1), (self.n_h, 1), (self.n_y, self.n_y), (self.n_g, self.n_y),
                  (self.n_h, self.n_y)]
        return values, adjoint, shapes

    def kkt_values(self, x: np.ndarray, sol: LowerSolution) -> KKTValues:
        values, _, shapes = self._kkt_functions
        return KKTValues(*(np.asarray(v, dtype=float).reshape(s, order="F")
                           for v, s in zip(values(x, sol.y, sol.lam, sol.mu), shapes)))

    def kkt_x_adjoint(self, x: np.ndarray, sol: LowerSolution, v_s: np.ndarray, v_g: np.ndarray,
                      v_h: np.ndarray) -> np.ndarray:
        return np.asarray(self._kkt_functions[1](x, sol.y, sol.lam, sol.mu, v_s, v_g, v_h)).ravel()

    def symbolic(self) -> "ExpressionLower":
        return self

    def moving_hessian(self) -> tuple[Callable[[np.ndarray], np.ndarray],
                                      Callable[[np.ndarray, np.ndarray], np.ndarray]] | None:
        """The Hessian d^2f/dy^2 at y = 0 (f is quadratic in y) and its adjoint, where least squares and moving with
        x."""
        if not self.closed_form:
            return None
        P = ca.substitute(self.hess_f, self.y, ca.DM.zeros(self.n_y))
        if not ca.depends_on(P, self.x):
            return None
        V = ca.SX.sym("V", self.n_y, self.n_y)
        hess_fun = self.params.function("conditioning_P", [self.x], [P])
        adj_fun = self.params.function("conditioning_adjoint", [self.x, V],
                                       [ca.jtimes(ca.vec(P), self.x, ca.vec(V), True)])
        return (lambda xt: np.asarray(hess_fun(xt), dtype=float),
                lambda xt, v: np.asarray(adj_fun(xt, np.outer(v, v)), dtype=float).ravel())
