"""method="global", algorithm "scip": nonconvex leaders proven by SCIP's spatial branch-and-bound.

Published optima (each value re-derived by hand in the problem's docstring and re-checked by brute force in
tests/problems/test_literature_data.py):
- bolib-hendersonquandt1958: Henderson & Quandt (1958), Microeconomic Theory, Stackelberg duopoly; BOLIB
  HendersonQuandt1958 (Zhou, Zemkoho & Tin 2020), F* = -3266.67 (exact -9800/3).
- macmpec-bard3: Bard (1988), Math. Program. 40:15-27, Example 3 (MacMPEC bard3, BOLIB Bard1988Ex3),
  F* = -12.6787 (exact -12.6787109375): concave leader, x^2 in an upper and a lower constraint.
- macmpec-ex9.2.8: Yezza (1996), JOTA 89:189-219, Example 3.1; Floudas et al. (1999), Handbook of Test Problems,
  ch. 9 (MacMPEC ex9.2.8), F* = 1.5.
- bolib-lucchettietal1987: Lucchetti, Mignanego & Pieri (1987), Optimization 18:857-866; BOLIB, F* = 0.
- bolib-ishizukaaiyoshi1992a: Ishizuka & Aiyoshi (1992), Ann. Oper. Res. 34:73-88; BOLIB, F* = 0.
- bolib-tollsettingp1, p4, p5: toll setting (Labbé, Marcotte & Savard 1998, Management Science 44(12):1608-1622);
  BOLIB TollSettingP1/P4/P5, revenue 7, 4 and 2.5.
"""

from __future__ import annotations

import itertools

import casadi as ca
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.optimize import linprog, minimize_scalar

import bilevel as bl
from bilevel.experiments.compare import relative_gap
from bilevel.problems import registry
from bilevel.problems.random_bilinear import BilinearData, build_bilinear_bilevel, random_bilinear_data
from bilevel.solvers.globalopt import method as global_method, scip as global_scip

pytest.importorskip("pyscipopt")

NONCONVEX_LEADER = sorted({"bolib-hendersonquandt1958", "macmpec-ex9.2.8", "macmpec-bard3", *registry.names("bilinear"),
                           *registry.names("polynomial")})
GAP = 1e-6


def _check_proven(res: bl.BilevelResult, known: float) -> None:
    gb = res.certificate.global_bound
    assert res.status is bl.Status.SOLVED, res.message
    assert res.stats["algorithm"].startswith("scip")
    assert res.certificate.passed and gb is not None and gb.proven and gb.gap <= GAP
    assert relative_gap(res.upper_objective, known) <= GAP, (res.upper_objective, known)
    slack = GAP * max(1.0, abs(known))
    assert gb.lower_bound - slack <= known <= gb.upper_bound + slack, (gb, known)


def test_the_nonconvex_textbook_set_holds_three_bilinear_literature_problems_and_a_toll_problem() -> None:
    assert len(set(registry.names("bilinear")) & set(registry.names("textbook"))) >= 3
    assert registry.names("toll")
    assert all("BOLIB" in registry.spec(n).source for n in registry.names("toll"))


@pytest.mark.parametrize("name", NONCONVEX_LEADER)
def test_published_optimum_proven(name: str) -> None:
    """Each problem's published optimum (citations in the module docstring and in its registry `source`)."""
    res = bl.solve(registry.get(name), method="global")
    _check_proven(res, registry.spec(name).optimum)


def three_path_toll(ub: float = 10.0) -> bl.BilevelProblem:
    """One unit of traffic on three paths: tolled 2 + t1, tolled 3 + t2, toll-free 6. Revenue max is 4 (t1 = 4,
    t2 >= 3; the follower ties with the toll-free path and the optimistic convention sends it on path 1)."""
    p = bl.BilevelProblem("three-path-toll")
    t = p.upper_variable("t", 2, lb=0, ub=ub)
    y = p.lower_variable("y", 3, lb=0)
    p.maximize_upper(t[0] * y[0] + t[1] * y[1])
    p.minimize_lower((2 + t[0]) * y[0] + (3 + t[1]) * y[1] + 6 * y[2])
    p.lower_constraint(y[0] + y[1] + y[2] == 1)
    return p


def test_three_path_toll_setting_is_proven() -> None:
    res = bl.solve(three_path_toll(), method="global")
    _check_proven(res, 4.0)
    assert res.x["t"][0] == pytest.approx(4.0, abs=1e-6) and res.x["t"][1] >= 3.0 - 1e-6


def test_unbounded_toll_is_refused_naming_the_variable_and_the_fix() -> None:
    with pytest.raises(bl.ModelError, match=r"x\[0\], x\[1\] \(canonical upper variables\).*declare bounds"):
        bl.solve(three_path_toll(ub=np.inf), method="global")


