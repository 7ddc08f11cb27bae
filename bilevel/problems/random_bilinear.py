"""Random bilevel programs with a bilinear leader over an LP lower level (seeded), for tests and benchmarks of
method="global", algorithm "scip".

min_x  x'Cy + c'x + e'y   s.t.  0 <= x <= 1,
y in argmin_y  (d + R'x)'y  s.t.  A y <= b,  0 <= y <= 1.
The follower's cost depends on x (a price or a toll); b > 0 keeps y = 0 feasible, so the lower level has an optimum
at every x, at a vertex of a polytope that does not depend on x.
"""

from __future__ import annotations

from dataclasses import dataclass

import casadi as ca
import numpy as np

from ..model import BilevelProblem


@dataclass(frozen=True)
class BilinearData:
    """The coefficients of one random instance (see the module docstring)."""

    C: np.ndarray
    c: np.ndarray
    e: np.ndarray
    d: np.ndarray
    R: np.ndarray
    A: np.ndarray
    b: np.ndarray


def random_bilinear_data(rng: np.random.Generator, n_x: int, n_y: int, m: int) -> BilinearData:
    """Standard normal C, c, e, d, R, A and b uniform in [0.5, 2]."""
    return BilinearData(rng.normal(size=(n_x, n_y)), rng.normal(size=n_x), rng.normal(size=n_y),
                        rng.normal(size=n_y), rng.normal(size=(n_x, n_y)), rng.normal(size=(m, n_y)),
                        rng.uniform(0.5, 2.0, size=m))


def build_bilinear_bilevel(data: BilinearData) -> BilevelProblem:
    """The instance as a BilevelProblem (x in [0, 1]^n_x, y in [0, 1]^n_y)."""
    DM = ca.DM
    p = BilevelProblem("random-bilinear")
    x = p.upper_variable("x", data.C.shape[0], lb=0, ub=1)
    y = p.lower_variable("y", data.C.shape[1], lb=0, ub=1)
    p.minimize_upper(ca.dot(x, ca.mtimes(DM(data.C), y)) + ca.dot(DM(data.c), x) + ca.dot(DM(data.e), y))
    p.minimize_lower(ca.dot(DM(data.d) + ca.mtimes(DM(data.R).T, x), y))
    p.lower_constraint(ca.mtimes(DM(data.A), y) <= DM(data.b))
    return p
