"""Method `differential-evolution` (bilevel.solvers.evolution): known optima, a multimodal objective, honesty."""

from __future__ import annotations

import casadi as ca
import numpy as np
import pytest

import bilevel as bl
from bilevel.problems import registry


@pytest.mark.parametrize("name", ["bolib-gumusfloudas2001ex4", "macmpec-ex9.2.5", "macmpec-ex9.2.8",
                                  "bolib-hendersonquandt1958"])
def test_boxed_textbook_problems_reach_their_known_optimum(name: str) -> None:
    """Every upper variable bounded: evolution then the descent reach the literature optimum (see
    registry.spec(name).source: Gumus & Floudas 2001 Ex. 4, F* = 9; Clark & Westerberg 1990, F* = 5; Yezza 1996
    Ex. 3.1, F* = 1.5; Henderson & Quandt 1958, F* = -3266.67), solved and certified."""
    res = bl.solve(registry.get(name), method="differential-evolution")
    optimum = registry.spec(name).optimum
    assert res.status is bl.Status.SOLVED and res.certificate.passed
    assert abs(res.upper_objective - optimum) <= 1e-5 * max(1.0, abs(optimum))


def _wavy(start: float) -> bl.BilevelProblem:
    """y*(x) = x, F = sin(3y) + 0.1 y^2 on [-3, 3]: local minima near -2.6, -0.51 (global) and 1.54."""
    p = bl.BilevelProblem("wavy")
    x = p.upper_variable("x", lb=-3, ub=3, start=start)
    y = p.lower_variable("y")
    p.minimize_lower((y - x) ** 2)
    p.minimize_upper(ca.sin(3 * y) + 0.1 * y ** 2)
    return p


@pytest.mark.parametrize("seed", range(3))
def test_evolution_finds_the_global_minimum_the_descent_from_the_start_misses(seed: int) -> None:
    """From x = 1.5 the descent stops in the local minimum near 1.54; evolution (its population holds that start)
    reaches the global one, checked against a 600,001-point grid of the reduced objective."""
    grid = np.linspace(-3, 3, 600_001)
    best = float(np.min(np.sin(3 * grid) + 0.1 * grid ** 2))
    local = bl.solve(_wavy(1.5), method="hypergradient", starts=1)
    assert local.upper_objective > best + 0.2
    res = bl.solve(_wavy(1.5), method="differential-evolution", seed=seed)
    assert res.status is bl.Status.SOLVED
    assert best - 1e-9 <= res.upper_objective <= best + 1e-8


def test_without_polish_the_answer_is_never_solved_and_unbounded_boxes_are_refused() -> None:
    """The population's best point is a heuristic's answer (inaccurate, still certified); a variable without finite
    bounds is named with the fix."""
    res = bl.solve(_wavy(1.5), method="differential-evolution", polish=False)
    assert res.status is bl.Status.INACCURATE and res.certificate.passed
    p = bl.BilevelProblem()
    x = p.upper_variable("x", lb=0)
    y = p.lower_variable("y")
    p.minimize_lower((y - x) ** 2)
    p.minimize_upper(y ** 2)
    with pytest.raises(bl.ModelError, match="declare lb and ub"):
        bl.solve(p, method="differential-evolution")
    with pytest.raises(bl.UnknownOption, match="popsize"):
        bl.solve(_wavy(0.0), method="differential-evolution", pop_size=3)


def test_population_sweep_equals_pointwise_phi_where_the_lower_level_ignores_x() -> None:
    """willems-eigen with input poisoning (the SDP does not see Du, solved once): the mapped sweep of a population
    gives the engine's pointwise phi to 1e-12 relative; a lower level that depends on x is refused."""
    from bilevel.problems.willems import build_attack
    from bilevel.solvers.engine.prepared import prepare
    from bilevel.solvers.engine.implicit import Hypergradient

    attack = build_attack(objective="eigen", horizon=15, seed=0, delta_u=0.6)
    oracle = Hypergradient(prepare(attack.problem))
    xs = np.random.default_rng(0).uniform(-0.6, 0.6, (attack.budget().size, 7))
    pointwise = np.array([oracle.evaluate(x).phi for x in xs.T])
    np.testing.assert_allclose(oracle.batch_phi(xs), pointwise, rtol=1e-12, atol=0)
    with pytest.raises(bl.ModelError, match="does not depend"):
        Hypergradient(prepare(_wavy(0.0))).batch_phi(np.zeros((1, 3)))


def test_a_lower_level_infeasible_on_the_whole_box_is_an_error_not_an_answer() -> None:
    """y >= 1 and y <= x with x in [-2, 0]: no point of the box has a lower solution, so there is no answer."""
    p = bl.BilevelProblem("nowhere")
    x = p.upper_variable("x", lb=-2, ub=0)
    y = p.lower_variable("y")
    p.lower_constraint(y >= 1)
    p.lower_constraint(y <= x)
    p.minimize_lower(y ** 2)
    p.minimize_upper(x ** 2 + y)
    res = bl.solve(p, method="differential-evolution", max_iter=3, popsize=3)
    assert res.status is bl.Status.ERROR and "could not be solved" in res.message and res.upper_objective is None


def _deferred_reference(values, lb, ub, rng, max_iter, init):
    """The deferred (vectorized) generation as evolve wrote it before it ran in place: allocated arrays, np.where
    crossover; no stop rule."""
    from bilevel.solvers.evolution import MUTATION, RECOMBINATION, _others
    n, width = lb.size, ub - lb
    unit = np.clip((init - lb) / width, 0.0, 1.0)
    size = unit.shape[0]
    energies = np.asarray(values((lb + unit * width).T), dtype=float)
    best = int(np.argmin(energies))
    for _ in range(max_iter):
        weight = rng.uniform(*MUTATION)
        members = np.arange(size)
        r0, r1 = _others(rng, members, size)
        mutant = unit[best] + weight * (unit[r0] - unit[r1])
        cross = rng.random((size, n), dtype=np.float32) < RECOMBINATION
        cross[members, rng.integers(n, size=size)] = True
        trial = np.where(cross, mutant, unit[members])
        outside = (trial < 0.0) | (trial > 1.0)
        trial[outside] = rng.uniform(size=int(outside.sum()))
        trial_energies = np.asarray(values((lb + trial * width).T), dtype=float)
        better = trial_energies <= energies
        unit[better], energies[better] = trial[better], trial_energies[better]
        best = int(np.argmin(energies))
    return lb + unit[best] * width, energies[best]


def test_in_place_generation_is_bit_identical_to_the_allocating_one() -> None:
    """evolve's deferred generation, run in place, draws the same stream and reaches the same population as the
    allocating formulation: the same best point and value, bit for bit, on a rugged objective (ties at its floor)."""
    from bilevel.solvers.evolution import evolve
    lb, ub = -np.array([1.0, 2.0, 0.5, 1.5]), np.array([1.0, 2.0, 0.5, 1.5])

    def f(xs):
        return np.maximum(np.sum(np.sin(3.0 * xs) + 0.1 * xs ** 2, axis=0), -2.5)
    init = np.random.default_rng(5).uniform(lb, ub, (40, 4))
    out = evolve(f, lb, ub, np.random.default_rng(9), 60, 10, -1.0, vectorized=True, init=init.copy())  # no tol stop
    x, fun = _deferred_reference(f, lb, ub, np.random.default_rng(9), 60, init.copy())
    assert out.nit == 60 and np.array_equal(out.x, x) and out.fun == fun
