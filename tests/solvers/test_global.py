"""method="global": proven optima on the textbook problems, agreement with active-set enumeration on random
linear bilevel programs, derived big-M on a problem with large multipliers, limits, and scope errors.

Known optima and their sources: bilevel/problems/literature*.py (confirmed by brute force in
tests/problems/test_literature_data.py).
"""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

import bilevel as bl
from bilevel.experiments.compare import relative_gap
from bilevel.problems import registry
from bilevel.problems.random_linear import build_linear_bilevel, random_linear_data
from bilevel.solvers.globalopt import method as global_method
from bilevel.solvers.engine.prepared import prepare
from bilevel.solvers.globalopt.bigm import BigM, derive_big_m
from bilevel.solvers.globalopt.form import linear_mpcc
from bilevel.solvers.globalopt.milp import solve_milp
from bilevel.solvers.globalopt.nodes import Relaxation

from .active_sets import active_set_optimum

NONCONVEX_LEADER = {"bolib-hendersonquandt1958", "macmpec-ex9.2.8", "macmpec-bard3", *registry.names("bilinear"),
                    *registry.names("polynomial")}
"""Textbook problems with a nonconvex leader: algorithm "scip" (tests/solvers/test_global_scip.py)."""

NONLINEAR_LOWER = {*registry.names("nonlinear-convex"), *registry.names("x-matrix")}
"""Textbook problems with a convex NLP lower level or an x-dependent lower constraint matrix: algorithm "scip" with
Slater bounds on the multipliers (tests/solvers/test_global_nlp.py)."""

TEXTBOOK = registry.names("textbook")
IN_SCOPE = [n for n in TEXTBOOK if n not in NONCONVEX_LEADER | NONLINEAR_LOWER]
GAP = 1e-6


def _check_proven(res: bl.BilevelResult, known: float) -> None:
    gb = res.certificate.global_bound
    assert res.status is bl.Status.SOLVED, res.message
    assert res.certificate.passed and gb is not None and gb.proven
    assert gb.gap <= GAP
    assert relative_gap(res.upper_objective, known) <= GAP, (res.upper_objective, known)
    slack = GAP * max(1.0, abs(known))
    assert gb.lower_bound - slack <= known <= gb.upper_bound + slack, (gb, known)


@pytest.mark.parametrize("name", IN_SCOPE)
def test_textbook_optimum_proven(name: str) -> None:
    res = bl.solve(registry.get(name), method="global")
    _check_proven(res, registry.spec(name).optimum)


def test_scope_covers_bilin_and_nonunique_lower_levels() -> None:
    """The brief's named cases are in scope: macmpec-bilin (18.4) and the non-unique-lower problems with LP lower
    levels (ex9.1.1, ex9.1.5, ex9.2.9), where the global value is the optimistic one."""
    nonunique = set(registry.names("nonunique-lower"))
    assert "macmpec-bilin" in IN_SCOPE
    assert {"macmpec-ex9.1.1", "macmpec-ex9.1.5", "macmpec-ex9.2.9"} <= nonunique & set(IN_SCOPE)


def test_a_nonlinear_lower_level_without_scip_says_why_and_what_to_use(monkeypatch) -> None:
    monkeypatch.setattr(global_method, "scip_available", lambda: False)
    with pytest.raises(bl.ModelError, match="kind 'nlp'.*class: nonlinear lower level.*pip install pyscipopt") as err:
        bl.solve(registry.get("bolib-floudaszlobec1998"), method="global")
    assert "relaxation" in str(err.value)


@settings(max_examples=25, deadline=None)
@given(seed=st.integers(0, 2**32 - 1), n_x=st.integers(1, 2), n_y=st.integers(1, 2), m=st.integers(1, 3),
       coupled=st.booleans())
def test_random_lp_lp_matches_active_set_enumeration(seed: int, n_x: int, n_y: int, m: int, coupled: bool) -> None:
    data = random_linear_data(np.random.default_rng(seed), n_x, n_y, m, coupled_cost=coupled)
    brute = active_set_optimum(data)
    res = bl.solve(build_linear_bilevel(data), method="global")
    assert np.isfinite(brute)  # x = 0, y = 0 is lower-feasible (b > 0), so the problem is feasible
    _check_proven(res, brute)


