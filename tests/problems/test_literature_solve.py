"""Every registered textbook problem solved to its published optimum (1e-4 relative) with a passing certificate.

Sources and brute-force confirmation of each optimum: bilevel/problems/literature*.py and
tests/problems/test_literature_data.py.
"""

from __future__ import annotations

import pytest

import bilevel as bl
from bilevel.experiments.compare import relative_gap
from bilevel.problems import registry

TEXTBOOK = registry.names("textbook")

HYPERGRADIENT_MISSES = {
    "macmpec-ex9.1.1": "non-unique lower solution: the optimistic choice is not what the lower solver returns",
    "macmpec-bilin": "LP lower level: piecewise-constant hypergradient stalls at the local value 16 (F* = 18.4)",
    "bolib-lucchettietal1987": "F* = 0 only at x = 1 under the optimistic tie; descent stops at F = 0.5",
    "bolib-tollsettingp4": "LP lower level: stops at the local revenue 2.5 (one commodity tolled; F* = 4)",
}
"""Where projected hypergradient descent does not reach the published optimum (see docs/solvers.md)."""

SLOW_FOR_HYPERGRADIENT = {"macmpec-bard2"}  # reaches 6599.7 (gap 4.6e-5) but needs ~100 s
SLOW_FOR_RELAXATION = {"bolib-tollsettingp1"}  # reaches 7.0000002 (inaccurate) but needs ~250 s with 8 starts


def _check(name: str, method: str, **options) -> None:
    res = bl.solve(registry.get(name), method=method, seed=0, **options)
    known = registry.spec(name).optimum
    assert res.certificate is not None and res.certificate.passed, (res.status, res.message)
    assert res.status in (bl.Status.SOLVED, bl.Status.INACCURATE)
    assert relative_gap(res.upper_objective, known) <= 1e-4, (res.upper_objective, known)


def test_at_least_fifteen_textbook_problems_are_registered() -> None:
    assert len(TEXTBOOK) >= 15
    tags = {t for n in TEXTBOOK for t in registry.spec(n).tags}
    assert {"linear-linear", "quadratic-quadratic", "nonunique-lower", "max-lower", "equality"} <= tags


@pytest.mark.parametrize("name", [n for n in TEXTBOOK if n not in SLOW_FOR_RELAXATION])
def test_relaxation_reaches_published_optimum(name: str) -> None:
    _check(name, "relaxation", starts=8)


@pytest.mark.slow
def test_relaxation_tollsettingp1_slow() -> None:
    _check("bolib-tollsettingp1", "relaxation", starts=8)


IPOPT_MISSES = {
    "macmpec-bilin": "IPOPT's 8 starts end at the local value 16 (see docs/solvers.md)",
    "bolib-lucchettietal1987": "F* = 0 only at x = 1 under the optimistic tie; the 8 starts end at F = 0.5",
}
"""Where IPOPT does not reach the published optimum (method 'global' proves both)."""


@pytest.mark.parametrize("name", [n for n in TEXTBOOK if n not in IPOPT_MISSES])
def test_ipopt_reaches_published_optimum(name: str) -> None:
    _check(name, "ipopt", starts=8)


@pytest.mark.parametrize("name", [n for n in TEXTBOOK if n not in HYPERGRADIENT_MISSES.keys() | SLOW_FOR_HYPERGRADIENT])
def test_hypergradient_reaches_published_optimum(name: str) -> None:
    _check(name, "hypergradient", starts=8)


@pytest.mark.slow
def test_hypergradient_bard2_slow() -> None:
    _check("macmpec-bard2", "hypergradient", starts=8)
