"""Method `reduced`: IPOPT over the upper variables with every upper constraint (also those on the lower solution)
kept as a constraint, y*(x) and its derivative from the engine's exact lower solve and adjoint."""

from __future__ import annotations

import casadi as ca
import numpy as np
import pytest

import bilevel as bl
from bilevel.errors import ModelError
from bilevel.problems import registry
from bilevel.solvers.engine.prepared import prepare


@pytest.mark.parametrize("name", ["macmpec-ex9.2.2", "bolib-gumusfloudas2001ex4"])
def test_textbook_problems_with_upper_constraints_on_the_lower_solution_reach_their_optimum(name: str) -> None:
    """Shimizu & Aiyoshi (1981), IEEE TAC 26:460-466, Example 1 (the leader's y <= x on the follower's QP solution,
    F* = 100 at x = y = 10), and Gumus & Floudas (2001), J. Glob. Optim. 20:1-31, Example 4 (three half-planes on
    (x, y), F* = 9 at x = 3, y = 5): the registered optimum and solution, certified."""
    spec = registry.spec(name)
    res = bl.solve(registry.get(name), method="reduced")
    assert res.status.value == "solved" and res.certificate.passed, res.message
    assert res.upper_objective == pytest.approx(spec.optimum, abs=1e-5)
    for var, value in spec.solution.items():
        np.testing.assert_allclose(np.concatenate([res.x.get(var, []), res.y.get(var, [])]).ravel(), value, atol=1e-4)


def test_a_least_squares_learner_under_a_ball_on_its_solution() -> None:
    """y*(x) = x (least squares) and the leader maximizes sum(y) subject to ||y||^2 <= 1: F* = sqrt(n) at
    x = y = 1/sqrt(n) (Cauchy-Schwarz), certified."""
    n = 5
    p = bl.BilevelProblem("coupled")
    x = p.upper_variable("x", n, lb=-1, ub=1)
    y = p.lower_variable("y", n)
    p.minimize_lower(ca.sumsqr(y - x))
    p.maximize_upper(ca.sum1(y))
    p.upper_constraint(ca.sumsqr(y) <= 1)
    res = p.solve("reduced")
    assert res.status.value == "solved" and res.certificate.passed, res.message
    assert res.upper_objective == pytest.approx(np.sqrt(n), rel=1e-7)
    np.testing.assert_allclose(res.x["x"], np.full(n, 1 / np.sqrt(n)), atol=1e-6)
    np.testing.assert_allclose(res.y["y"], res.x["x"], atol=1e-9)


def test_a_lower_level_whose_solution_need_not_be_unique_is_refused() -> None:
    with pytest.raises(ModelError, match="class 'lp'"):
        bl.solve(registry.get("bard1998-ex5.1.1"), method="reduced")
    p = bl.BilevelProblem("flat")
    x = p.upper_variable("x", 1, lb=-1, ub=1)
    y = p.lower_variable("y", 2, lb=-1, ub=1)
    p.minimize_lower((y[0] - x) ** 2)  # y[1] free in [-1, 1]: a singular QP Hessian
    p.minimize_upper(x ** 2 + y[1] ** 2)
    with pytest.raises(ModelError, match="singular"):
        bl.solve(p, method="reduced")


def test_options_are_the_keywords_and_bad_ones_are_named() -> None:
    """The options auto matches against (options_of) are solve_reduced's keywords, listed by show_options; a
    misspelt option is an UnknownOption naming the accepted ones, a bad IPOPT option a ModelError."""
    import inspect

    from bilevel.errors import UnknownOption
    from bilevel.solvers.engine.prepared import options_of
    from bilevel.solvers.reduced import solve_reduced

    keywords = {k for k, v in inspect.signature(solve_reduced).parameters.items() if v.kind is v.KEYWORD_ONLY}
    assert keywords == set(options_of(solve_reduced)) >= {"starts", "nlp_tol", "max_iter", "active_tol"}
    p = registry.get("macmpec-ex9.2.2")
    with pytest.raises(UnknownOption, match="max_iters.*accepts: active_tol"):
        bl.solve(p, method="reduced", max_iters=3)
    with pytest.raises(ModelError, match="IPOPT did not accept"):
        bl.solve(p, method="reduced", ipopt={"no_such_option": 1})



def _ranged(shared: bool, lo: float, hi: float, inner: bool = False) -> bl.BilevelProblem:
    """y*(x) = x (least squares); on the box [-1, 1]^2 with lo <= y0^2 + y1^2 <= hi (the two bounds on one expression
    (shared) or on two equal ones built apart) the leader maximizes y0 + 2 y1 (the upper bound active) or, inner,
    minimizes ||y - (0.1, 0.2)||^2 (the lower bound active)."""
    p = bl.BilevelProblem("ranged")
    x = p.upper_variable("x", 2, lb=-1, ub=1)
    y = p.lower_variable("y", 2)
    p.minimize_lower(ca.sumsqr(y - x))
    if inner:
        p.minimize_upper(ca.sumsqr(y - ca.DM([0.1, 0.2])))
    else:
        p.maximize_upper(y[0] + 2 * y[1])
    e = ca.sumsqr(y)
    p.upper_constraint(e <= p.parameter("hi", value=hi), name="high")
    p.upper_constraint((e if shared else ca.sumsqr(y)) >= lo, name="low")
    return p


def test_a_two_sided_bound_on_one_expression_is_one_ranged_row_with_the_same_answer() -> None:
    """G_ranges pairs the rows `e - b` and `a - e` of one expression node (width b - a at the parameters' values), not
    two equal expressions built apart; method reduced states the pair as one ranged row and reaches the answer of the
    two rows: F* = sqrt(5 hi) with the upper bound active, (sqrt(lo) - sqrt(0.05))^2 with the lower one."""
    p = _ranged(True, 0.25, 0.5)
    up, lo, width = prepare(p).canon.G_ranges
    assert list(up) == [0] and list(lo) == [1] and width() == pytest.approx([0.25])
    p.set_value("hi", 0.64)
    assert width() == pytest.approx([0.39])  # b - a read at the parameters' current values
    for inner, optimum in ((False, np.sqrt(5 * 0.64)), (True, (0.5 - np.sqrt(0.05)) ** 2)):
        one, two = _ranged(True, 0.25, 0.64, inner), _ranged(False, 0.25, 0.64, inner)
        assert len(prepare(one).canon.G_ranges[0]) == 1 and len(prepare(two).canon.G_ranges[0]) == 0
        a, b = one.solve("reduced", ranged_rows=True), two.solve("reduced", ranged_rows=True)
        assert a.status.value == b.status.value == "solved" and a.certificate.passed, a.message
        assert a.upper_objective == pytest.approx(optimum, rel=1e-7)
        np.testing.assert_allclose(a.x["x"], b.x["x"], atol=1e-6)
