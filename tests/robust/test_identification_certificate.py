"""The identification + CE LQR certificate: the certified model ball contains the exact re-fit's model, and a
certificate is proven only with its LMIs re-checked."""

from __future__ import annotations

import numpy as np
import pytest

from bilevel.problems.identification_instance import attack_instance
from bilevel.robust import Proof, as_target, certify, sphere_poisoning
from bilevel.robust.identification import model_radius


@pytest.fixture(scope="module")
def atk():
    return attack_instance("ss", 100, 0.0, "ce-lqr", seed=0)


def test_the_model_ball_contains_the_refit(atk) -> None:
    target = as_target(atk)
    theta0 = target.refit(target.signals)
    rng = np.random.default_rng(2)
    for delta in (1e-3, 1e-2, 5e-2):
        eps, s = model_radius(atk, delta)
        assert s > 0
        for _ in range(100):
            theta = target.refit(target.poisoned(sphere_poisoning(target, delta, rng)))
            assert np.linalg.norm(theta - theta0, 2) <= eps


def test_the_clean_loop_is_stable_and_an_unproven_budget_is_unknown(atk) -> None:
    target = as_target(atk)
    assert target.true_radius({}) < 1
    cert = certify(atk, 0.01)
    assert cert.proof is Proof.UNKNOWN and not cert.proven
