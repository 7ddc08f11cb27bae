"""Method `reduced`: IPOPT over the upper variables with every upper constraint (also those on the lower solution)
kept as a constraint, y*(x) and its derivative from the engine's exact lower solve and adjoint."""

from __future__ import annotations

import casadi as ca
import numpy as np
import pytest

import bilevel as bl
from bilevel.errors import ModelError
from bilevel.problems import registry


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
