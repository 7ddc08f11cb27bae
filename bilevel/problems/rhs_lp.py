"""The right-hand-side LP attack of the scale and natural-declaration benchmarks and tests: the follower minimizes
c'y s.t. A y <= b + x, -1 <= y <= 1; the leader maximizes c'y over x in [-delta, delta]^m.

Data from default_rng(seed): A ~ N(0, 1) (m x n), b = A y0 + s with y0 ~ U(-0.5, 0.5)^n and s ~ U(0.3, 1)^m (so y0
stays feasible for every attack), c ~ N(0, 1)^n. The lower level is declared three ways: `lower_qp` (matrices), one
vector `lower_constraint`, or one `lower_constraint` per row (named row0, row1, ...).
"""

from __future__ import annotations

import casadi as ca
import numpy as np

from ..errors import ModelError
from ..model import BilevelProblem

FORMS = ("lower_qp", "vector", "rows")


def rhs_lp_data(m: int, n: int, seed: int = 0) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(A, b, c) of the instance at m rows x n variables (module docstring)."""
    rng = np.random.default_rng(seed)
    A = rng.standard_normal((m, n))
    b = A @ rng.uniform(-0.5, 0.5, n) + rng.uniform(0.3, 1.0, m)
    return A, b, rng.standard_normal(n)


def rhs_lp(m: int, n: int, form: str = "lower_qp", delta: float = 0.2, seed: int = 0) -> BilevelProblem:
    """The attack at m rows x n variables, its lower level declared by `form` (FORMS)."""
    if form not in FORMS:
        raise ModelError(f"rhs_lp: form {form!r} is not one of {', '.join(FORMS)}")
    A, b, c = rhs_lp_data(m, n, seed)
    p = BilevelProblem(f"rhs-{form}")
    x = p.upper_variable("x", m, lb=-delta, ub=delta)
    y = p.lower_variable("y", n, lb=-1, ub=1)
    p.maximize_upper(ca.dot(ca.DM(c), y))
    if form == "lower_qp":
        p.lower_qp(y, q=c, A=A, b=b + x)
        return p
    p.minimize_lower(ca.dot(ca.DM(c), y))
    if form == "vector":
        p.lower_constraint(ca.mtimes(ca.DM(A), y) <= b + x)
    else:
        for i in range(m):
            p.lower_constraint(ca.dot(ca.DM(A[i]), y) <= b[i] + x[i], name=f"row{i}")
    return p
