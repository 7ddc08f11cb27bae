"""Options time_limit and verbose of every method (bilevel.solvers.engine.limits), the default budget of
differential-evolution, and the default method "auto" (bilevel.solvers.registry.choose_method)."""

from __future__ import annotations

import casadi as ca
import numpy as np
import pytest

import bilevel as bl
from bilevel.problems import registry
from bilevel.solvers.engine.prepared import prepare
from bilevel.solvers.evolution import default_budget
from bilevel.defaults import defaults
from bilevel.solvers import registry as solver_registry
from bilevel.solvers.registry import choose_method

AUTO_MIN_UPPER = defaults["auto.min_upper"]


def _least_squares(n: int, seed: int = 0) -> bl.BilevelProblem:
    """Targets of a 30 x 6 least-squares fit shifted by B x, |x| <= 0.1; the attacker maximizes the fit's deviation."""
    rng = np.random.default_rng(seed)
    A, B, b = rng.standard_normal((30, 6)), rng.standard_normal((30, n)), rng.standard_normal(30)
    p = bl.BilevelProblem(f"ls{n}")
    x = p.upper_variable("x", n, lb=-0.1, ub=0.1)
    y = p.lower_variable("y", 6)
    p.minimize_lower(ca.sumsqr(ca.mtimes(ca.DM(A), y) - ca.DM(b) - ca.mtimes(ca.DM(B), x)))
    p.maximize_upper(ca.sumsqr(y))
    return p


@pytest.mark.parametrize("method", ["ipopt", "relaxation", "hypergradient", "differential-evolution", "reduced"])
def test_a_method_stopped_by_time_limit_keeps_its_best_point_and_says_so(method: str) -> None:
    """A limit that has passed before the second start (or generation) stops the method: it returns a point, its
    status is not solved, its message names the limit, and the point is bilevel feasible (certificate re-solve)."""
    res = bl.solve(_least_squares(3), method=method, starts=2, time_limit=1e-6)
    assert res.status is not bl.Status.SOLVED
    assert "time_limit = 1e-06 s reached" in res.message
    x = res.x["x"]
    assert np.all(np.isfinite(x)) and np.all(np.abs(x) <= 0.1 + 1e-9)
    assert res.certificate is not None and res.certificate.lower_feasibility <= 1e-6


def test_block_exact_stops_at_the_time_limit() -> None:
    res = bl.solve(registry.get("vrft-maxmin"), method="block-exact", starts=2, time_limit=1e-6)
    assert res.status is not bl.Status.SOLVED and "time_limit = 1e-06 s reached" in res.message


def test_a_generous_time_limit_changes_nothing() -> None:
    """The limit only stops work: well inside it, the answer is the unlimited one."""
    p = _least_squares(3)
    free, limited = bl.solve(p, method="hypergradient"), bl.solve(p, method="hypergradient", time_limit=600)
    assert limited.status is free.status is bl.Status.SOLVED
    assert limited.upper_objective == pytest.approx(free.upper_objective, rel=1e-12)


@pytest.mark.parametrize("bad", [0, -1.0, float("inf"), "5", True])
def test_time_limit_must_be_a_positive_number(bad: object) -> None:
    with pytest.raises(bl.ModelError, match="time_limit"):
        bl.solve(_least_squares(2), method="ipopt", time_limit=bad)


@pytest.mark.parametrize("method, line", [("hypergradient", "[hypergradient] start 1/1, iteration 0: phi = "),
                                          ("ipopt", "[ipopt] start 1/1: "),
                                          ("reduced", "[reduced] start 1/1: Solve_Succeeded, F = "),
                                          ("relaxation", "[relaxation] t = 1.0e+00: "),
                                          ("differential-evolution", "[differential-evolution] generation 1/3: ")])
def test_verbose_reports_progress_on_stderr(method: str, line: str, capsys) -> None:
    options = {"max_iter": 3} if method == "differential-evolution" else {}
    bl.solve(_least_squares(2), method=method, starts=1, verbose=True, **options)
    out, err = capsys.readouterr()
    assert line in err and out == ""


def test_evolution_default_budget_is_bounded_in_the_dimension() -> None:
    """scipy's 15 n members up to 64, generations sized to about 3,000 evaluations (100 up to 30 members)."""
    assert default_budget(1) == (15, 100) and default_budget(2) == (30, 100)
    assert default_budget(4) == (60, 50)
    for n in (80, 1000):
        members, generations = default_budget(n)
        assert (members, generations) == (64, 46) and members * (generations + 1) <= 3100


@pytest.fixture
def local_rule(monkeypatch) -> None:
    """auto without its global-first step (auto.global_size 0): the local rule alone."""
    monkeypatch.setitem(bl.defaults, "auto.global_size", 0)


def test_auto_takes_hypergradient_on_a_least_squares_lower_level_with_many_upper_entries(local_rule) -> None:
    """From AUTO_MIN_UPPER upper entries on; the result names the method that ran and why, and equals that method's
    own result."""
    p = _least_squares(AUTO_MIN_UPPER)
    res = p.solve()
    assert res.method == "hypergradient" and res.stats["auto"]["method"] == "hypergradient"
    assert res.message.startswith("auto: hypergradient, for a least-squares lower level")
    direct = bl.solve(_least_squares(AUTO_MIN_UPPER), method="hypergradient")
    assert res.upper_objective == pytest.approx(direct.upper_objective, rel=1e-12)
    assert choose_method(prepare(_least_squares(AUTO_MIN_UPPER - 1)), {})[0] == "ipopt"