@settings(max_examples=8, deadline=None)
@given(seed=st.integers(0, 2**32 - 1), n_y=st.integers(1, 2), m=st.integers(1, 3))
def test_random_quadratic_upper_matches_active_set_enumeration(seed: int, n_y: int, m: int) -> None:
    data = random_linear_data(np.random.default_rng(seed), 2, n_y, m, quadratic_upper=True)
    brute = active_set_optimum(data)
    res = bl.solve(build_linear_bilevel(data), method="global")
    assert np.isfinite(brute)  # x = 0, y = 0 is lower-feasible (b > 0), so the problem is feasible
    assert res.stats["algorithm"].startswith("branch-and-bound")
    gb = res.certificate.global_bound
    assert res.status is bl.Status.SOLVED and gb.proven
    assert abs(res.upper_objective - brute) <= 1e-6 * max(1.0, abs(brute))  # Clarabel on both sides


def large_multiplier_problem(eps: float = 1e-4) -> bl.BilevelProblem:
    """min 2e4 x - y, x in [0, 1], y >= -1; y in argmin -y s.t. eps y <= x, y <= 10.

    y*(x) = min(x / eps, 10), so F = 1e4 x on [0, 1e-3] and 2e4 x - 10 beyond: F* = 0 at x = y = 0, where the
    active constraint's multiplier is 1 / eps = 1e4. Any big-M below 1e4 on it removes that branch and leaves
    F = 10 (x = 1e-3, y = 10).
    """
    p = bl.BilevelProblem("large-multipliers")
    x = p.upper_variable("x", 1, lb=0, ub=1)
    y = p.lower_variable("y", 1)
    p.minimize_upper(2e4 * x - y)
    p.upper_constraint(y >= -1)
    p.minimize_lower(-y)
    p.lower_constraint(eps * y <= x, name="scaled")
    p.lower_constraint(y <= 10, name="cap")
    return p


def test_large_multipliers_derived_big_m_keeps_the_optimum() -> None:
    res = bl.solve(large_multiplier_problem(), method="global")
    _check_proven(res, 0.0)
    assert res.stats["algorithm"].startswith("milp")
    assert res.multipliers["scaled"][0] == pytest.approx(1e4, rel=1e-6)
    assert res.stats["big_m_multiplier"][0] >= 1e4  # derived bound covers the optimum's multiplier
    assert any("scaled[0]: slack <=" in line for line in res.certificate.global_bound.big_m)


def test_large_multipliers_a_guessed_big_m_cuts_the_optimum() -> None:
    """The same MILP with the multiplier bound guessed at 1e3 returns 10, not 0: the derivation is what matters."""
    form = linear_mpcc(prepare(large_multiplier_problem()))
    relax = Relaxation(form)
    derived = derive_big_m(relax)
    guessed = BigM(derived.slack, np.minimum(derived.multiplier, 1e3), derived.labels, derived.fixed)
    assert solve_milp(relax, derived, GAP, 30.0, 1000).upper == pytest.approx(0.0, abs=1e-9)
    assert solve_milp(relax, guessed, GAP, 30.0, 1000).upper == pytest.approx(10.0, abs=1e-6)


def test_bounds_in_the_declared_sense_for_a_maximized_upper_level() -> None:
    res = bl.solve(registry.get("macmpec-bilin"), method="global")
    gb = res.certificate.global_bound
    assert gb.lower_bound == pytest.approx(18.4) and gb.upper_bound == pytest.approx(18.4)
    assert res.to_dict()["certificate"]["global_bound"]["proven"] is True


def test_node_limit_gives_max_iterations_with_valid_bounds() -> None:
    res = bl.solve(registry.get("macmpec-bilin"), method="global", node_limit=2)
    gb = res.certificate.global_bound if res.certificate else None
    assert res.status is bl.Status.MAX_ITERATIONS, res.message
    assert "node_limit" in res.message and "bounds" in res.message
    assert gb is not None and not gb.proven
    assert res.stats["lower_bound"] <= 18.4 + 1e-9 <= res.stats["upper_bound"] + 2e-9


