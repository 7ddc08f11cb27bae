"""Random bilevel programs with an LP lower level (seeded), for tests and benchmarks of method="global".

min_x  c_x'x + c_y'y + 1/2 sum_j u_j (x_j - x0_j)^2   s.t.  0 <= x <= 1,
y in argmin_y  (d + C x)'y  s.t.  A y + B x <= b,  0 <= y <= y_max.
b > 0, so y = 0 is feasible at x = 0; the lower feasible set is bounded by the box, so the lower level has an
optimum wherever it is feasible. u = 0 gives an LP-LP instance.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..model import BilevelProblem


@dataclass(frozen=True)
class LinearBilevelData:
    """The coefficients of one random instance (see the module docstring)."""

    c_x: np.ndarray
    c_y: np.ndarray
    u: np.ndarray
    x0: np.ndarray
    d: np.ndarray
    C: np.ndarray
    A: np.ndarray
    B: np.ndarray
    b: np.ndarray
    y_max: float

    @property
    def shape(self) -> tuple[int, int, int]:
        """(upper variables, lower variables, lower constraints apart from the box)."""
        return self.c_x.size, self.c_y.size, self.b.size


def random_linear_data(rng: np.random.Generator, n_x: int, n_y: int, m: int, quadratic_upper: bool = False,
                       coupled_cost: bool = False) -> LinearBilevelData:
    """Integer coefficients in [-5, 5] (b in [1, 10]; d and each row of A nonzero, so every lower constraint and
    the lower cost involve y); optional convex quadratic upper term and x-dependent lower cost."""
    if min(n_x, n_y, m) < 1:
        raise ValueError(f"need n_x, n_y, m >= 1, got {n_x}, {n_y}, {m}")
    ints = lambda *shape: rng.integers(-5, 6, size=shape).astype(float)  # noqa: E731
    nonzero = lambda *shape: rng.choice([-5, -4, -3, -2, -1, 1, 2, 3, 4, 5], size=shape).astype(float)  # noqa: E731
    A = ints(m, n_y)
    empty = ~A.any(axis=1)
    A[empty, rng.integers(0, n_y, size=int(empty.sum()))] = nonzero(int(empty.sum()))
    return LinearBilevelData(
        c_x=ints(n_x), c_y=ints(n_y),
        u=rng.integers(0, 4, size=n_x).astype(float) if quadratic_upper else np.zeros(n_x),
        x0=rng.random(n_x), d=nonzero(n_y), C=ints(n_y, n_x) if coupled_cost else np.zeros((n_y, n_x)),
        A=A, B=ints(m, n_x), b=rng.integers(1, 11, size=m).astype(float), y_max=10.0)


def build_linear_bilevel(data: LinearBilevelData, name: str = "random-linear") -> BilevelProblem:
    """The BilevelProblem of `data`."""
    n_x, n_y, _ = data.shape
    p = BilevelProblem(name)
    x = p.upper_variable("x", n_x, lb=0, ub=1)
    y = p.lower_variable("y", n_y, lb=0, ub=data.y_max)
    upper = sum(data.c_x[j] * x[j] for j in range(n_x)) + sum(data.c_y[i] * y[i] for i in range(n_y))
    upper += sum(0.5 * data.u[j] * (x[j] - data.x0[j]) ** 2 for j in range(n_x) if data.u[j])
    p.minimize_upper(upper)
    p.minimize_lower(sum((data.d[i] + sum(data.C[i, j] * x[j] for j in range(n_x))) * y[i] for i in range(n_y)))
    for k in range(data.b.size):
        p.lower_constraint(sum(data.A[k, i] * y[i] for i in range(n_y)) + sum(data.B[k, j] * x[j] for j in range(n_x))
                           <= data.b[k])
    return p
