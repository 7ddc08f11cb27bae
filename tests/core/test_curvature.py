"""Convexity proofs on a box (lower/curvature.py's composition rules, convexity.py's interval PSD test): what each
proves, what each refuses, and that a proof is never wrong on sampled points (a negative second difference in y
along a random direction inside the box would refute it)."""

from __future__ import annotations

import casadi as ca
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from bilevel.lower.convexity import _interval_psd
from bilevel.lower.curvature import convex_by_rules

x, y = ca.SX.sym("x", 1), ca.SX.sym("y", 2)
X_BOX = (np.array([0.0]), np.array([2.0]))
Y_BOX = (np.array([0.0, -1.0]), np.array([3.0, 1.0]))

PROVEN = {
    "quartic of an affine form": (x + 2 * y[0] - 15) ** 4,
    "exp of an affine form": ca.exp(y[0] - x) + (x + y[1]) ** 2,
    "x-scaled square, x >= 0": (x + 1) * y[1] ** 2 / 2 - x * y[0],
    "disc row": (y[0] - 1) ** 2 + (y[1] - 1) ** 2 - 0.25,
    "reciprocal of a positive affine form": 1 / (y[0] + 1) + ca.sqrt(x + 1) * y[1],
    "negated concave": -ca.log(y[0] + 1) - ca.sqrt(y[0] + 2),
}
NOT_PROVEN = {
    "cube on a sign-changing box": y[1] ** 3,
    "log-sum-exp (convex, outside the rules)": ca.log(ca.exp(y[0]) + ca.exp(y[1])),
    "x-scaled square with x - 1 of both signs": (x - 1) * y[1] ** 2,
    "product of two lower variables": y[0] * y[1],
    "concave square root": ca.sqrt(y[0] + 1),
    "cube of a nonnegative variable, which CasADi writes y * sq(y) (the Hessian bound proves it)": 2 * y[0] ** 3,
}


@pytest.mark.parametrize("name", sorted(PROVEN))
def test_composition_rules_prove(name: str) -> None:
    assert convex_by_rules(x, y, PROVEN[name], X_BOX, Y_BOX)


@pytest.mark.parametrize("name", sorted(NOT_PROVEN))
def test_composition_rules_claim_nothing_outside_them(name: str) -> None:
    assert not convex_by_rules(x, y, NOT_PROVEN[name], X_BOX, Y_BOX)


@settings(max_examples=30, deadline=None, derandomize=True)
@given(seed=st.integers(0, 2**32 - 1))
def test_a_proof_holds_on_sampled_segments(seed: int) -> None:
    """Each proven expression is midpoint-convex in y on random segments inside the box, at random x in the box."""
    rng = np.random.default_rng(seed)
    fun = ca.Function("f", [x, y], [ca.vertcat(*PROVEN.values())])
    xs = rng.uniform(*X_BOX)
    a, b = rng.uniform(*Y_BOX), rng.uniform(*Y_BOX)
    ends = 0.5 * (np.asarray(fun(xs, a)) + np.asarray(fun(xs, b)))
    middle = np.asarray(fun(xs, 0.5 * (a + b)))
    assert np.all(middle <= ends + 1e-9 * (1 + np.abs(ends)))


def test_weyl_bound_proves_a_dense_constant_hessian_that_gershgorin_misses() -> None:
    """[[1, 0.9, 0.9], [0.9, 1, 0.9], [0.9, 0.9, 1]] has eigenvalues 0.1, 0.1, 2.8 (PD) but off-diagonal row sums
    1.8 > 1: Weyl's bound proves it, and the interval of radius 0.03 around it (||radius||_F = 0.09 < 0.1), not that
    of radius 0.04 (0.12)."""
    P = np.full((3, 3), 0.9) + 0.1 * np.eye(3)
    assert _interval_psd(P, P)
    assert _interval_psd(P - 0.03, P + 0.03)
    assert not _interval_psd(P - 0.04, P + 0.04)
    assert not _interval_psd(P - np.eye(3), P)  # a member with eigenvalue -0.9
