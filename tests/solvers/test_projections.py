"""Projections: idempotent, feasible, optimal (variational inequality, brute force) and non-expansive."""

from __future__ import annotations

import itertools

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

import bilevel as bl
from bilevel.solvers.engine.projections import Blocks, Box, NormBall, SparseNormBall

NORMS = [1, 2, np.inf]
TOL = 1e-9


@st.composite
def vectors(draw, n: int | None = None) -> np.ndarray:
    n = draw(st.integers(1, 7)) if n is None else n
    seed = draw(st.integers(0, 2**31 - 1))
    scale = draw(st.sampled_from([0.1, 1.0, 10.0]))
    return scale * np.random.default_rng(seed).standard_normal(n)


@st.composite
def convex_sets(draw) -> tuple[object, int]:
    """A norm ball (maybe off-center, maybe within a box containing its center) or a box, and a dimension."""
    n = draw(st.integers(1, 7))
    rng = np.random.default_rng(draw(st.integers(0, 2**31 - 1)))
    kind = draw(st.sampled_from(["ball", "boxed-ball", "box"]))
    center = rng.standard_normal(n)
    lb, ub = center - rng.uniform(0.0, 2.0, n), center + rng.uniform(0.0, 2.0, n)
    lb[rng.random(n) < 0.3] = -np.inf
    if kind == "box":
        return Box(lb, ub), n
    ball = NormBall(float(rng.uniform(0.1, 3.0)), draw(st.sampled_from(NORMS)), center)
    return (ball if kind == "ball" else ball.with_box(lb, ub)), n


def random_member(proj, n: int, rng: np.random.Generator) -> np.ndarray:
    """A point of the (convex) set: a random convex combination of two projected random points."""
    t = rng.random()
    return t * proj(5.0 * rng.standard_normal(n)) + (1 - t) * proj(5.0 * rng.standard_normal(n))


@settings(max_examples=300, deadline=None)
@given(convex_sets(), st.data())
def test_convex_projections_are_optimal_idempotent_and_nonexpansive(set_and_n, data) -> None:
    proj, n = set_and_n
    v, w = data.draw(vectors(n)), data.draw(vectors(n))
    rng = np.random.default_rng(data.draw(st.integers(0, 2**31 - 1)))
    p = proj(v)
    assert proj.contains(p, TOL)
    np.testing.assert_allclose(proj(p), p, atol=1e-10)
    for _ in range(5):  # variational inequality <v - P(v), z - P(v)> <= 0 for z in the set
        z = random_member(proj, n, rng)
        assert np.dot(v - p, z - p) <= 1e-9 * (1.0 + np.linalg.norm(v - p) * np.linalg.norm(z - p))
    assert np.linalg.norm(proj(v) - proj(w)) <= np.linalg.norm(v - w) + 1e-9


@pytest.mark.parametrize("norm", NORMS)
def test_norm_ball_projection_beats_sampled_feasible_points(norm: float) -> None:
    """P(v) is nearer to v than any of 20000 random points of the ball (and its boundary)."""
    rng = np.random.default_rng(1)
    ball = NormBall(1.5, norm, center=[0.5, -1.0, 2.0])
    for _ in range(20):
        v = 4.0 * rng.standard_normal(3)
        p = ball(v)
        z = rng.standard_normal((20_000, 3))
        z *= (1.5 * rng.random((20_000, 1)) ** 0.2) / np.linalg.norm(z, ord=norm, axis=1)[:, None]
        z += ball.center
        assert np.linalg.norm(v - p) <= np.linalg.norm(v - z, axis=1).min() + 1e-12


def test_l1_projection_known_values() -> None:
    ball = NormBall(1.0, 1)
    np.testing.assert_allclose(ball(np.array([3.0, 1.0, -0.5])), [1.0, 0.0, 0.0])
    np.testing.assert_allclose(ball(np.array([1.0, 1.0])), [0.5, 0.5])
    np.testing.assert_allclose(ball(np.array([0.2, -0.3])), [0.2, -0.3])
    np.testing.assert_allclose(NormBall(2.0, "inf")(np.array([3.0, -0.5])), [2.0, -0.5])


def _brute_sparse(ball: SparseNormBall, v: np.ndarray) -> float:
    """Smallest distance from v to the sparse ball over all supports of size k (exact per support)."""
    c = np.zeros_like(v) if ball.center is None else ball.center
    best = np.inf
    for support in itertools.combinations(range(v.size), int(ball.k)):
        idx = list(support)
        sub = NormBall(ball.radius, ball.norm, c[idx])
        if ball.box is not None:
            sub = sub.with_box(np.broadcast_to(ball.box.lb, v.shape)[idx], np.broadcast_to(ball.box.ub, v.shape)[idx])
        z = c.copy()
        z[idx] = sub(v[idx])
        best = min(best, float(np.linalg.norm(v - z)))
    return best


@settings(max_examples=100, deadline=None)
@given(v=vectors(), k=st.integers(0, 4), norm=st.sampled_from(NORMS), radius=st.floats(0.05, 5.0),
       centered=st.booleans())
