"""method="global" on convex-NLP lower levels and lower constraint matrices that depend on x (SCIP, multiplier bounds
from a Slater point): the literature problems' published optima proven, refusals by class, and a property against
brute force on random instances.

Published optima (citations in each problem's registry `source`; every value re-derived by brute force in
tests/problems/test_literature_data.py):
- bolib-floudaszlobec1998: Floudas & Zlobec (1998), BOLIB FloudasZlobec1998, F* = 1.
- bolib-colson2002bipa1, bipa3, bipa4, bipa5: Colson (2002), BIPA1/3/4/5 (BOLIB, BASBLib c_2002_0x): F* = 250, 2,
  (10 - 1/sqrt 3)^2 = 88.7863 (BOLIB 88.79), 2.749768 (BOLIB 2.75).
- bolib-allendestill2013: Allende & Still (2013), BOLIB AllendeStill2013, F* = 1.
- bolib-outrata1990ex2e, bolib-outrata1993ex31, bolib-outrata1993ex32: Outrata (1990, 1993), BOLIB F* = 0.9, 1.56,
  3.208 (rounded; here 0.8974598, 1.5628738, 3.2077000).
"""

from __future__ import annotations

import casadi as ca
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.optimize import minimize_scalar

import bilevel as bl
from bilevel.problems import registry
from bilevel.problems.random_convex import ConvexData, build_convex_bilevel, random_convex_data
from bilevel.solvers.globalopt import scip as global_scip

from ..problems.bruteforce import BruteForce, search
from .test_global_scip import GAP, _check_proven

pytest.importorskip("pyscipopt")

NONLINEAR_LOWER = sorted({*registry.names("convex-nlp"), *registry.names("x-matrix"), "bolib-floudaszlobec1998"})


def test_the_set_holds_six_convex_nlp_and_two_x_matrix_literature_problems() -> None:
    textbook = set(registry.names("textbook"))
    assert len(set(registry.names("convex-nlp")) & textbook) >= 6
    assert len(set(registry.names("x-matrix")) & textbook) >= 2


@pytest.mark.parametrize("name", NONLINEAR_LOWER)
def test_published_optimum_proven(name: str) -> None:
    _check_proven(bl.solve(registry.get(name), method="global"), registry.spec(name).optimum)


def test_slater_bounds_are_stated() -> None:
    """FloudasZlobec1998: y^ = (0, 1/2) strictly inside y1^2 + x y2 <= 1 for x in [0, 1], f = -y2 in [-100, -1/2]:
    the bound on that row's multiplier is (-0.5 + 100) / 0.5 = 199."""
    res = bl.solve(registry.get("bolib-floudaszlobec1998"), method="global")
    lines = res.certificate.global_bound.big_m
    assert any(line.startswith("multiplier bounds from the Slater point") for line in lines)
    row = next(line for line in lines if line.startswith("g1[0]: lam"))
    assert float(row.split("<=")[1].split("(")[0]) == pytest.approx(199.0, rel=1e-5)


def _one_dimensional(lower_row) -> bl.BilevelProblem:
    p = bl.BilevelProblem("x-row")
    x = p.upper_variable("x", 1, lb=0, ub=1)
    y = p.lower_variable("y", 1, lb=0, ub=5)
    p.minimize_upper(x - y)
    p.minimize_lower(-y)
    p.lower_constraint(lower_row(x, y))
    return p


def test_x_dependent_lower_constraint_matrix_is_proven() -> None:
    """(1 + x) y <= 3: A(x)'lam in the stationarity; y = 3 / (1 + x), F = x - 3 / (1 + x) is smallest at x = 0."""
    _check_proven(bl.solve(_one_dimensional(lambda x, y: (1 + x) * y <= 3), method="global"), -3.0)


def test_no_slater_point_is_refused_by_class() -> None:
    """Dempe & Dutta (2012), Example 2.4 (BOLIB DempeDutta2012Ex24): y^2 <= 0 has no interior, the KKT conditions
    fail at the lower solution y = 0, and the KKT reformulation is not equivalent: refused, not answered."""
    p = bl.BilevelProblem("dempe-dutta")
    x = p.upper_variable("x", 1, lb=-10, ub=10)
    y = p.lower_variable("y", 1, lb=-10, ub=10)
    p.minimize_upper((x - 1) ** 2 + y ** 2)
    p.minimize_lower(x ** 2 * y)
    p.lower_constraint(y ** 2 <= 0)
    with pytest.raises(bl.ModelError, match="Slater.*class: lower multipliers without a derivable bound"):
        bl.solve(p, method="global")