def test_node_limit_returns_valid_bounds_and_an_honest_status() -> None:
    res = bl.solve(registry.get("bolib-tollsettingp1"), method="global", node_limit=2)
    assert res.status is bl.Status.MAX_ITERATIONS, res.message
    assert "node_limit" in res.message and "gap" in res.message
    assert res.stats["lower_bound"] - 1e-6 <= 7.0 <= res.stats["upper_bound"] + 1e-6  # revenue 7 in between


def test_time_limit_returns_an_honest_status() -> None:
    data = random_bilinear_data(np.random.default_rng(0), 4, 12, 8)
    res = bl.solve(build_bilinear_bilevel(data), method="global", time_limit=0.01)
    assert res.status is bl.Status.MAX_ITERATIONS, res.message
    assert "time_limit" in res.message
    low, high = res.stats["lower_bound"], res.stats["upper_bound"]
    assert low <= high


def test_without_pyscipopt_the_refusal_names_the_class_and_the_install(monkeypatch) -> None:
    monkeypatch.setattr(global_method, "scip_available", lambda: False)
    monkeypatch.setattr(global_scip, "scip_available", lambda: False)
    problem = registry.get("bolib-tollsettingp5")
    with pytest.raises(bl.ModelError, match="nonconvex upper objective.*pip install pyscipopt.*relaxation"):
        bl.solve(problem, method="global")
    with pytest.raises(bl.ModelError, match="needs pyscipopt.*pip install"):
        bl.solve(problem, method="global", algorithm="scip")


def test_convex_algorithms_refuse_a_nonconvex_leader_and_scip_takes_a_convex_one() -> None:
    with pytest.raises(bl.ModelError, match="nonconvex upper objective.*algorithm='scip'"):
        bl.solve(registry.get("bolib-tollsettingp5"), method="global", algorithm="branch-and-bound")
    res = bl.solve(registry.get("macmpec-bard1"), method="global", algorithm="scip")
    _check_proven(res, 17.0)


def _x_hessian(lower_curvature) -> bl.BilevelProblem:
    """min (y - 0.6)^2 + 0.1 x over x in [0, 2], y in argmin{c(x) y^2 - 2 y : 0 <= y <= 5}: y(x) = 1 / c(x)."""
    p = bl.BilevelProblem("x-hessian")
    x = p.upper_variable("x", 1, lb=0, ub=2)
    y = p.lower_variable("y", 1, lb=0, ub=5)
    p.minimize_upper((y - 0.6) ** 2 + 0.1 * x)
    p.minimize_lower(lower_curvature(x) * y ** 2 - 2 * y)
    return p


def test_x_dependent_lower_hessian_affine_in_x_is_proven() -> None:
    """Lower Hessian 2 (1 + x), PSD on the box [0, 2] (checked at its vertices): y = 1 / (1 + x), and the proven
    value is the minimum of (1 / (1 + x) - 0.6)^2 + 0.1 x, computed here on a grid refined by a bounded search."""
    res = bl.solve(_x_hessian(lambda x: 1 + x), method="global")

    def along(v: float) -> float:
        return (1.0 / (1.0 + v) - 0.6) ** 2 + 0.1 * v

    xs = np.linspace(0.0, 2.0, 2001)
    k = int(np.argmin([along(v) for v in xs]))
    near = minimize_scalar(along, bounds=(xs[max(k - 1, 0)], xs[min(k + 1, xs.size - 1)]), method="bounded",
                           options={"xatol": 1e-12})
    _check_proven(res, min(near.fun, along(xs[k])))
    assert "x-dependent lower Hessian" in res.message or res.stats["algorithm"].startswith("scip")


def test_x_dependent_lower_hessian_refusals_name_the_class() -> None:
    with pytest.raises(bl.ModelError, match="x-dependent lower Hessian, nonlinear in x.*does not cover"):
        bl.solve(_x_hessian(lambda x: 1 + x ** 2), method="global")
    p = bl.BilevelProblem("corner")   # lower Hessian 2 (1 - x1 - x2): negative only near the corner (0.51, 0.51)
    x = p.upper_variable("x", 2, lb=0, ub=0.51)
    y = p.lower_variable("y", 1, lb=0, ub=5)
    p.minimize_upper(x[0] * y)
    p.minimize_lower((1 - x[0] - x[1]) * y ** 2 - y)
    with pytest.raises(bl.NonConvexLowerLevel, match="vertex of the upper box"):
        bl.solve(p, method="global")


def test_lower_constraint_nonlinear_in_x_is_proven() -> None:
    """min x - y over x in [0, 1], y in argmax{y : y + x^2 <= 3, 0 <= y <= 5}: y = 3 - x^2, F = x - 3 + x^2,
    minimal at x = 0 with F* = -3 (the slack of y + x^2 <= 3 is nonlinear in x: an SCIP constraint, SOS1)."""
    p = bl.BilevelProblem("b(x)")
    x = p.upper_variable("x", 1, lb=0, ub=1)
    y = p.lower_variable("y", 1, lb=0, ub=5)
    p.minimize_upper(x - y)
    p.minimize_lower(-y)
    p.lower_constraint(y + x ** 2 <= 3)
    _check_proven(bl.solve(p, method="global"), -3.0)


