"""Random bilevel programs with a convex quadratically constrained lower level, optionally with a constraint row whose
coefficients depend on x (seeded), for tests of method="global" on convex-NLP lower levels.

min_x  h x + e'y + w x y_1   s.t.  0 <= x <= 1,
y in argmin_y  1/2 y'Py + (q + x r)'y   s.t.  |y - c|^2 <= rho^2,  (a + x b)'y <= (a + x b)'c + m,  -3 <= y <= 3.
P is positive definite, |c|_inf <= 1 and rho <= 1.5 keep the disc inside the box, and c satisfies both rows strictly
at every x (margins rho^2 and m > 0): a Slater point, so the lower level has a unique solution at every x.
"""

from __future__ import annotations

from dataclasses import dataclass

import casadi as ca
import numpy as np

from ..model import BilevelProblem


@dataclass(frozen=True)
class ConvexData:
    """The coefficients of one random instance (see the module docstring); a and b are None without the row."""

    h: float
    e: np.ndarray
    w: float
    P: np.ndarray
    q: np.ndarray
    r: np.ndarray
    c: np.ndarray
    rho: float
    a: np.ndarray | None
    b: np.ndarray | None
    m: float


def random_convex_data(rng: np.random.Generator, n_y: int, x_row: bool) -> ConvexData:
    """Standard normal e, q, r, a, b and P = L L' + I/2; c uniform in [-1, 1], rho in [0.5, 1.5], m in [0.3, 1]."""
    L = rng.normal(size=(n_y, n_y))
    return ConvexData(float(rng.normal()), rng.normal(size=n_y), float(rng.normal()), L @ L.T + 0.5 * np.eye(n_y),
                      rng.normal(size=n_y), rng.normal(size=n_y), rng.uniform(-1, 1, size=n_y),
                      float(rng.uniform(0.5, 1.5)), rng.normal(size=n_y) if x_row else None,
                      rng.normal(size=n_y) if x_row else None, float(rng.uniform(0.3, 1.0)))


def build_convex_bilevel(data: ConvexData) -> BilevelProblem:
    """The instance as a BilevelProblem (x in [0, 1], y in [-3, 3]^n_y)."""
    DM = ca.DM
    p = BilevelProblem("random-convex")
    x = p.upper_variable("x", 1, lb=0, ub=1)
    y = p.lower_variable("y", data.e.size, lb=-3, ub=3)
    p.minimize_upper(data.h * x + ca.dot(DM(data.e), y) + data.w * x * y[0])
    p.minimize_lower(0.5 * ca.dot(y, ca.mtimes(DM(data.P), y)) + ca.dot(DM(data.q) + x * DM(data.r), y))
    p.lower_constraint(ca.sumsqr(y - DM(data.c)) <= data.rho ** 2)
    if data.a is not None:
        row = DM(data.a) + x * DM(data.b)
        p.lower_constraint(ca.dot(row, y) <= ca.dot(row, DM(data.c)) + data.m)
    return p