def test_convexity_not_proven_is_refused_by_class() -> None:
    """log(exp(y1) + exp(y2)) is convex, but neither interval Hessian bounds nor the composition rules (log of a
    convex function) prove it: refused by class."""
    p = bl.BilevelProblem("log-sum-exp")
    x = p.upper_variable("x", 1, lb=0, ub=1)
    y = p.lower_variable("y", 2, lb=-1, ub=1)
    p.minimize_upper(x + y[0])
    p.minimize_lower(ca.log(ca.exp(y[0]) + ca.exp(y[1])) - x * y[0])
    p.lower_constraint(y[0] ** 2 + y[1] ** 2 <= 1)
    with pytest.raises(bl.ModelError, match="class: lower level not provably convex on the box"):
        bl.solve(p, method="global")


def test_equalities_beside_a_curved_row_are_refused_by_class() -> None:
    p = bl.BilevelProblem("equality")
    x = p.upper_variable("x", 1, lb=0, ub=1)
    y = p.lower_variable("y", 2, lb=-2, ub=2)
    p.minimize_upper(x - y[0])
    p.minimize_lower(ca.exp(y[0]) + y[1] ** 2)
    p.lower_constraint(y[0] + y[1] == x)
    p.lower_constraint(y[0] ** 2 <= 1)
    with pytest.raises(bl.ModelError, match="equality constraints.*class: lower multipliers without a derivable"):
        bl.solve(p, method="global")


# --- the property: a convex quadratically constrained lower level (bilevel/problems/random_convex.py), with and
# without a constraint row depending on x, against brute force: tests/problems/bruteforce.py's grid over x (refined
# around its best points, then by a bounded scalar search), the lower level solved exactly at each x (Clarabel's
# SOCP polished by Newton's method on its active set, independent of the global method) ---

def brute_force(data: ConvexData) -> float:
    """min over x in [0, 1] of F(x, y*(x)) (y* unique: the lower objective is strictly convex)."""
    bf = BruteForce(build_convex_bilevel(data))
    coarse = search(bf, [(0.0, 1.0)], 51, refine=2)
    centre = float(coarse.best_x[0])
    near = minimize_scalar(lambda v: bf.leader_value(np.array([v]))[0], method="bounded",
                           bounds=(max(centre - 0.02, 0.0), min(centre + 0.02, 1.0)), options={"xatol": 1e-10})
    return min(coarse.best_value, float(near.fun))


@settings(max_examples=10, deadline=None, derandomize=True)
@given(seed=st.integers(0, 2**32 - 1), n_y=st.integers(1, 2), x_row=st.booleans())
def test_random_quadratic_constraint_lower_matches_brute_force(seed: int, n_y: int, x_row: bool) -> None:
    data = random_convex_data(np.random.default_rng(seed), n_y, x_row)
    res = bl.solve(build_convex_bilevel(data), method="global")
    brute = brute_force(data)
    gb = res.certificate.global_bound
    assert res.status is bl.Status.SOLVED and gb.proven, res.message
    slack = GAP * max(1.0, abs(brute))  # the method's stated gap
    assert gb.lower_bound <= brute + slack, (gb.lower_bound, brute)  # the proven bound holds at the brute-force point
    assert abs(res.upper_objective - brute) <= slack, (res.upper_objective, brute)


def test_an_internal_scip_error_is_a_status_with_its_cause(monkeypatch) -> None:
    """SCIP raising inside optimize (as on BOLIB's GumusFloudas2001Ex1, LP numerics at feastol 1e-9) ends the search
    with status error and SCIP's message, never an exception out of solve."""
    class Failing:
        def setParam(self, name: str, value: object) -> None:
            pass

        def optimize(self) -> None:
            raise Exception("SCIP: error in LP solver!")

    monkeypatch.setattr(global_scip, "_build", lambda *args: (Failing(), []))
    res = bl.solve(registry.get("bolib-colson2002bipa1"), method="global")
    assert res.status is bl.Status.ERROR and "error in LP solver" in res.message and "scip_feastol" in res.message
