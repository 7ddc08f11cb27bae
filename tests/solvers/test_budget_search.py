"""The budget search (bilevel.attacks.budget_search): path, then bisection, on monotone goals with a known threshold."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings, strategies as st

from bilevel.errors import ModelError
from bilevel.attacks.budget_search import smallest_budget


@settings(max_examples=60, deadline=None)
@given(threshold=st.floats(1e-3, 2.0), rel_tol=st.floats(1e-3, 0.2),
       path=st.lists(st.floats(1e-3, 2.0), min_size=1, max_size=6, unique=True).map(sorted))
def test_the_search_brackets_the_threshold_of_a_monotone_goal(threshold: float, rel_tol: float,
                                                             path: list[float]) -> None:
    """Goal reached iff budget >= threshold: the answer reaches it and lies within rel_tol of the threshold; inf
    exactly when the path stops short; the runs record every budget tried with its outcome."""
    found = smallest_budget(lambda d: d, lambda d: d >= threshold, path, rel_tol)
    if path[-1] < threshold:
        assert found.delta == np.inf and [d for d, _ in found.runs] == path
        return
    assert threshold <= found.delta <= threshold / (1 - rel_tol) + 1e-12
    assert all(d == v for d, v in found.runs) and found.delta in [d for d, _ in found.runs]


def test_bad_paths_and_tolerances_are_refused() -> None:
    with pytest.raises(ModelError, match="increasing and positive"):
        smallest_budget(lambda d: d, lambda v: v >= 1, (0.3, 0.1))
    with pytest.raises(ModelError, match="increasing and positive"):
        smallest_budget(lambda d: d, lambda v: v >= 1, ())
    with pytest.raises(ModelError, match="rel_tol"):
        smallest_budget(lambda d: d, lambda v: v >= 1, (1.0,), rel_tol=0.0)
