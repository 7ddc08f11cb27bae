"""DeePC attacks (deepc-tracking, deepc-first-action): the engine's learner is an independent cvxpy DeePC written here,
the attack's value is recomputed by re-solving that DeePC on the poisoned data and simulating the true plant, budgets
hold, and the attack beats random poisoning of the same budget."""

from __future__ import annotations

import cvxpy as cp
import numpy as np
import pytest
from scipy.signal import lfilter

from bilevel.errors import InvalidData, ModelError, NotPersistentlyExciting
from bilevel.problems import registry
from bilevel.problems.budget import Budget
from bilevel.problems.deepc import declaration
from bilevel.problems.deepc_instance import DeePCAttack, attack_instance

SMALL = {"T": 60, "horizon": 6}
"""A small instance (55 Hankel columns) that solves in about a second."""


def own_deepc(atk, u_data: np.ndarray, y_data: np.ndarray, u_ini: np.ndarray | None = None,
              y_ini: np.ndarray | None = None) -> tuple[float, np.ndarray, np.ndarray]:
    """(optimal value, g, u) of DeePC written out here: Hankel columns by slicing, the l1 term by bounds s <= t;
    u_ini, y_ini default to the instance's past."""
    L, k = atk.t_ini + atk.horizon, atk.t_ini
    cols = u_data.size - L + 1
    Hu = np.array([u_data[j:j + L] for j in range(cols)]).T
    Hy = np.array([y_data[j:j + L] for j in range(cols)]).T
    g, s, t = cp.Variable(cols), cp.Variable(k), cp.Variable(k)
    u, y = Hu[k:] @ g, Hy[k:] @ g
    cost = (atk.q * cp.sum_squares(y - atk.reference) + atk.r_weight * cp.sum_squares(u)
            + atk.lambda_g * cp.sum_squares(g) + atk.lambda_y * cp.sum(t))
    u_ini = atk.past_u[-k:] if u_ini is None else u_ini
    y_ini = atk.past_y[-k:] if y_ini is None else y_ini
    constraints = [Hu[:k] @ g == u_ini, Hy[:k] @ g == y_ini + s, s <= t, -s <= t]
    if atk.u_max is not None:
        constraints.append(cp.abs(u) <= atk.u_max)
    problem = cp.Problem(cp.Minimize(cost), constraints)
    problem.solve(solver=cp.CLARABEL, tol_gap_abs=1e-10, tol_gap_rel=1e-10, tol_feas=1e-10)
    assert problem.status == cp.OPTIMAL
    return problem.value, g.value, Hu[k:] @ g.value


def plant_output(atk, u: np.ndarray) -> np.ndarray:
    """The flexible transmission's output from rest by lfilter (B(z)/A(z) in powers of 1/z)."""
    num, den = np.asarray(atk.plant.num[0][0], float), np.asarray(atk.plant.den[0][0], float)
    return lfilter(np.concatenate([np.zeros(den.size - num.size), num]), den, u)


def true_cost(atk, plan: np.ndarray) -> float:
    """The plant simulated over its past then the plan: q ||y - r||^2 + r_w ||u||^2 over the plan."""
    y = plant_output(atk, np.concatenate([atk.past_u, plan]))[atk.past_u.size:]
    return float(atk.q * np.sum((y - atk.reference) ** 2) + atk.r_weight * np.sum(plan ** 2))


def own_closed_loop_cost(atk, steps: int) -> float:
    """Receding horizon on clean data written out here: re-solve, apply the first input, measure, repeat."""
    k, u, y = atk.t_ini, list(atk.past_u), list(atk.past_y)
    for _ in range(steps):
        u.append(own_deepc(atk, atk.u, atk.y, np.array(u[-k:]), np.array(y[-k:]))[2][0])
        y.append(plant_output(atk, np.array(u))[-1])
    applied, outputs = np.array(u[atk.past_u.size:]), np.array(y[atk.past_u.size:])
    return float(atk.q * np.sum((outputs - atk.reference) ** 2) + atk.r_weight * applied @ applied)


def test_clean_learner_is_the_independent_deepc() -> None:
    """With a zero budget the engine's lower solution (g, u) and value are those of the DeePC written here."""
    atk = attack_instance(**SMALL, eps=0.0, norm="linf", past_std=0.5, seed=2)
    problem, ll, v = declaration(atk)
    result = problem.solve("ipopt", starts=1)
    assert result.status.value == "solved" and result.certificate.passed, result.message
    value, g, u = own_deepc(atk, atk.u, atk.y)
    assert result.lower_objective == pytest.approx(value, rel=1e-6)
    np.testing.assert_allclose(np.ravel(result.value(ll[v["g"]])), g, atol=1e-5 * np.abs(g).max())
    np.testing.assert_allclose(np.ravel(result.value(ll[v["u"]])), u, atol=1e-5 * np.abs(u).max())
    assert result.upper_objective == pytest.approx(true_cost(atk, u), rel=1e-6)
    assert atk.u0_clean == pytest.approx(u[0], abs=1e-5 * np.abs(u).max())


