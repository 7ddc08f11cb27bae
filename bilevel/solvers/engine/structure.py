"""Structure read from a declared problem, cost linear in its expression graph: budget balls among the upper
constraints (projected onto exactly instead of penalized) and the projections they make.

A row G_i(x) <= 0 of the upper constraints is a ball when it depends on one contiguous block x_S of upper
variables only, with a constant Hessian 2 a I (a > 0) on that block: G_i = a ||x_S - c||^2 - a r^2. Such rows
are what `sumsqr(v - c) <= r**2` declares; `norm_2(v - c) <= r` (sqrt(q) - r with r free of x) is read as its
square q - r^2 where r >= 0. `norm_inf(v - c) <= r` (a max of |v_i - c_i| over a contiguous block, each entry once
with coefficient +-1) is an l_inf ball: its projection is the box [c - r, c + r] on the block.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Callable

import casadi as ca
import numpy as np

from ...canonical import CanonicalBilevel
from ...parameters import scalar
from .projections import Blocks, Box, NormBall, Projection

_REL = 1e-12


@dataclass(frozen=True)
class Ball:
    """Upper constraint row `row` reads ||x[block] - center||_norm <= radius (norm 2 or inf)."""

    row: int
    block: slice
    center: np.ndarray
    radius: float
    norm: float = 2

    def sphere_point(self, rng: np.random.Generator) -> np.ndarray:
        """A random point on the ball's boundary (l2: uniform on the sphere; l_inf: one entry at +-radius)."""
        n = self.block.stop - self.block.start
        if self.norm == np.inf:
            z = rng.uniform(-1.0, 1.0, n)
            z[rng.integers(n)] = rng.choice((-1.0, 1.0))
            return self.center + self.radius * z
        z = rng.standard_normal(n)
        return self.center + z * (self.radius / max(float(np.linalg.norm(z)), 1e-300))


def depends(expr: ca.SX, x: ca.SX, order: int = 1) -> np.ndarray:
    """Which entries of x the expression depends on (order 2: appears nonlinearly), by sparsity propagation."""
    if not expr.numel() or not x.numel():
        return np.zeros(int(x.numel()), dtype=bool)
    return np.asarray(ca.which_depends(ca.vec(expr), x, order, False), dtype=bool)


def _contiguous(mask: np.ndarray) -> slice | None:
    idx = np.flatnonzero(mask)
    if idx.size == 0 or idx[-1] - idx[0] + 1 != idx.size:
        return None
    return slice(int(idx[0]), int(idx[-1]) + 1)


@dataclass(frozen=True)
class BallForm:
    """A row that may be a ball: symbolically, one contiguous block with a constant diagonal Hessian; whether it
    is, and its center and radius, are read from the parameter values (`ball`)."""

    row: int
    block: slice
    values: Callable  # x -> (diag of the Hessian, G_row, gradient on the block, radius of a norm row or 0), at x = 0

    def ball(self, n_x: int) -> Ball | None:
        """The ball at the current parameter values, or None if the row is not one there."""
        diag, value, grad, radius = (np.asarray(v, dtype=float).ravel() for v in self.values(np.zeros(n_x)))
        a = 0.5 * float(diag[0])
        if a <= 0 or np.max(np.abs(diag - diag[0])) > _REL * abs(diag[0]) or radius[0] < 0:
            return None
        center = -grad / (2 * a)
        r2 = float(center @ center) - scalar(value) / a
        return Ball(self.row, self.block, center, float(np.sqrt(r2))) if r2 >= 0 else None


def _ball_form(canon: CanonicalBilevel, row: int) -> BallForm | None:
    g, radius = canon.G[row], ca.SX(0)
    if ca.depends_on(g, canon.y):
        return None
    if g.is_op(ca.OP_SUB) and g.dep(0).is_op(ca.OP_SQRT) and not ca.depends_on(g.dep(1), canon.x):
        radius = g.dep(1)  # norm_2(v - c) <= r: sqrt(q) <= r is q <= r^2 where r >= 0 (else no point)
        g = g.dep(0).dep(0) - radius ** 2
    block = _contiguous(depends(g, canon.x))
    if block is None:
        return None
    xs = canon.x[block]
    hess = ca.hessian(g, xs)[0]
    if ca.depends_on(hess, canon.x):
        return None
    n = block.stop - block.start
    if hess.nnz() != n or not all(i == j for i, j in zip(*hess.sparsity().get_triplet())):
        return None
    return BallForm(row, block, canon.params.function("ball", [canon.x], [ca.diag(hess), g, ca.gradient(g, xs),
                                                                          radius]))


