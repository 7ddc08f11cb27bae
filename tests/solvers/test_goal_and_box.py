"""The caller's goal (option callback, StopIteration), near-tie preference (option prefer) and the declared box
(BilevelProblem.set_bounds; the deprecated Prepared.rebox)."""

from __future__ import annotations

import numpy as np
import pytest

import bilevel as bl
from bilevel.solvers.engine.prepared import prepare

from .test_evolution import _wavy


@pytest.mark.parametrize("method", ["hypergradient", "differential-evolution"])
def test_callback_stops_the_method_at_the_callers_goal(method: str) -> None:
    """A callback raising StopIteration once F < 0.5 ends the run at that point: its F (declared, checked here against
    sin(3x) + 0.1 x^2 at the returned x) is below 0.5, the method saw the declared objective, and the answer is not
    `solved` (a goal, not a local minimum); where the probe finds a better point nearby, the message says the goal
    stopped the method (not "try more starts")."""
    seen = []

    def goal(point) -> None:
        seen.append(point.fun)
        assert point.fun == pytest.approx(np.sin(3 * point.y[0]) + 0.1 * point.y[0] ** 2, rel=1e-12)
        if point.fun < 0.5:
            raise StopIteration

    res = bl.solve(_wavy(1.5), method=method, callback=goal, starts=1, seed=0)
    x = float(np.ravel(res.x["x"])[0])
    assert res.upper_objective < 0.5 and res.upper_objective == pytest.approx(np.sin(3 * x) + 0.1 * x * x, abs=1e-9)
    assert seen[-1] == pytest.approx(res.upper_objective, abs=1e-9) and res.status is not bl.Status.SOLVED
    assert res.certificate.passed
    if res.status is bl.Status.NOT_LOCALLY_OPTIMAL:
        assert "callback's goal was reached" in res.message and "try more starts" not in res.message
    assert "the caller's goal" in res.message


def test_prefer_breaks_near_ties_between_starts() -> None:
    """F = (y^2 - 1)^2 on [-2, 2] has two global minima, x = -1 and x = 1: prefer(x) = x picks +1, -x picks -1."""
    p = bl.BilevelProblem("two-wells")
    x = p.upper_variable("x", lb=-2, ub=2, start=-1.5)
    y = p.lower_variable("y")
    p.minimize_lower((y - x) ** 2)
    p.minimize_upper((y ** 2 - 1) ** 2)
    p.suggest_start(x=1.5)
    for sign in (1.0, -1.0):
        res = bl.solve(p, method="hypergradient", starts=2, prefer=lambda point, s=sign: s * point.x[0])
        assert float(np.ravel(res.x["x"])[0]) == pytest.approx(sign, abs=1e-6)


def test_set_bounds_gives_every_later_solve_the_new_box() -> None:
    """After set_bounds to [0.5, 3] the wavy problem's minimum is the local one near 1.54 (the global one, -0.51, is
    cut off; checked on a 250,001-point grid of the box), and its certificate checks the new box; the preparation is
    kept (a box is not a declaration)."""
    p = _wavy(1.5)
    prep = prepare(p)
    p.set_bounds("x", 0.5, 3.0)
    res = bl.solve(p, method="hypergradient", starts=3, seed=0)
    assert prepare(p) is prep and prep.canon.x_lb[0] == 0.5 and prep.canon.x_ub[0] == 3.0
    x = float(np.ravel(res.x["x"])[0])
    grid = np.linspace(0.5, 3.0, 250_001)
    best = grid[np.argmin(np.sin(3 * grid) + 0.1 * grid ** 2)]
    assert 0.5 <= x <= 3.0 and x == pytest.approx(best, abs=1e-4) and res.certificate.upper_feasibility == 0.0
    with pytest.raises(bl.ModelError, match="lower bound exceeds its upper bound"):
        p.set_bounds("x", 1.0, 0.0)
    with pytest.raises(bl.UnknownName, match="did you mean 'x'"):
        p.set_bounds("xx", 0.0, 1.0)
    with pytest.raises(bl.ModelError, match="lower variable"):
        p.set_bounds(p.lower_variables[0].name, 0.0, 1.0)


def test_rebox_is_a_deprecated_set_bounds() -> None:
    """Prepared.rebox warns (removed in 0.2.0) and gives the problem the box by set_bounds."""
    p = _wavy(1.5)
    prep = prepare(p)
    with pytest.warns(DeprecationWarning, match="set_bounds"):
        prep.rebox(np.array([0.5]), np.array([3.0]))
    assert p.upper_variables[0].lb[0] == 0.5 and prep.canon.x_ub[0] == 3.0 and p.bounds_revision == 1
    with pytest.warns(DeprecationWarning), pytest.raises(bl.ModelError, match="lb <= ub"):
        prep.rebox(np.array([1.0]), np.array([0.0]))
