"""Issue "Honest answers II", items 4 and 5: no `solved` at a point that is not a local optimum of the optimistic
bilevel problem.

Item 4: a lower level with a non-unique solution set, where the method's lower selection is not the optimistic
one (bilevel.solvers.verdict.optimistic). Item 5: a point at a kink of y*(x), where the upper objective decreases along
the kink in a direction no random probe finds (bilevel.solvers.verdict.probe: +/- coordinates and the adjacent pieces'
descent directions).
"""

from __future__ import annotations

import casadi as ca
import numpy as np
import pytest

import bilevel as bl
from bilevel.problems import registry
from bilevel.result import Status
from bilevel.solvers.engine.prepared import MethodRun, prepare
from bilevel.solvers.verdict.finalize import finalize
from bilevel.solvers.verdict.probe import improving_neighbour


def face() -> bl.BilevelProblem:
    """y in [0, 1]^2, follower min y0 + y1 s.t. y0 + y1 >= x: every y on that face is optimal. The leader
    (min -y0) wants y = (x, 0): optimistic optimum F* = -1 at x = 1; the face's midpoint gives -x/2."""
    p = bl.BilevelProblem("face")
    x = p.upper_variable("x", lb=0, ub=1)
    y = p.lower_variable("y", 2, lb=0, ub=1)
    p.minimize_upper(-y[0])
    p.minimize_lower(y[0] + y[1])
    p.lower_constraint(y[0] + y[1] >= x)
    return p


def ridge(K: float = 100.0) -> bl.BilevelProblem:
    """y*(x) = |x0 - x1| (an LP whose two vertices tie on the diagonal), F = K y - x0 on [0, 1]^2: F* = -1 at
    (1, 1), reached along the kink x0 = x1 where F = -x0; off it F grows like (K - 1) |x0 - x1|. From (0.5, 0.5)
    the generalized gradient (-1, 0) is no descent direction and F decreases only in a cone of half-angle ~1/K."""
    p = bl.BilevelProblem("ridge")
    x = p.upper_variable("x", 2, lb=0, ub=1, start=[0.5, 0.5])
    y = p.lower_variable("y")
    p.minimize_upper(K * y - x[0])
    p.minimize_lower(y)
    p.lower_constraint(y >= x[0] - x[1])
    p.lower_constraint(y >= x[1] - x[0])
    return p


def tie(K: float = 100.0) -> bl.BilevelProblem:
    """Follower min (x0 - x1) y on [0, 1]: vertex y = 1 for x0 < x1, y = 0 for x0 > x1, and at the tie x0 = x1
    every y (the solver's is the edge's midpoint). F = K (x1 - x0)(2y - 1) - x0 = K |x0 - x1| - x0 off the tie,
    -x0 on it for every y: F* = -1 at (1, 1)."""
    p = bl.BilevelProblem("tie")
    x = p.upper_variable("x", 2, lb=0, ub=1)
    y = p.lower_variable("y", lb=0, ub=1)
    p.minimize_upper(K * (x[1] - x[0]) * (2 * y - 1) - x[0])
    p.minimize_lower((x[0] - x[1]) * y)
    return p


def axis_kink() -> bl.BilevelProblem:
    """F = 100 |x0 - 0.5| + x0 - x1 + y^2, y*(x) = x0 - 0.5 (smooth; the kink is F's own), on [0, 1]^2: F* = -0.5
    at (0.5, 1)."""
    p = bl.BilevelProblem("axis-kink")
    x = p.upper_variable("x", 2, lb=0, ub=1)
    y = p.lower_variable("y")
    p.minimize_upper(100 * ca.fabs(x[0] - 0.5) + x[0] - x[1] + y ** 2)
    p.minimize_lower((y - x[0] + 0.5) ** 2)
    return p


def test_non_optimistic_selection_is_not_solved() -> None:
    """Item 4's reproducer: hypergradient's lower solver takes the face's midpoint, F = -0.5 at x = 1."""
    res = face().solve(method="hypergradient")
    assert res.status is Status.NOT_LOCALLY_OPTIMAL
    assert res.upper_objective == pytest.approx(-0.5, abs=1e-6)
    assert "optimistic" in res.message
    assert res.stats["optimistic"]["objective"] == pytest.approx(-1.0, abs=1e-6)
    assert res.stats["optimistic"]["y"] == pytest.approx([1.0, 0.0], abs=1e-6)


def test_optimistic_selection_is_solved() -> None:
    """IPOPT on the KKT reformulation picks y = (1, 0) itself: the check confirms it and keeps SOLVED."""
    res = face().solve(method="ipopt")
    assert res.status is Status.SOLVED
    assert res.upper_objective == pytest.approx(-1.0, abs=1e-6)
    assert res.stats["optimistic"]["objective"] == pytest.approx(-1.0, abs=1e-6)