@dataclass(frozen=True)
class CubeForm:
    """A row max_i |s_i (x[block])_i - o_i| - r (s_i = +-1), an l_inf ball whose center and radius are read from the
    parameter values (`ball`)."""

    row: int
    block: slice
    values: Callable  # x -> (slopes, offsets, radius), at x = 0, entries in block order

    def ball(self, n_x: int) -> Ball | None:
        """The l_inf ball at the current parameter values, or None if the row is not one there."""
        slopes, offsets, radius = (np.asarray(v, dtype=float).ravel() for v in self.values(np.zeros(n_x)))
        if np.any(np.abs(np.abs(slopes) - 1.0) > _REL) or not radius[0] >= 0 or not np.isfinite(radius[0]):
            return None
        return Ball(self.row, self.block, -offsets / slopes, float(radius[0]), np.inf)


def _max_of_abs(expr: ca.SX) -> list[ca.SX] | None:
    """The arguments a_i of expr = fmax(..., |a_i|, ...) (a tree of fmax over fabs leaves and zeros), or None."""
    if expr.is_op(ca.OP_FMAX):
        left, right = _max_of_abs(expr.dep(0)), _max_of_abs(expr.dep(1))
        return None if left is None or right is None else left + right
    if expr.is_op(ca.OP_FABS):
        return [expr.dep(0)]
    return [] if expr.is_zero() else None


def _cube_form(canon: CanonicalBilevel, row: int) -> CubeForm | None:
    g = canon.G[row]
    if not g.is_op(ca.OP_SUB) or ca.depends_on(g, canon.y) or ca.depends_on(g.dep(1), canon.x):
        return None
    args = _max_of_abs(g.dep(0))
    if not args:
        return None
    owners = [np.flatnonzero(depends(a, canon.x)) for a in args]
    if any(o.size != 1 or depends(a, canon.x, 2).any() for o, a in zip(owners, args)):
        return None
    idx = np.array([int(o[0]) for o in owners])
    order = np.argsort(idx)
    block = _contiguous(np.isin(np.arange(int(canon.x.numel())), idx))
    if block is None or np.unique(idx).size != idx.size:
        return None
    args = [args[i] for i in order]
    slopes = ca.vertcat(*[ca.jacobian(a, canon.x[int(idx[i])]) for a, i in zip(args, order)])
    return CubeForm(row, block, canon.params.function("cube", [canon.x], [slopes, ca.vertcat(*args), g.dep(1)]))


def ball_forms(canon: CanonicalBilevel) -> list[BallForm | CubeForm]:
    """The upper constraint rows that can be balls, l2 or l_inf (the symbolic part of find_balls, independent of
    values)."""
    forms = [_ball_form(canon, row) or _cube_form(canon, row) for row in range(int(canon.G.numel()))]
    return [f for f in forms if f is not None]


def find_balls(canon: CanonicalBilevel, forms: list[BallForm | CubeForm] | None = None) -> list[Ball]:
    """The upper constraint rows that are l2 or l_inf balls on disjoint contiguous blocks of x (forms: ball_forms)."""
    balls: list[Ball] = []
    owned = np.zeros(int(canon.x.numel()), dtype=bool)
    for form in ball_forms(canon) if forms is None else forms:
        ball = form.ball(int(canon.x.numel()))
        if ball is not None and not owned[ball.block].any():
            owned[ball.block] = True
            balls.append(ball)
    return balls


def upper_projection(canon: CanonicalBilevel, balls: list[Ball]) -> Projection:
    """Projection onto the declared box intersected with the recognized balls (exact: blocks are disjoint)."""
    if not balls:
        return Box(canon.x_lb, canon.x_ub)
    blocks = [(b.block, NormBall(b.radius, b.norm, b.center)) for b in balls]
    return Blocks(blocks, int(canon.x.numel())).with_box(canon.x_lb, canon.x_ub)


def budget_scale(canon: CanonicalBilevel, balls: list[Ball]) -> np.ndarray:
    """Per-entry length scale of the upper variables: a ball's radius on its block, else 1."""
    scale = np.ones(int(canon.x.numel()))
    for b in balls:
        scale[b.block] = max(b.radius, 1e-300)
    return scale