def test_nonlinear_upper_constraint_and_expression_translation() -> None:
    """An upper constraint x^2 + y^2 <= 1 (nonlinear) with a leader using exp, log, sqrt, sin, division and a
    fractional power: SCIP's optimum is the independent grid optimum of the same bilevel problem."""
    p = bl.BilevelProblem("nonlinear-upper")
    x = p.upper_variable("x", 1, lb=0.1, ub=2)
    y = p.lower_variable("y", 1, lb=0, ub=2)
    F = ca.exp(x) * y - ca.log(x) + ca.sqrt(x) / (1 + y) + ca.sin(x) * ca.cos(y) + x ** 1.5
    p.minimize_upper(F)
    p.upper_constraint(x ** 2 + y ** 2 <= 1)
    p.minimize_lower((y - x) ** 2)        # follower: y = x
    res = bl.solve(p, method="global")
    assert res.status is bl.Status.SOLVED, res.message
    def along(v: float) -> float:  # F on the bilevel-feasible curve y = x, 0.1 <= x <= 1/sqrt(2) (2 x^2 <= 1)
        return float(np.exp(v) * v - np.log(v) + np.sqrt(v) / (1 + v) + np.sin(v) * np.cos(v) + v ** 1.5)

    xs = np.linspace(0.1, 1 / np.sqrt(2), 2001)
    k = int(np.argmin([along(v) for v in xs]))
    near = minimize_scalar(along, bounds=(xs[max(k - 1, 0)], xs[min(k + 1, xs.size - 1)]), method="bounded",
                           options={"xatol": 1e-12})
    assert res.upper_objective == pytest.approx(min(near.fun, along(xs[k])), abs=1e-5)
    assert res.certificate.global_bound.proven


# --- the property: bilinear leader over an LP lower level (bilevel/problems/random_bilinear.py), against brute
# force over the lower level's vertices ---

def _vertices(A: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Vertices of {y : A y <= b, 0 <= y <= 1} by solving every choice of n_y active rows."""
    n = A.shape[1]
    rows = np.vstack([A, -np.eye(n), np.eye(n)])
    rhs = np.concatenate([b, np.zeros(n), np.ones(n)])
    found: list[np.ndarray] = []
    for active in itertools.combinations(range(rows.shape[0]), n):
        M = rows[list(active)]
        if abs(np.linalg.det(M)) < 1e-10:
            continue
        v = np.linalg.solve(M, rhs[list(active)])
        if np.all(rows @ v <= rhs + 1e-9) and not any(np.allclose(v, u, atol=1e-9) for u in found):
            found.append(v)
    return np.array(found)


def brute_force(data: BilinearData) -> float:
    """Optimistic optimum: min over vertices v of min over {x in [0,1]^n : v is a follower optimum at x} of F(x, v).

    F(x, .) is linear, so over the follower's optimal face (a face of the polytope) its minimum is at a vertex; for
    fixed v the set of x making v optimal is {x : (d + R'x)'(v - u) <= 0 for every vertex u}, so each inner
    problem is an LP in x (F(x, v) is linear in x)."""
    C, c, e, d, R = data.C, data.c, data.e, data.d, data.R
    V = _vertices(data.A, data.b)
    best = np.inf
    for v in V:
        diffs = v[None, :] - V                        # rows v - u
        A_ub, b_ub = diffs @ R.T, -diffs @ d          # (d + R'x)'(v - u) <= 0
        res = linprog(C @ v + c, A_ub=A_ub, b_ub=b_ub, bounds=[(0, 1)] * C.shape[0], method="highs")
        if res.status == 0:
            best = min(best, float(res.fun) + float(e @ v))
    return best


@settings(max_examples=12, deadline=None, derandomize=True)
@given(seed=st.integers(0, 2**32 - 1), n_x=st.integers(1, 2), n_y=st.integers(1, 3), m=st.integers(1, 2))
def test_random_bilinear_leader_matches_vertex_enumeration(seed: int, n_x: int, n_y: int, m: int) -> None:
    data = random_bilinear_data(np.random.default_rng(seed), n_x, n_y, m)
    brute = brute_force(data)
    assert np.isfinite(brute)  # y = 0 is a vertex and some vertex is optimal at every x
    res = bl.solve(build_bilinear_bilevel(data), method="global")
    _check_proven(res, brute)


def test_command_line_names_the_class_of_a_refused_problem(monkeypatch, capsys) -> None:
    """`bilevel solve NAME --method global` on a refused problem: exit code 2 and the class in the error."""
    from bilevel.cli import main

    monkeypatch.setattr(global_method, "scip_available", lambda: False)
    assert main(["solve", "bolib-floudaszlobec1998", "--method", "global"]) == 2
    assert "class: nonlinear lower level" in capsys.readouterr().err
    assert main(["solve", "bolib-tollsettingp5", "--method", "global"]) == 2
    err = capsys.readouterr().err
    assert "class: nonconvex leader" in err and "pip install pyscipopt" in err