def test_literature_ambiguous_lp_non_optimistic_point() -> None:
    """Bard (1998), Practical Bilevel Optimization, ex. 9.1.5 (MacMPEC ex9.1.5; F* = -1 at x = 0 with the optimistic
    y = (0, 1)): at x = 0 the follower's solutions are y1 + y2 = 1; the independent lower solve's midpoint
    y = (0.5, 0.5) gives F = 4.5, and that point, certified, must not be reported solved."""
    spec = registry.spec("macmpec-ex9.1.5")
    assert spec.optimum == -1.0
    prep = prepare(registry.get("macmpec-ex9.1.5"))
    point = prep.lower_point(np.array([0.0]))
    assert point.y == pytest.approx([0.5, 0.5], abs=1e-6)
    res = finalize(prep, MethodRun(prep.pack(point), Status.SOLVED, "given point"), "given", 0.0)
    assert res.certificate.passed and res.certificate.lower_unique is False
    assert res.status is Status.NOT_LOCALLY_OPTIMAL
    assert res.upper_objective == pytest.approx(4.5, abs=1e-6)
    assert res.stats["optimistic"]["objective"] == pytest.approx(spec.optimum, abs=1e-6)


def test_literature_ambiguous_lp_solved_at_optimum() -> None:
    """The same problem's methods still reach F* = -1 and are reported solved (no false alarm)."""
    res = registry.get("macmpec-ex9.1.5").solve(method="ipopt")
    assert res.status is Status.SOLVED
    assert res.upper_objective == pytest.approx(-1.0, abs=1e-6)


def test_probe_follows_the_kink() -> None:
    """Item 5: hypergradient stops at (0.5, 0.5) where the two vertices tie; the adjacent pieces' steepest descent
    direction (1, 1) finds F = -0.5 - 0.1/sqrt(2) at radius 0.1 on the kink."""
    res = ridge().solve(method="hypergradient", starts=1)
    assert res.x["x"] == pytest.approx([0.5, 0.5], abs=1e-6)
    assert res.status is Status.NOT_LOCALLY_OPTIMAL
    probe = res.stats["probe"]
    assert probe["x"][0] == pytest.approx(probe["x"][1], abs=1e-9)
    assert probe["objective"] == pytest.approx(-0.5 - 0.1 / np.sqrt(2.0), abs=1e-6)
    best = ridge().solve(method="ipopt", starts=1)
    assert best.status is Status.SOLVED and best.upper_objective == pytest.approx(-1.0, abs=1e-6)


def test_probe_follows_a_tie_between_vertices() -> None:
    """At (0.5, 0.5) the lower solution is an edge (not unique, not degenerate): the kink shows as the different
    active sets of the samples next to x, and the pieces' steepest descent direction follows the tie."""
    prep = prepare(tie())
    better = improving_neighbour(prep, np.array([0.5, 0.5]), -0.5, prep.projection, optimistic=True)
    assert better is not None
    assert better.x == pytest.approx([0.5 + 0.1 / np.sqrt(2.0)] * 2, abs=1e-9)
    assert better.objective == pytest.approx(-0.5 - 0.1 / np.sqrt(2.0), abs=1e-6)


def test_probe_passes_a_kink_minimum() -> None:
    """At kinks that are local minima no neighbour is better, F taken optimistically: the ridge's and the tie's
    optimum (1, 1), F = -1, and axis_kink's (0.5, 1), F = -0.5 (a kink in x0, the bound in x1)."""
    for problem, x, F in ((ridge(), [1.0, 1.0], -1.0), (tie(), [1.0, 1.0], -1.0), (axis_kink(), [0.5, 1.0], -0.5)):
        prep = prepare(problem)
        assert improving_neighbour(prep, np.array(x), F, prep.projection, optimistic=True) is None


def test_probe_tries_each_coordinate() -> None:
    """axis_kink at (0.5, 0.5), F = 0: the gradient there is (1, -1), no descent direction; F decreases only within
    ~1/100 rad of +x1, which the coordinate direction finds."""
    prep = prepare(axis_kink())
    better = improving_neighbour(prep, np.array([0.5, 0.5]), 0.0, prep.projection)
    assert better is not None
    assert better.x == pytest.approx([0.5, 0.6], abs=1e-12)
    assert better.objective == pytest.approx(-0.1, abs=1e-9)


def test_a_first_order_direction_is_judged_by_its_own_tolerance() -> None:
    """A neighbour along a first-order direction only (axis_kink's +x1 coordinate, 0.1 better) is judged by
    probe.descent_rel_tol even where that is the looser of the two tolerances: 0.1 passes a bar of 0.05, while random
    directions need 0.5 and find nothing."""
    from bilevel.defaults import reset_defaults, set_defaults

    prep = prepare(axis_kink())
    try:
        set_defaults("probe", rel_tol=0.5, descent_rel_tol=0.05)
        better = improving_neighbour(prep, np.array([0.5, 0.5]), 0.0, prep.projection)
        set_defaults("probe", descent_rel_tol=0.5)
        assert improving_neighbour(prep, np.array([0.5, 0.5]), 0.0, prep.projection) is None
    finally:
        reset_defaults()
    assert better is not None and better.x == pytest.approx([0.5, 0.6], abs=1e-12)
