"""The one projected ascent loop (bilevel.solvers.engine.ascent) on a box: both Barzilai-Borwein rules and the stop
hook."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import example, given, settings
from hypothesis import strategies as st

from bilevel.solvers.engine.ascent import budget_direction, projected_ascent
from bilevel.solvers.engine.projections import Box


def _separable(c: np.ndarray, mu: np.ndarray):
    """f(x) = c'x - sum(mu x^2) / 2, maximized over a box at clip(c / mu, lb, ub) (separable, strictly concave)."""
    f = lambda x: (float(c @ x - 0.5 * (mu * x) @ x), x)  # noqa: E731
    return f, lambda x: c - mu * x


@settings(max_examples=40, deadline=None, derandomize=True)
@given(st.integers(0, 10**6), st.sampled_from(["short", "long"]))
@example(23477, "long")
@example(2569, "short")
@example(1306, "short")
@example(303, "long")
def test_box_maximizer_is_reached_by_either_step_rule(seed: int, bb: str) -> None:
    """Some coordinates end on a face of the box, some inside: x* = clip(c / mu, -b, b) coordinate by coordinate.
    The explicit examples are the ill-conditioned boxes (curvature ratio up to 4000 in budget units) on which the loop
    converges slowest; which of them reach a given distance from x* in a given number of steps depends on the last bits
    of the BLAS kernel, so the bounds below are the loop's accuracy, not a rounding coin-flip: see _box_run."""
    _box_run(seed, bb)


