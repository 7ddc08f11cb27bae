"""The DeePC certificate (bilevel.robust.deepc): the numpy re-fit against cvxpy, a proof at a small budget that the
true tracking cost of every sampled poisoning and of the engine's attack respects, the two routes' agreement, a
tampered map caught by the re-check, and the refusals."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from bilevel.errors import ModelError
from bilevel.problems.budget import Budget
from bilevel.problems.deepc_instance import attack_instance
from bilevel.robust import Proof, as_target, certified_margin, certify, sphere_poisoning
from bilevel.robust.deepc import gram_maps, kkt_maps, numpy_plan


@pytest.fixture(scope="module")
def target():
    return as_target(attack_instance(T=60, seed=0))


def test_numpy_refit_matches_cvxpy(target) -> None:
    atk = target.declaration.attack
    rng = np.random.default_rng(1)
    du, dy = 0.01 * rng.standard_normal(atk.u.size), 0.01 * rng.standard_normal(atk.y.size)
    for u, y in ((atk.u, atk.y), (atk.u + du, atk.y + dy)):
        assert np.allclose(numpy_plan(atk, u, y), atk.plan(u, y), atol=1e-7)
    # a slack weight too small to keep the slack at zero: the re-fit falls back to cvxpy on the full QP
    loose = dataclasses.replace(atk, past_u=rng.standard_normal(atk.past_u.size), lambda_y=1e-3)
    assert np.allclose(numpy_plan(loose, loose.u, loose.y), loose.plan(loose.u, loose.y), atol=1e-7)


def test_the_two_routes_agree(target) -> None:
    gram, kkt = gram_maps(target.declaration), kkt_maps(target.declaration)
    assert np.abs(gram.g - kkt.g).max() <= 1e-7 * np.abs(gram.g).max()
    assert np.allclose(gram.r0, kkt.r0, atol=1e-7) and np.allclose(gram.quad, kkt.quad, rtol=1e-6)


def test_proof_bounds_the_sampled_and_attacked_costs(target) -> None:
    delta = 1e-4
    cert = certify(target, delta)
    evidence = cert.evidence[0]
    assert cert.proof is Proof.PROVEN and evidence.check.passed and evidence.mechanism == "kkt-sensitivity"
    level = target.declaration.level
    assert target.declaration.clean_cost <= evidence.numbers["linear"] <= cert.bound < level
    rng = np.random.default_rng(2)
    costs = [target.true_radius(sphere_poisoning(target, delta, rng)) * level for _ in range(200)]
    attacked = target.true_radius(target.attacks["engine"](delta, 0)) * level
    assert max(costs) <= cert.bound and attacked <= cert.bound
    assert attacked > target.declaration.clean_cost  # the attack does move the cost


def test_large_budget_is_never_proven(target) -> None:
    cert = certify(target, 0.02)
    assert cert.proof in (Proof.BOUNDED, Proof.UNKNOWN) and not cert.proven


def test_tampered_map_fails_its_recheck() -> None:
    target = as_target(attack_instance(T=60, seed=3))
    cost = target.declaration
    cost.cache["gram"] = dataclasses.replace(gram_maps(cost), g=0.5 * gram_maps(cost).g)  # a too-small linear map
    cert = certify(target, 1e-4)
    assert cert.proof is Proof.UNKNOWN and not cert.evidence[0].check.passed


def test_margin_below_a_given_delta_ub(target) -> None:
    margin = certified_margin(target, delta_ub=0.01)
    assert 0 < margin.delta_lb < 0.01 and margin.certificate.proven


@pytest.mark.parametrize("change, why", [({"objective": "first-action"}, "tracking cost"),
                                         ({"budget": Budget(0.05, "linf")}, "l2 budget"),
                                         ({"u_max": 2.0}, "no input bound")])
def test_other_settings_are_refused(change, why) -> None:
    atk = dataclasses.replace(attack_instance(T=60, seed=0), **change)
    with pytest.raises(ModelError, match=why):
        as_target(atk)


def _ascent_poisoning(target, delta: float, starts: int, steps: int, seed: int) -> dict[str, np.ndarray]:
    """The largest true tracking cost a projected-gradient ascent finds on the budget spheres (the gradient of the
    Gram form's plan written out here; the cost judged by the target's numpy KKT re-fit)."""
    from bilevel.robust.deepc import _cost_metric, _unit_rows, hankel_rows

    atk = target.declaration.attack
    t, k, n, lam, rw = atk.u.size, atk.t_ini, atk.horizon, atk.lambda_g, atk.r_weight
    w0, units = hankel_rows(atk, atk.u, atk.y), _unit_rows(atk)
    pi = np.diag(np.concatenate([np.zeros(2 * k), np.full(n, 1 / rw), np.full(n, 1 / atk.q)]))
    h = np.concatenate([atk.past_u[-k:], atk.past_y[-k:], np.zeros(n), np.full(n, atk.reference)])
    mm, c = _cost_metric(atk)
    radii = target.radii(delta)

    def onto(a):
        return np.concatenate([radii["u"] * a[:t] / np.linalg.norm(a[:t]), radii["y"] * a[t:] / np.linalg.norm(a[t:])])

    def cost_grad(a):
        w = w0 + np.tensordot(a, units, axes=1)
        m = w @ w.T + lam * pi
        v = np.linalg.solve(m, h)
        r = mm @ (-(lam / rw) * v[2 * k:2 * k + n]) - c
        z = np.linalg.solve(m, np.concatenate([np.zeros(2 * k), (lam / rw) * mm.T @ r, np.zeros(n)]))
        return r @ r, 2 * (np.einsum("r,src,c->s", z, units, w.T @ v) + np.einsum("r,src,c->s", v, units, w.T @ z))

    rng = np.random.default_rng(seed)
    best, best_a = -np.inf, None
    for _ in range(starts):
        a, step = onto(rng.standard_normal(2 * t)), 1e-3
        for _ in range(steps):
            f, grad = cost_grad(a)
            trial = onto(a + step * radii["y"] * grad / np.linalg.norm(grad))
            a, step = (trial, 1.5 * step) if cost_grad(trial)[0] > f else (a, 0.5 * step)
        if cost_grad(a)[0] > best:
            best, best_a = cost_grad(a)[0], a
    return {"u": best_a[:t], "y": best_a[t:]}


def test_plan_sensitivity_way_is_tighter_than_m_alone(target) -> None:
    # T = 60, seed 0 (before kappa and the S-lemma's block norms): the first way alone proved the level up to delta
    # 8.1e-4, with the plan's sensitivity 1.66e-3
    from bilevel.robust.deepc import cost_bound

    cost, delta = target.declaration, 1.3e-3
    cert = certify(target, delta)
    numbers = cert.evidence[0].numbers
    assert cert.proof is Proof.PROVEN and cert.evidence[0].check.passed
    assert numbers["third_through_plan"] < 0.2 * numbers["third_through_m"]
    m_alone = dataclasses.replace(gram_maps(cost), p0w0=float("inf"), beta_p=float("inf"))
    old = cost_bound(m_alone, cost.attack, delta, (numbers["multiplier_u"], numbers["multiplier_y"]))
    assert old["bound"] >= cost.level > cert.bound


def test_plan_sensitivity_bound_holds_where_it_decides(target) -> None:
    # near the new delta_lb: 2000 sphere poisonings, the engine's attack and a gradient ascent of the true cost
    delta = 1.6e-3
    cert = certify(target, delta)
    assert cert.proven and cert.evidence[0].numbers["third_through_plan"] < cert.evidence[0].numbers["third_through_m"]
    level = target.declaration.level
    rng = np.random.default_rng(3)
    sampled = max(target.true_radius(sphere_poisoning(target, delta, rng)) for _ in range(2000)) * level
    attacked = target.true_radius(target.attacks["engine"](delta, 0)) * level
    ascended = target.true_radius(_ascent_poisoning(target, delta, starts=3, steps=60, seed=4)) * level
    assert max(sampled, attacked, ascended) <= cert.bound
    assert ascended > target.declaration.clean_cost  # the ascent does move the cost


def test_lower_bound_on_m_through_the_linear_part_decides_and_holds(target) -> None:
    # T = 60, seed 0: with M >= (1 - beta)^2 M0 alone the level is proven up to delta 1.84e-3, with
    # kappa = max(1 - beta, 1 - gamma / 2) up to 1.92e-3; at 1.9e-3 the bound must hold for 2000 sphere poisonings,
    # the engine's attack and a gradient ascent of the true cost
    from bilevel.robust.deepc import cost_bound

    cost, delta = target.declaration, 1.9e-3
    cert = certify(target, delta)
    numbers = cert.evidence[0].numbers
    assert cert.proof is Proof.PROVEN and cert.evidence[0].check.passed
    assert numbers["kappa"] > 1 - numbers["beta"]
    beta_alone = dataclasses.replace(gram_maps(cost), gamma=float("inf"))
    assert cost_bound(beta_alone, cost.attack, delta, (numbers["multiplier_u"], numbers["multiplier_y"]))["bound"] \
        >= cost.level
    level = cost.level
    rng = np.random.default_rng(5)
    sampled = max(target.true_radius(sphere_poisoning(target, delta, rng)) for _ in range(2000)) * level
    attacked = target.true_radius(target.attacks["engine"](delta, 0)) * level
    ascended = target.true_radius(_ascent_poisoning(target, delta, starts=3, steps=60, seed=6)) * level
    assert max(sampled, attacked, ascended) <= cert.bound


def test_block_norm_bounds_the_sup_and_beats_the_block_sum() -> None:
    # the S-lemma value is at most the two blocks' sum and at least every ||F a|| on the balls, including the
    # maximizer's candidates along each block's top singular vectors combined with both signs
    from bilevel.robust.deepc import _block_norm

    rng = np.random.default_rng(7)
    t, radii = 6, (0.7, 2.0)
    rows = rng.standard_normal((2 * t, 3, 4))
    flat = rows.reshape(2 * t, -1)
    bound = _block_norm(rows, t, radii)
    assert bound <= radii[0] * np.linalg.norm(flat[:t], 2) + radii[1] * np.linalg.norm(flat[t:], 2)
    tops = [np.linalg.svd(flat[blk].T)[2][0] for blk in (slice(0, t), slice(t, 2 * t))]
    tries = [np.concatenate([radii[0] * tops[0], sign * radii[1] * tops[1]]) for sign in (1, -1)]
    for _ in range(2000):
        a = rng.standard_normal(2 * t)
        a[:t], a[t:] = radii[0] * a[:t] / np.linalg.norm(a[:t]), radii[1] * a[t:] / np.linalg.norm(a[t:])
        tries.append(a)
    assert max(np.linalg.norm(flat.T @ a) for a in tries) <= bound


@pytest.mark.parametrize("name, factor, delta", [("p0w0", 0.1, 1.3e-3), ("gamma", 0.5, 1.9e-3), ("beta", 0.8, 1.9e-3)])
def test_tampered_factor_fails_its_recheck(name, factor, delta) -> None:
    # T = 60, seed 0, where each factor decides (the plan-sensitivity way's ||P0 W0|| at 1.3e-3, kappa's gamma and
    # beta at 1.9e-3): a too-small factor in the Gram route's maps is caught by the second route
    target = as_target(attack_instance(T=60, seed=0))
    cost = target.declaration
    cost.cache["gram"] = dataclasses.replace(gram_maps(cost), **{name: factor * getattr(gram_maps(cost), name)})
    cert = certify(target, delta)
    assert cert.proof is Proof.UNKNOWN and not cert.evidence[0].check.passed
