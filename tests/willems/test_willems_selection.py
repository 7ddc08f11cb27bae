"""The learner's selection among optimal Q sets its sensitivity to input poisoning (bilevel.experiments.willems_selection)."""

from __future__ import annotations

import numpy as np

from bilevel.ddc.data import batch_reactor_data
from bilevel.ddc.depersis_tesi import lqr_controller
from bilevel.experiments.willems_selection import input_gains


def test_input_poisoning_moves_the_gain_affinely_through_the_learners_q() -> None:
    """The appendix SDP has no U0: poisoned K' = K + A_u Q (X0 Q)^-1 with the clean Q, and the entrywise
    change is bounded by delta * (the reported gain)."""
    x, u = batch_reactor_data(15, np.random.default_rng(3))
    clean = lqr_controller(x, u, input_cost=False)
    delta = 0.05
    a_u = delta * np.sign(np.random.default_rng(4).standard_normal(u.shape))
    poisoned = lqr_controller(x, u + a_u, input_cost=False)
    g = clean.q @ np.linalg.inv(x[:, :-1] @ clean.q)
    np.testing.assert_allclose(poisoned.k, clean.k + a_u @ g, atol=1e-6)
    assert np.abs(poisoned.k - clean.k).max() <= delta * input_gains(x, u)["clarabel"] * (1 + 1e-6)


def test_minimum_norm_selection_has_no_null_space_part_and_same_clean_gain() -> None:
    x, u = batch_reactor_data(50, np.random.default_rng(5))
    gains = input_gains(x, u)
    assert gains["null_share"] > 0.1  # Clarabel's Q carries a null-space part at N = 50
    assert 0 < gains["min-norm"] < gains["clarabel"]