def test_time_limit_gives_max_iterations() -> None:
    data = random_linear_data(np.random.default_rng(3), 3, 8, 12)
    res = bl.solve(build_linear_bilevel(data), method="global", time_limit=0.05)
    assert res.status is bl.Status.MAX_ITERATIONS, res.message
    assert "time_limit" in res.message


def test_infeasible_problem_is_reported() -> None:
    p = bl.BilevelProblem("infeasible")
    x = p.upper_variable("x", 1, lb=0, ub=1)
    y = p.lower_variable("y", 1)
    p.minimize_upper(x + y)
    p.upper_constraint(y <= -1)
    p.minimize_lower(y)
    p.lower_constraint(y >= x)
    assert bl.solve(p, method="global").status is bl.Status.INFEASIBLE


def test_options_are_checked() -> None:
    problem = registry.get("macmpec-bilin")
    with pytest.raises(bl.UnknownOption, match="time_limit"):
        bl.solve(problem, method="global", timelimit=1)
    with pytest.raises(bl.ModelError, match="algorithm"):
        bl.solve(problem, method="global", algorithm="cplex")
    with pytest.raises(bl.ModelError, match="finite derived big-M"):
        bl.solve(problem, method="global", algorithm="milp")


def test_compare_runs_global_and_marks_problems_outside_its_scope(tmp_path, monkeypatch) -> None:
    from bilevel.experiments.compare import NOT_APPLICABLE, compare, markdown_table

    monkeypatch.setattr(global_method, "scip_available", lambda: False)  # a convex NLP lower level is then refused
    assert "global" in bl.METHODS  # `bilevel compare` iterates over METHODS
    rows = compare(["macmpec-bilin", "bolib-floudaszlobec1998"], ["global"], str(tmp_path / "c.csv"), progress=None)
    assert rows[0].reached and rows[1].status == NOT_APPLICABLE
    summary = "reached (1e-4 relative, certified) on 1/1 (100%); solved and certified 1/1; not applicable to 1"
    assert summary in markdown_table(rows)
    again = compare(["macmpec-bilin", "bolib-floudaszlobec1998"], ["global"], str(tmp_path / "c.csv"), progress=None)
    assert [r.status for r in again] == [r.status for r in rows]  # rows read back from the CSV (resume)


def test_sides_forced_over_the_relaxed_polyhedron_are_fixed_and_justified() -> None:
    """bard2: the resource rows and x <= (10, 5, 15, 20) keep y <= (8.33, 14.3, 33.3, 21.4) on R, below the
    bounds (20, 20, 40, 40), so y <= ub never binds: those multipliers are fixed to 0 and reported as forced."""
    res = bl.solve(registry.get("macmpec-bard2"), method="global")
    assert res.stats["fixed_by_lp"] == {f"y.ub[{i}]": "H = 0" for i in range(4)}
    assert np.abs(res.multipliers["y.ub"]).max() <= 1e-12
    lines = [line for line in res.certificate.global_bound.big_m if line.startswith("y.ub")]
    assert len(lines) == 4 and all("multiplier = 0" in line for line in lines)


def test_stopped_before_an_incumbent_the_certificate_still_carries_the_bounds() -> None:
    """SCIP stopped at its first node on macmpec-bard3 (F* = -12.6787, Bard 1998) has no incumbent: the result has no
    point, and its certificate (failed on "point") still holds the proven bound, as docs/solvers.md says (issue 47)."""
    pytest.importorskip("pyscipopt")
    res = bl.solve(registry.get("macmpec-bard3"), method="global", algorithm="scip", node_limit=1)
    assert res.status is bl.Status.MAX_ITERATIONS and not res.x, res.message
    cert = res.certificate
    assert not cert.passed and cert.failed == ("point",) and "no incumbent" in cert.note
    assert not cert.global_bound.proven and cert.global_bound.lower_bound <= -12.6787 + 1e-4
    again = bl.BilevelResult.from_dict(res.to_dict())
    assert again.certificate.global_bound.lower_bound == cert.global_bound.lower_bound
