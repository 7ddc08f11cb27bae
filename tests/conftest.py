"""Shared fixtures: small bilevel problems with optima known in closed form or from the literature."""

from __future__ import annotations

import casadi as ca
import pytest
from hypothesis import settings

import bilevel as bl
from bilevel.problems import registry

# Every property test draws the same examples on every run and machine: a verdict must not depend on which example a
# run happens to draw (a test's own @settings overrides only what it names, so derandomize holds for all of them).
settings.register_profile("bilevel", derandomize=True, deadline=None, print_blob=True)
settings.load_profile("bilevel")


def bard_511() -> bl.BilevelProblem:
    """Bard (1998), Practical Bilevel Optimization, Example 5.1.1 (also Dempe 2002): F* = -12 at (4, 4)."""
    return registry.get("bard1998-ex5.1.1")


def projection_qp(maximize_lower: bool = False) -> bl.BilevelProblem:
    """y*(x) = projection of x onto {y0 + y1 <= 1}; F = |y - (1,2)|^2 + 0.1|x|^2 (optimum derived in tests)."""
    p = bl.BilevelProblem("projection-qp")
    x = p.upper_variable("x", 2, lb=-5, ub=5)
    y = p.lower_variable("y", 2)
    p.minimize_upper(ca.sumsqr(y - ca.DM([1, 2])) + 0.1 * ca.sumsqr(x))
    f = ca.sumsqr(y - x)
    if maximize_lower:
        p.maximize_lower(-f)
    else:
        p.minimize_lower(f)
    p.lower_constraint(y[0] + y[1] <= 1)
    return p


@pytest.fixture
def bard() -> bl.BilevelProblem:
    return bard_511()
