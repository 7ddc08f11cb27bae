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
