"""A lower level written with products of linear maps (BilevelProblem.linear_map): the kind is built over the lifted
upper vector [x; z], z = [A_i arg_i(x)], and every call at x lifts x numerically and pulls x-derivatives back
through the maps' adjoints. Expressions stay the size of what they are written with; the matrices are applied by
BLAS (or the operator's code) only.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from functools import cached_property
from typing import Callable

import casadi as ca
import numpy as np

from ..errors import BilevelError, ModelError
from ..linear_maps import Images, Operator, affine_parts
from ..toeplitz import ToeplitzBank
from ..parameters import ParameterSet
from .base import ExpressionLower, KKTValues, LowerLevel, LowerSolution


class Lift:
    """x -> [x; z(x)] and the pull-back of [x; z]-gradients to x: g_x + J_arg(x)' A' g_z.

    Images of the same argument (a filter bank applied to one attacked signal) share it: the argument is evaluated
    and pulled back once, and their matrices are stacked into one (Operator.stacked), so the bank costs one product
    each way (one BLAS product, or one FFT convolution for filter matrices).
    """

    def __init__(self, x: ca.SX, images: Images, params: ParameterSet) -> None:
        self.images, self.n_x, self.n_z = images, int(x.numel()), images.size
        args: list[ca.SX] = []
        self._groups: list[list[int]] = []
        for k, img in enumerate(images.items):
            same = next((g for g, a in enumerate(args) if a.shape == img.arg.shape and ca.is_equal(a, img.arg, 3)),
                        None)
            if same is None:
                args.append(img.arg)
                self._groups.append([k])
            else:
                self._groups[same].append(k)
        self._stacked = [self._stack(group) for group in self._groups]
        flat = ca.vertcat(*[ca.vec(a) for a in args])
        v = ca.SX.sym("v", int(flat.numel()))
        self._args = params.function("image_args", [x], [flat])
        self._args_adjoint = params.function("image_args_adjoint", [x, v], [ca.jtimes(flat, x, v, True)])
        self._affine = affine_parts(flat, x, params.sym)
        """(J, b, J') where the arguments are J x + b: a sparse product each way instead of a sweep."""
        self._arg_shapes = [a.shape for a in args]
        self._cuts = np.cumsum([0] + [int(a.numel()) for a in args])
        self._zcuts = np.cumsum([0] + [int(i.sym.numel()) for i in images.items])
        self._item_shapes = [i.sym.shape for i in images.items]
        self._zindex = [self._z_entries(group) for group in self._groups]
        self._last: tuple[bytes, np.ndarray] | None = None
        self._point: tuple[tuple[bytes, int], np.ndarray] | None = None
        self._params = params

    def _stack(self, group: list[int]) -> Operator | ToeplitzBank | None:
        """The group's matrices stacked (one product for all: Operator.stacked), None unless there are several, of
        one stackable kind, and the shared argument is a single column."""
        items = [self.images.items[k] for k in group]
        if len(items) < 2 or any(i.arg.shape[1] != 1 for i in items):
            return None
        return Operator.stacked([i.operator for i in items])

    def _z_entries(self, group: list[int]) -> slice | np.ndarray:
        """The entries of z that hold the group's images, in order (a slice where they are consecutive)."""
        if all(self._zcuts[k + 1] == self._zcuts[b] for k, b in zip(group, group[1:])):
            return slice(int(self._zcuts[group[0]]), int(self._zcuts[group[-1] + 1]))
        return np.concatenate([np.arange(self._zcuts[k], self._zcuts[k + 1]) for k in group])

    def __call__(self, x: np.ndarray) -> np.ndarray:
        """[x; z(x)], read-only (the same array for repeated calls at a point); z is kept for the last arguments of the
        maps (a step that moves only entries the maps do not read, e.g. an exact block, costs no product)."""
        x = np.asarray(x, dtype=float).ravel()
        point = (x.tobytes(), self._params.revision)  # the arguments may read parameters too
        if self._point is not None and self._point[0] == point:
            return self._point[1]
        args = (np.asarray(self._args(x), dtype=float).ravel() if self._affine is None
                else self._affine[0] @ x + self._affine[1])
        key = args.tobytes()
        if self._last is None or self._last[0] != key:
            z = np.empty(self.n_z)
            for g, group in enumerate(self._groups):
                a = args[self._cuts[g]:self._cuts[g + 1]].reshape(self._arg_shapes[g], order="F")
                a = a if a.shape[1] > 1 else a[:, 0]
                if self._stacked[g] is not None:  # the images of one argument: one product
                    z[self._zindex[g]] = self._stacked[g].apply(a)
                    continue
                for k in group:
                    prod = self.images.items[k].operator.apply(a)
                    z[self._zcuts[k]:self._zcuts[k + 1]] = np.asarray(prod, dtype=float).reshape(-1, order="F")
            self._last = (key, z)
        lifted = np.concatenate([x, self._last[1]])
        lifted.flags.writeable = False
        self._point = (point, lifted)
        return lifted

    def rows(self, X: np.ndarray) -> np.ndarray:
        """[x; z(x)] for each row x of X, each map applied to the arguments of all rows in one product where they are
        single columns (one call of `self` per row otherwise)."""
        X = np.asarray(X, dtype=float)
        if self._affine is None or any(shape[1] > 1 for shape in self._arg_shapes):
            return np.array([self(x) for x in X])
        args = self._affine[0] @ X.T + self._affine[1][:, None]  # one argument column per row of X
        Z = np.empty((self.n_z, X.shape[0]))
        for g, group in enumerate(self._groups):
            a = args[self._cuts[g]:self._cuts[g + 1]]
            if self._stacked[g] is not None:
                Z[self._zindex[g]] = self._stacked[g].apply(a)
                continue
            for k in group:
                Z[self._zcuts[k]:self._zcuts[k + 1]] = self.images.items[k].operator.apply(a)
        return np.hstack([X, Z.T])

    def pullback(self, x: np.ndarray, g: np.ndarray) -> np.ndarray:
        """d/dx of <g, [x; z(x)]> for g over [x; z] (a vector, or columns of a matrix)."""
        g = np.asarray(g, dtype=float)
        cols = g.reshape(g.shape[0], -1)
        out = cols[:self.n_x].copy()
        for j in range(cols.shape[1]):
            gz = cols[self.n_x:, j]
            back = []
            for grp, group in enumerate(self._groups):
                if self._stacked[grp] is not None:
                    total = self._stacked[grp].adjoint(gz[self._zindex[grp]])
                else:
                    parts = [gz[self._zcuts[k]:self._zcuts[k + 1]].reshape(self._item_shapes[k], order="F")
                             for k in group]
                    total = sum(np.asarray(self.images.items[k].operator.adjoint(p if p.shape[1] > 1 else p[:, 0]),
                                           dtype=float).reshape(self._arg_shapes[grp], order="F")
                                for k, p in zip(group, parts))
                back.append(np.asarray(total, dtype=float).reshape(-1, order="F"))
            back = np.concatenate(back)
            out[:, j] += (np.asarray(self._args_adjoint(x, back), dtype=float).ravel() if self._affine is None
                          else self._affine[2] @ back)
        return out.reshape((self.n_x,) + g.shape[1:])

    def expanded(self) -> ca.SX:
        """z as expressions of x (the matrices written into the graph): for the KKT reformulation only."""
        return ca.densify(ca.vertcat(*[ca.vec(ca.mtimes(i.operator.casadi(f"the linear map of {i.name!r}"), i.arg))
                                       for i in self.images.items]))


@dataclass
class ImageLower(LowerLevel):
    """The lower level of a problem with linear-map products: `inner` is the kind over [x; z], called at lift(x)."""

    inner: LowerLevel
    lift: Lift
    x: ca.SX
    params: ParameterSet = field(default_factory=ParameterSet, repr=False)

    def __post_init__(self) -> None:
        if self.inner.psd:
            raise ModelError("a lower level with LMIs cannot use linear-map products yet; write the LMI's data as "
                             "expressions (ca.mtimes) or as cvxpy Parameters (lower_cvxpy)")
        self.kind = self.inner.kind
        self.psd, self.psd_names = [], []
        self.g_names, self.h_names = self.inner.g_names, self.inner.h_names
        self.convexity_probe = self.inner.convexity_probe

    @property
    def fixed(self) -> bool:
        return self.inner.fixed

    @property
    def inner_kind(self) -> LowerLevel:
        """The kind over [x; z], called at lift_point(x)."""
        return self.inner

    def lift_point(self, x: np.ndarray) -> np.ndarray:
        """[x; z(x)] (Lift.__call__)."""
        return self.lift(x)

    def pullback(self, x: np.ndarray, g: np.ndarray) -> np.ndarray:
        """d/dx of <g, [x; z(x)]> (Lift.pullback)."""
        return self.lift.pullback(x, g)

    @property
    def linear_map_arguments(self) -> list[ca.SX]:
        """The arguments of the declared linear maps, expressions of x."""
        return [i.arg for i in self.lift.images.items]

    @property
    def rows_solver(self) -> Callable[[np.ndarray], list[np.ndarray | None]]:
        """solve_rows: the maps applied to all rows at once."""
        return self.solve_rows

    def nonunique_at(self, x: np.ndarray) -> str | None:
        return None if self.closed_form else self.inner.nonunique_at(self.lift(x))

    def moving_hessian(self) -> tuple[Callable[[np.ndarray], np.ndarray],
                                      Callable[[np.ndarray, np.ndarray], np.ndarray]] | None:
        """The inner kind's, composed with the lift (the adjoint pulled back to x)."""
        parts = self.inner.moving_hessian()
        if parts is None:
            return None
        hessian, adjoint = parts
        lift = self.lift
        return lambda x: hessian(lift(x)), lambda x, v: lift.pullback(x, adjoint(lift(x), v))

    @property
    def y(self) -> ca.SX:
        return self.inner.y

    def evaluate(self, x: np.ndarray, y: np.ndarray) -> tuple[float, np.ndarray, np.ndarray, list[np.ndarray]]:
        return self.inner.evaluate(self.lift(x), y)

    def derivatives(self, x: np.ndarray, y: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, list[np.ndarray]]:
        return self.inner.derivatives(self.lift(x), y)

    def hessian(self, x: np.ndarray, y: np.ndarray) -> np.ndarray:
        return self.inner.hessian(self.lift(x), y)

    def curvatures(self, x: np.ndarray, y: np.ndarray) -> list[tuple[str, np.ndarray]]:
        return self.inner.curvatures(self.lift(x), y)

    def kkt_values(self, x: np.ndarray, sol: LowerSolution) -> KKTValues:
        return self.inner.kkt_values(self.lift(x), sol)

    def kkt_x_adjoint(self, x: np.ndarray, sol: LowerSolution, v_s: np.ndarray, v_g: np.ndarray,
                      v_h: np.ndarray) -> np.ndarray:
        return self.lift.pullback(x, self.inner.kkt_x_adjoint(self.lift(x), sol, v_s, v_g, v_h))

    def kkt_solve(self, x: np.ndarray, K: np.ndarray, rhs: np.ndarray) -> tuple[np.ndarray, int]:
        return self.inner.kkt_solve(self.lift(x), K, rhs)

    def solve(self, x: np.ndarray) -> LowerSolution:
        return self.inner.solve(self.lift(self.check_point(x)))

    def solve_rows(self, X: np.ndarray) -> list[np.ndarray | None]:
        """The lower solution y at each row of X, None where it cannot be solved (a LowerSolve for the local probe):
        the maps applied to all rows at once (Lift.rows), then `solve` at each lifted row."""
        out: list[np.ndarray | None] = []
        for lifted in self.lift.rows(np.asarray(X, dtype=float)):
            try:
                out.append(self.inner.solve(lifted).y)
            except BilevelError:
                out.append(None)
        return out

    def reference_solve(self, x: np.ndarray) -> LowerSolution:
        return self.inner.reference_solve(self.lift(self.check_point(x)))

    def symbolic(self) -> ExpressionLower:
        """The lower level in x with the matrices written into the expressions (the KKT reformulation's form: its
        size is that of the matrices)."""
        return self._symbolic

    @cached_property
    def _symbolic(self) -> ExpressionLower:
        inner = self.inner.symbolic()
        z = self.lift.images.sym
        value = self.lift.expanded()
        sub = lambda e: ca.substitute(e, z, value)  # noqa: E731
        return type(inner)(self.x, inner.y, sub(inner.f), sub(inner.g), sub(inner.h), [], inner.g_names,
                           inner.h_names, [], sub(inner.hess_f), self.params)
