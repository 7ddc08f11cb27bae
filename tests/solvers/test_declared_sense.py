"""A maximized problem's per-start records, history and progress lines report the upper objective (F, or phi with
its penalty) in its declared sense, as the result does (canonical.in_sense decides the sign)."""

import re

import pytest

import bilevel as bl


def bard_max() -> bl.BilevelProblem:
    """Bard (1998) Example 5.1.1 with the leader maximizing 4y - x on a box: optimum 12 at x = y = 4."""
    p = bl.BilevelProblem("bard-max")
    x = p.upper_variable("x", lb=0, ub=10)
    y = p.lower_variable("y", lb=0)
    p.maximize_upper(4 * y - x)
    p.minimize_lower(y)
    for c in (-x - y <= -3, -2 * x + y <= 0, 2 * x + y <= 12, 3 * x - 2 * y <= 4):
        p.lower_constraint(c)
    return p


@pytest.mark.parametrize("method", ["ipopt", "relaxation", "hypergradient", "differential-evolution"])
def test_records_and_progress_are_in_the_declared_sense(method: str, capsys) -> None:
    res = bard_max().solve(method, starts=2, seed=0, verbose=True)
    assert res.upper_objective == pytest.approx(12.0, abs=1e-6)
    starts = [s["objective"] for s in res.start_records if s.get("objective") is not None]
    assert starts and max(starts) == pytest.approx(12.0, abs=1e-4), res.start_records
    history = [h["objective"] for h in res.history if h.get("objective") is not None]
    assert all(h > 0 for h in history), history  # every point of the path has 4y - x > 0 (at -12: minimization sign)
    printed = [float(v) for v in re.findall(r"\b(?:F|phi) = (-?[0-9.e+-]+)", capsys.readouterr().err)]
    assert any(abs(v - 12.0) < 1e-4 for v in printed) and min(printed) > -11.0, printed  # relaxed steps reach > 12