def poisoned(atk, result) -> tuple[np.ndarray, np.ndarray]:
    return atk.u + np.ravel(result.x["du"]), atk.y + np.ravel(result.x["dy"])


def random_poisoning(atk, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    """A random change of each signal on its budget's boundary (sign vertex for linf, sphere for l2)."""
    out = []
    for s in (atk.u, atk.y):
        if atk.budget.norm == "linf":
            out.append(s + atk.budget.radius(s) * rng.choice([-1.0, 1.0], s.size))
        else:
            d = rng.standard_normal(s.size)
            out.append(s + atk.budget.radius(s) * d / np.linalg.norm(d))
    return out[0], out[1]


@pytest.mark.parametrize("name,norm,extra", [("deepc-tracking", "l2", {}),
                                             ("deepc-tracking", "linf", {"u_max": 1.5, "past_std": 0.5}),
                                             ("deepc-first-action", "l2", {})])
def test_attack_is_recomputed_independently_and_beats_random_poisoning(name: str, norm: str, extra: dict) -> None:
    """Also with an input bound and a past that leaves the plant moving (linf case)."""
    check_attack(name, norm, {**SMALL, **extra})


@pytest.mark.slow
def test_attack_at_the_registered_defaults() -> None:
    """T = 200, horizon 10: the same checks at the size the benchmark runs."""
    check_attack("deepc-tracking", "l2", {})


def check_attack(name: str, norm: str, params: dict) -> None:
    """One start of `name`: certified, budgets hold, the value is recomputed independently, beats random poisoning;
    a first-action attack also destabilizes the receding-horizon loop."""
    atk = attack_instance(**params, norm=norm, objective=name.removeprefix("deepc-"), seed=1)
    result = registry.get(name, **params, norm=norm, seed=1).solve(starts=1, seed=0)
    assert result.status.value == "solved" and result.certificate.passed, result.message
    u_p, y_p = poisoned(atk, result)
    order = 2 if norm == "l2" else np.inf
    for clean, bad, label in ((atk.u, u_p, "u"), (atk.y, y_p, "y")):
        assert np.linalg.norm(bad - clean, order) <= 0.05 * np.linalg.norm(clean, order) * (1 + 1e-7), label
    _, _, plan = own_deepc(atk, u_p, y_p)
    value = true_cost(atk, plan) if atk.objective == "tracking" else (plan[0] - atk.u0_clean) ** 2
    assert result.upper_objective == pytest.approx(value, rel=1e-5, abs=1e-8)
    _, _, clean_plan = own_deepc(atk, atk.u, atk.y)
    clean = true_cost(atk, clean_plan) if atk.objective == "tracking" else 0.0
    rng = np.random.default_rng(3)
    randoms = []
    for _ in range(20):
        plan = own_deepc(atk, *random_poisoning(atk, rng))[2]
        randoms.append(true_cost(atk, plan) if atk.objective == "tracking" else (plan[0] - atk.u0_clean) ** 2)
    assert value > clean and value > 1.5 * max(randoms), (value, clean, max(randoms))
    if atk.objective == "first-action":  # the receding-horizon loop on the poisoned data goes unstable
        assert atk.closed_loop_cost(u_p, y_p, 60) > 100 * atk.closed_loop_cost(atk.u, atk.y, 60)


def test_closed_loop_is_the_independent_receding_horizon() -> None:
    """Receding horizon on clean data: the cost equals the loop written here, and the output settles near r."""
    atk = attack_instance(**SMALL, seed=1)
    assert atk.closed_loop_cost(atk.u, atk.y, 30) == pytest.approx(own_closed_loop_cost(atk, 30), rel=1e-6)
    outputs = atk.closed_loop(atk.u, atk.y, 60)[1]
    assert np.all(np.abs(outputs[-10:] - atk.reference) < 0.05)


def test_bad_parameters_are_refused() -> None:
    with pytest.raises(ModelError, match="objective"):
        attack_instance(objective="cost")
    with pytest.raises(ModelError, match="l2 or linf"):
        attack_instance(norm="l1")
    with pytest.raises(InvalidData, match="record at least"):
        attack_instance(T=30)
    with pytest.raises(ModelError, match="u_max"):
        attack_instance(u_max=-1.0)
    with pytest.raises(NotPersistentlyExciting):
        atk = attack_instance(**SMALL)
        DeePCAttack(atk.plant, np.ones(60), atk.y, atk.past_u, atk.past_y, Budget(0.05))


def test_deepc_page_runs() -> None:
    """docs/deepc.md's code prints what the page says."""
    from tests.docs_pages import run_page

    run_page("deepc.md")