def _box_run(seed: int, bb: str) -> None:
    """The box instance of `seed` solved from a random start with step rule bb, checked against its maximizer.

    The window tolerance 1e-12 sits far above the rounding of f (~1e-16 relative), so where the loop stops does not
    depend on the kernel's last bits. Measured over seeds 0-2999 x both rules under OpenBLAS's SkylakeX and Haswell
    kernels (2026-11-24): all 6,000 runs converge within 531 steps, relative gap to f* at most 1.44e-10, distance to x*
    at most 1.5e-4 * max(b); the bounds below keep a margin of 4x or more over those worst cases."""
    rng = np.random.default_rng(seed)
    n = 30
    b, mu = rng.uniform(0.1, 2.0, n), rng.uniform(0.5, 5.0, n)
    c = mu * b * rng.uniform(-3.0, 3.0, n)  # |c / mu| > b on about two thirds of the coordinates
    f, grad = _separable(c, mu)

    def direction(x: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        g = grad(x)
        return g, b * budget_direction(b * g, 1.0, np.inf)

    x, fx, _, it, _, converged = projected_ascent(f, direction, Box(-b, b), rng.uniform(-b, b), b, 2000, 1e-12, [],
                                                  bb=bb)
    x_star = np.clip(c / mu, -b, b)
    f_star = f(x_star)[0]
    assert converged and it < 2000
    assert f_star - fx <= 1e-9 * (1.0 + abs(f_star))
    np.testing.assert_allclose(x, x_star, rtol=0, atol=1e-3 * b.max())
    assert np.all(np.abs(x) <= b)


def test_long_steps_reach_a_vertex_and_stop_where_the_projection_holds_still() -> None:
    """A linear objective on a box: the maximizer is the vertex sign(c) * b, and once there the projected step is
    zero, so the loop stops at once instead of waiting for the gain window."""
    rng = np.random.default_rng(3)
    b, c = rng.uniform(0.5, 1.5, 12), rng.standard_normal(12)
    f = lambda x: (float(c @ x), x)  # noqa: E731
    direction = lambda x: (c, b * budget_direction(b * c, 1.0, np.inf))  # noqa: E731
    history: list[dict[str, float]] = []
    x, fx, _, it, evals, converged = projected_ascent(f, direction, Box(-b, b), np.zeros(12), b, 100, 1e-14,
                                                      history, bb="long")
    np.testing.assert_array_equal(x, np.sign(c) * b)
    assert converged and fx == pytest.approx(float(np.abs(c) @ b))
    assert it < 10 and len(history) == it - 1  # the last iteration only found the zero projected step


def test_stop_hook_returns_the_first_accepted_point_that_meets_the_goal() -> None:
    """stop(aux) is checked at the start and at every accepted point; the loop returns that point as converged."""
    c, mu, b = np.array([1.0, -2.0, 0.5]), np.ones(3), np.full(3, 10.0)
    f, grad = _separable(c, mu)
    direction = lambda x: (grad(x), b * budget_direction(b * grad(x), 0.1, np.inf))  # noqa: E731
    goal = 2.0  # below the maximum 2.625 = |c|^2 / 2
    history: list[dict[str, float]] = []
    x, fx, aux, it, _, converged = projected_ascent(f, direction, Box(-b, b), np.zeros(3), b, 200, 1e-14, history,
                                                    stop=lambda x: f(x)[0] >= goal)
    assert converged and goal <= fx <= 2.625 and it == len(history)
    assert all(h["value"] < goal for h in history[:-1])
    np.testing.assert_array_equal(aux, x)
    _, _, _, it0, evals0, _ = projected_ascent(f, direction, Box(-b, b), x, b, 200, 1e-14, [],
                                               stop=lambda x: f(x)[0] >= goal)
    assert (it0, evals0) == (0, 1)


def test_moved_points_and_the_reason_for_stopping_are_reported() -> None:
    """`at` places the iterate where f evaluated (here f moves every point onto the plane x0 = x1, as the descent's
    restoration moves a point into the lower level's domain): the loop then ascends on that plane and every iterate
    lies on it. `why` names the stop: the gain window, the iteration limit, or a failed line search (min_step)."""
    c, b = np.array([1.0, 3.0]), np.full(2, 10.0)
    onto = lambda x: np.full(2, x.mean())  # noqa: E731
    f = lambda x: (float(c @ onto(x) - 0.5 * onto(x) @ onto(x)), onto(x))  # noqa: E731  (max on the plane at (2, 2): 4)
    direction = lambda x: (c - x, c - x)  # noqa: E731
    why: dict[str, str] = {}
    x, fx, aux, *_, converged = projected_ascent(f, direction, Box(-b, b), np.array([0.0, 1.0]), 1.0, 200, 1e-14,
                                                  [], at=lambda aux: aux, why=why)
    assert converged and why["stop"] == "window"
    np.testing.assert_allclose(x, [2.0, 2.0], atol=1e-6)
    assert x[0] == x[1] and fx == pytest.approx(4.0)
    why = {}
    projected_ascent(f, direction, Box(-b, b), np.array([0.0, 1.0]), 1.0, 1, 1e-14, [], at=lambda aux: aux, why=why)
    assert why["stop"] == "max_iter"
    why = {}
    flat = lambda x: (0.0 if x[0] <= 0.5 else -1.0, x)  # noqa: E731  (every step up decreases f)
    _, _, _, it, evals, converged = projected_ascent(flat, lambda x: (np.ones(2), np.ones(2)), Box(-b, b),
                                                     np.full(2, 0.5), 1.0, 10, 1e-14, [], why=why, min_step=0.1)
    assert converged and why["stop"] == "line search" and it == 1 and evals == 1 + 4  # 1, 1/2, 1/4, 1/8 tried


def test_trial_points_without_a_derivative_are_rejected_and_named() -> None:
    """A direction that raises RankDeficientRegressor (a lower level without a unique solution, x <= 0 here) makes
    its trial point fail: the ascent of -(x + 0.5)^2 on [-1, 1] backtracks and approaches 0 from above, never
    accepting x <= 0; started 1e-12 from that set, every step fails and the line search says why."""
    from bilevel.errors import RankDeficientRegressor

    def f(x: np.ndarray) -> tuple[float, np.ndarray]:
        return -float((x[0] + 0.5) ** 2), x

    def direction(x: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        if x[0] <= 0:
            raise RankDeficientRegressor("singular at x <= 0")
        g = -2 * (x + 0.5)
        return g, g / max(1.0, float(np.abs(g).max()))

    box = Box(np.array([-1.0]), np.array([1.0]))
    why: dict[str, str] = {}
    x, fx, _, _, _, _ = projected_ascent(f, direction, box, np.array([1.0]), 1.0, 200, 0.0, [], why=why)
    assert 0 < x[0] < 1e-6 and fx == pytest.approx(-0.25, abs=1e-6)
    why = {}
    x, _, _, it, _, _ = projected_ascent(f, direction, box, np.array([1e-12]), 1.0, 200, 0.0, [], why=why)
    assert x[0] == 1e-12 and it == 1 and why == {"stop": "line search", "singular": "singular at x <= 0"}
