"""Structure read from a declared problem, cost linear in its expression graph: budget balls among the upper
constraints (projected onto exactly instead of penalized) and the projections they make.

A row G_i(x) <= 0 of the upper constraints is a ball when it depends on one contiguous block x_S of upper
variables only, with a constant Hessian 2 a I (a > 0) on that block: G_i = a ||x_S - c||^2 - a r^2. Such rows
are what `sumsqr(v - c) <= r**2` declares; `norm_2(v) <= r` is not recognized (write its square).
"""

from __future__ import annotations

from dataclasses import dataclass

import casadi as ca
import numpy as np

from ..canonical import CanonicalBilevel
from .projections import Blocks, Box, NormBall, Projection

_REL = 1e-12


@dataclass(frozen=True)
class Ball:
    """Upper constraint row `row` reads ||x[block] - center||_2 <= radius."""

    row: int
    block: slice
    center: np.ndarray
    radius: float

    def sphere_point(self, rng: np.random.Generator) -> np.ndarray:
        """A uniformly random point on the ball's boundary sphere."""
        z = rng.standard_normal(self.block.stop - self.block.start)
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


def _ball(canon: CanonicalBilevel, row: int) -> Ball | None:
    g = canon.G[row]
    if ca.depends_on(g, canon.y):
        return None
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
    diag = np.asarray(ca.evalf(canon.params.substitute(ca.diag(hess)))).ravel()
    a = 0.5 * float(diag[0])
    if a <= 0 or np.max(np.abs(diag - diag[0])) > _REL * abs(diag[0]):
        return None
    value, grad = canon.params.function("ball", [canon.x], [g, ca.gradient(g, xs)])(np.zeros(int(canon.x.numel())))
    center = -np.asarray(grad).ravel() / (2 * a)
    r2 = float(center @ center) - float(value) / a
    if r2 < 0:
        return None
    return Ball(row, block, center, float(np.sqrt(r2)))


def find_balls(canon: CanonicalBilevel) -> list[Ball]:
    """The upper constraint rows that are Euclidean balls on disjoint contiguous blocks of x."""
    balls: list[Ball] = []
    owned = np.zeros(int(canon.x.numel()), dtype=bool)
    for row in range(int(canon.G.numel())):
        ball = _ball(canon, row)
        if ball is not None and not owned[ball.block].any():
            owned[ball.block] = True
            balls.append(ball)
    return balls


def upper_projection(canon: CanonicalBilevel, balls: list[Ball]) -> Projection:
    """Projection onto the declared box intersected with the recognized balls (exact: blocks are disjoint)."""
    if not balls:
        return Box(canon.x_lb, canon.x_ub)
    blocks = [(b.block, NormBall(b.radius, 2, b.center)) for b in balls]
    return Blocks(blocks, int(canon.x.numel())).with_box(canon.x_lb, canon.x_ub)


def budget_scale(canon: CanonicalBilevel, balls: list[Ball]) -> np.ndarray:
    """Per-entry length scale of the upper variables: a ball's radius on its block, else 1."""
    scale = np.ones(int(canon.x.numel()))
    for b in balls:
        scale[b.block] = max(b.radius, 1e-300)
    return scale