def test_auto_takes_ipopt_on_constrained_lower_levels_and_follows_the_options(local_rule) -> None:
    """A textbook LP lower level: ipopt, as its literature optimum confirms; an option only one method takes
    decides for it."""
    p = registry.get("bard1998-ex5.1.1")
    res = p.solve()
    assert res.method == "ipopt" and "whose solution depends on x" in res.message
    assert res.upper_objective == pytest.approx(registry.spec("bard1998-ex5.1.1").optimum, abs=1e-6)
    ls = prepare(_least_squares(AUTO_MIN_UPPER))
    assert choose_method(ls, {"mode": bl.Scholtes(1e-9)}) == ("ipopt", "option(s) mode belong to ipopt")
    assert choose_method(prepare(registry.get("macmpec-bard1")), {"exact_block": False})[0] == "hypergradient"


def test_auto_takes_reduced_where_an_upper_constraint_reads_a_least_squares_solution(local_rule) -> None:
    """y*(x) = x (least squares, 20 upper entries) and the leader maximizes sum(y) subject to ||y||^2 <= 1 on the
    learner's solution: hypergradient could only penalize that row, so auto runs reduced, which keeps it and reaches
    the optimum y = x = 1/sqrt(20) (all entries), F* = sqrt(20) (Cauchy-Schwarz); an ipopt-only option, or a QP lower
    level, keeps ipopt."""
    n = AUTO_MIN_UPPER
    p = bl.BilevelProblem("coupled")
    x = p.upper_variable("x", n, lb=-1, ub=1)
    y = p.lower_variable("y", n)
    p.minimize_lower(ca.sumsqr(y - x))
    p.maximize_upper(ca.sum1(y))
    p.upper_constraint(ca.sumsqr(y) <= 1)
    assert choose_method(prepare(p), {})[0] == "reduced"
    assert choose_method(prepare(p), {"mode": bl.Scholtes(1e-9)})[0] == "ipopt"
    assert choose_method(prepare(registry.get("macmpec-ex9.2.2")), {})[0] == "ipopt"
    res = p.solve()
    assert res.method == "reduced" and "1 upper constraint(s) on the solution of a least-squares" in res.message
    assert res.status.value == "solved" and res.certificate.passed, res.message
    assert res.upper_objective == pytest.approx(np.sqrt(n), rel=1e-6)
    np.testing.assert_allclose(res.x["x"], np.full(n, 1 / np.sqrt(n)), atol=1e-5)


@pytest.mark.parametrize("name", ["bolib-lucchettietal1987", "macmpec-bilin", "bard1998-ex5.1.1",
                                  "bolib-floudaszlobec1998"])
def test_auto_proves_small_problems_in_globals_class_first(name: str) -> None:
    """auto runs global first on a small problem in its class and returns its proven optimum: the local rule's
    ipopt stopped at 0.5 on bolib-lucchettietal1987 (F* = 0, Lucchetti et al. 1987) and at 16 on macmpec-bilin
    (F* = 18.4, Hansen et al. 1992); bard1998-ex5.1.1 has F* = -12 (Bard 1998); bolib-floudaszlobec1998, a convex-NLP
    lower level, has F* = 1 (Floudas & Zlobec 1998)."""
    res = registry.get(name).solve()
    assert res.method == "global" and res.status is bl.Status.SOLVED, res.message
    assert res.message.startswith("auto: global, for a ") and res.certificate.global_bound.proven
    assert res.upper_objective == pytest.approx(registry.spec(name).optimum, abs=1e-6)


def test_auto_falls_back_to_the_local_rule_and_says_what_global_did(monkeypatch) -> None:
    """A global search that cannot finish in auto's budget hands over to the local rule, which the message names
    with what global ended with; a problem outside global's class (a nonlinear lower level without pyscipopt) goes to
    the local rule directly."""
    monkeypatch.setitem(bl.defaults, "global.node_limit", 1)
    res = registry.get("macmpec-bilin").solve()
    assert res.method == "ipopt" and "global ended max_iterations within" in res.message
    assert res.stats["auto"]["global_first"].startswith("global ended max_iterations")
    monkeypatch.setattr(solver_registry, "scip_available", lambda: False)  # a convex-NLP lower level: outside
    res = registry.get("bolib-floudaszlobec1998").solve()
    assert res.method == "ipopt" and "global_first" not in res.stats["auto"]


def test_a_result_says_when_its_starts_ended_at_different_local_answers() -> None:
    """macmpec-bilin (F* = 18.4, Hansen et al. 1992) has several local maxima for ipopt's starts (16, 14.6, 5.6, ...):
    the message says how far apart the starts ended and suggests more starts; on macmpec-ex9.2.6 (De Silva's
    projection, F* = -1) every start reaches the optimum and the message says nothing of a spread, nor on
    bard1998-ex7.2.2, whose starts differ only by 3e-11 around F* = 0."""
    res = bl.solve(registry.get("macmpec-bilin"), method="ipopt", starts=8, seed=0)
    spread = res.stats["starts_spread"]
    assert spread["starts"] == 8 and 1 <= spread["reached_best"] < 8
    assert spread["best"] == pytest.approx(res.upper_objective, rel=1e-6) and spread["worst"] < spread["best"]
    assert "feasible starts ended apart" in res.message and "starts=32" in res.message
    for name in ("macmpec-ex9.2.6", "bard1998-ex7.2.2"):
        agree = bl.solve(registry.get(name), method="ipopt", starts=8, seed=0)
        assert "starts_spread" not in agree.stats and "ended apart" not in agree.message, name