def test_sparse_ball_is_feasible_idempotent_and_exact_without_box(v, k, norm, radius, centered) -> None:
    center = None if centered else np.linspace(-1, 1, v.size)
    ball = SparseNormBall(radius, k, norm, center)
    p = ball(v)
    c = np.zeros_like(v) if center is None else center
    assert np.count_nonzero(p != c) <= k
    assert np.linalg.norm(p - c, ord=norm) <= radius + TOL and ball.contains(p, TOL)
    np.testing.assert_allclose(ball(p), p, atol=1e-10)
    assert np.linalg.norm(v - p) <= _brute_sparse(ball, v) + 1e-9


@settings(max_examples=60, deadline=None)
@given(v=vectors(), k=st.integers(0, 4), norm=st.sampled_from(NORMS), seed=st.integers(0, 2**31 - 1))
def test_sparse_ball_with_box_is_feasible_and_exact_for_linf(v, k, norm, seed) -> None:
    rng = np.random.default_rng(seed)
    lb, ub = -rng.uniform(0.0, 1.0, v.size), rng.uniform(0.0, 1.0, v.size)
    ball = SparseNormBall(1.0, k, norm).with_box(lb, ub)
    p = ball(v)
    assert np.count_nonzero(p) <= k and ball.contains(p, TOL)
    assert np.all(p >= lb - TOL) and np.all(p <= ub + TOL)
    np.testing.assert_allclose(ball(p), p, atol=1e-10)
    if norm == np.inf:
        assert np.linalg.norm(v - p) <= _brute_sparse(ball, v) + 1e-9


def test_blocks_project_each_budget_and_the_box() -> None:
    """Data-poisoning budgets: a_u in an l2 ball, a_y in a sparse linf ball, theta free but bounded."""
    p = bl.BilevelProblem("blocks")
    p.upper_variable("a_u", 4)
    p.upper_variable("theta", 2, lb=-1, ub=1)
    p.upper_variable("a_y", (2, 2))
    layout = p.upper_layout()
    assert layout == {"a_u": slice(0, 4), "theta": slice(4, 6), "a_y": slice(6, 10)}
    proj = Blocks.for_problem(p, {"a_u": NormBall(1.0), "a_y": SparseNormBall(0.5, 2, np.inf)})
    boxed = proj.with_box(np.r_[np.full(4, -np.inf), -1, -1, np.full(4, -np.inf)],
                          np.r_[np.full(4, np.inf), 1, 1, np.full(4, np.inf)])
    v = np.array([3.0, 4.0, 0.0, 0.0, 5.0, -0.2, 0.1, -2.0, 0.3, 0.9])
    out = proj(v)
    np.testing.assert_allclose(out[:4], [0.6, 0.8, 0.0, 0.0])
    np.testing.assert_allclose(out[4:6], [5.0, -0.2])
    np.testing.assert_allclose(out[6:], [0.0, -0.5, 0.0, 0.5])
    np.testing.assert_allclose(boxed(v)[4:6], [1.0, -0.2])
    assert boxed.contains(boxed(v)) and not boxed.contains(v)
    pairs = Blocks([(slice(0, 2), Box(0, 1)), (slice(2, 4), NormBall(1.0, 1))], 4)
    np.testing.assert_allclose(pairs(np.array([2.0, -1.0, 2.0, 1.0])), [1.0, 0.0, 1.0, 0.0])


def test_invalid_sets_raise() -> None:
    with pytest.raises(bl.ModelError, match="norm"):
        NormBall(1.0, 3)
    with pytest.raises(bl.ModelError, match="does not meet the box"):
        NormBall(1.0, 2).with_box(np.array([2.0, 2.0]), np.array([3.0, 3.0]))
    with pytest.raises(bl.ModelError, match="overlaps"):
        Blocks([(slice(0, 3), Box(0, 1)), (slice(2, 4), Box(0, 1))], 4)
    with pytest.raises(bl.ModelError, match="known upper variable"):
        Blocks({"a_u": Box(0, 1)}, 4)
    with pytest.raises(bl.InvalidData, match="size 4"):
        Blocks([(slice(0, 2), Box(0, 1))], 4)(np.zeros(3))
    with pytest.raises(bl.ModelError, match="center inside the box"):
        SparseNormBall(1.0, 1, 2, center=[5.0, 5.0]).with_box(np.zeros(2), np.ones(2))


def test_blocks_on_a_slice_project_its_entries_as_the_whole_does() -> None:
    """Blocks.on(S): the entries of S projected as the whole projection projects them (one part covering S: that
    part itself; parts shifted otherwise); None where a part straddles S."""
    rng = np.random.default_rng(3)
    whole = Blocks([(slice(0, 4), NormBall(1.0)), (slice(4, 7), NormBall(0.5, np.inf)), (slice(7, 9), NormBall(2.0))],
                   9)
    ball = whole.on(slice(0, 4))
    assert isinstance(ball, NormBall) and ball.radius == 1.0
    tail = whole.on(slice(4, 10 - 1))
    for _ in range(20):
        v = 3 * rng.standard_normal(9)
        np.testing.assert_allclose(tail(v[4:9]), whole(v)[4:9], rtol=0, atol=0)
        np.testing.assert_allclose(ball(v[:4]), whole(v)[:4], rtol=0, atol=0)
    assert whole.on(slice(2, 6)) is None
