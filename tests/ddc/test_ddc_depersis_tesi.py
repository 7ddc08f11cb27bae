"""De Persis-Tesi learners on the batch reactor: LQR SDP equals the Riccati solution; stabilization; PE check."""

from __future__ import annotations

import numpy as np
import pytest
import scipy.linalg

from bilevel.ddc.analysis import analyze_state_feedback
from bilevel.ddc.data import batch_reactor_data, state_trajectory
from bilevel.ddc.depersis_tesi import (
    check_persistency,
    lqr_controller,
    stabilizing_controller,
    state_data,
)
from bilevel.ddc.plants import batch_reactor
from bilevel.errors import InvalidData, NotPersistentlyExciting

PLANT = batch_reactor()
A, B = PLANT.A, PLANT.B


def _dare_gain(r: np.ndarray) -> tuple[np.ndarray, float]:
    """Model-based LQR for u = K x: K = -(R + B'PB)^{-1} B'PA, cost trace(P) (unit noise on all states)."""
    p = scipy.linalg.solve_discrete_are(A, B, np.eye(4), r)
    return -np.linalg.solve(r + B.T @ p @ B, B.T @ p @ A), float(np.trace(p))


@pytest.mark.parametrize(("r_scale", "value"), [(1.0, 29.1262), (0.1, 10.9851)])
@pytest.mark.parametrize("seed", [0, 1, 2])
def test_lqr_sdp_equals_riccati(r_scale, value, seed):
    """De Persis & Tesi (2020), Theorem 4, on noise-free batch-reactor data (Walsh & Ye 2001; paper
    appendix), T = 15, white input, Qx = I: K equals the DARE gain (DESIGN.md: K = [[0.0637, -0.7056,
    -0.1564, -0.6700], [2.1492, 0.0882, 1.4900, -0.9798]] for R = I) and the optimal value equals
    trace(P_DARE) = 29.1262 (R = I) and 10.9851 (R = 0.1 I)."""
    r = r_scale * np.eye(2)
    k_dare, trace_p = _dare_gain(r)
    assert trace_p == pytest.approx(value, abs=1e-4)
    x, u = batch_reactor_data(15, np.random.default_rng(seed))
    result = lqr_controller(x, u, r=r)
    assert result.status == "optimal"
    np.testing.assert_allclose(result.k, k_dare, atol=1e-4)
    assert result.value == pytest.approx(value, abs=1e-3)
    analysis = analyze_state_feedback(A, B, result.k, r=r)
    assert analysis.h2_norm**2 == pytest.approx(trace_p, abs=1e-6)


def test_reference_gain_printed_in_design():
    """The DARE gain itself matches the numbers printed in DESIGN.md (4 decimals)."""
    k_dare, _ = _dare_gain(np.eye(2))
    expected = [[0.0637, -0.7056, -0.1564, -0.6700], [2.1492, 0.0882, 1.4900, -0.9798]]
    np.testing.assert_allclose(k_dare, expected, atol=5e-5)


def test_stabilizing_design_is_schur_stable():
    """De Persis & Tesi (2020), Theorem 3: the LMI solution gives A + B K Schur stable, and the
    data-based closed loop X1 Q (X0 Q)^{-1} equals the true A + B K on noise-free data."""
    x, u = batch_reactor_data(15, np.random.default_rng(0), random_x0=True)
    result = stabilizing_controller(x, u)
    acl = A + B @ result.k
    np.testing.assert_allclose(result.closed_loop, acl, atol=1e-7)
    assert np.max(np.abs(np.linalg.eigvals(acl))) < 1
    assert result.spectral_radius == pytest.approx(np.max(np.abs(np.linalg.eigvals(acl))), abs=1e-7)


def test_lqr_without_input_cost_is_stable_and_cheaper_in_state():
    """Paper appendix form (no R term): min trace(Qx X0 Q) still certifies stability, and its state
    cost trace(W) is no larger than that of the LQR gain (which also pays for the input)."""
    x, u = batch_reactor_data(15, np.random.default_rng(3))
    no_r = lqr_controller(x, u, input_cost=False)
    with_r = lqr_controller(x, u)
    state_cost = analyze_state_feedback(A, B, no_r.k).h2_norm ** 2
    assert no_r.spectral_radius < 1
    assert state_cost == pytest.approx(no_r.value, rel=1e-6)
    assert state_cost <= analyze_state_feedback(A, B, with_r.k).h2_norm ** 2


def test_not_persistently_exciting_data_are_refused():
    """rank [U0; X0] = n + m = 6 is required (De Persis & Tesi 2020, Lemma 1): T = 4 samples, or one
    input channel held at zero, cannot reach it; the message names the rank found and needed."""
    x, u = batch_reactor_data(4, np.random.default_rng(0))
    with pytest.raises(NotPersistentlyExciting, match=r"rank \[U0; X0\] = 4 but n \+ m = 6"):
        lqr_controller(x, u)
    u = np.random.default_rng(1).standard_normal((2, 15))
    u[1] = 0.0
    x = state_trajectory(A, B, u)
    with pytest.raises(NotPersistentlyExciting, match="n \\+ m = 6"):
        stabilizing_controller(x, u)


def test_data_shapes_and_values_are_checked():
    """X must hold T + 1 samples for T inputs; NaN/inf are refused; PE rank is returned when fine."""
    x, u = batch_reactor_data(15, np.random.default_rng(0))
    assert check_persistency(state_data(x, u)) == 6
    with pytest.raises(InvalidData, match="T\\+1"):
        state_data(x[:, :-1], u)
    x_bad = x.copy()
    x_bad[2, 3] = np.nan
    with pytest.raises(InvalidData, match="NaN"):
        lqr_controller(x_bad, u)
    with pytest.raises(InvalidData, match="Qx must be 4 x 4"):
        lqr_controller(x, u, qx=np.eye(3))


@pytest.mark.parametrize("input_cost", [False, True])
def test_balanced_learner_solves_n50_with_scs_and_ignores_input_poisoning(input_cost: bool) -> None:
    """Column balancing (states up to ~2e4 at T = 50): SCS then reaches Clarabel's value to 1e-5 relative
    (unbalanced it ended 4.5e-4 off on the appendix SDP, measured on 8 seeds); measured 2026-11-24: 1.3e-8 and 5.3e-8
    under OpenBLAS's SkylakeX and Haswell kernels ('optimal'), 1.1e-6 under Sandybridge with input cost, where SCS
    stops at 'optimal_inaccurate' (which of the two a first-order method reports at its tolerance is rounding). The
    weights use states only, so input poisoning leaves the appendix learner's Q unchanged."""
    x, u = batch_reactor_data(50, np.random.default_rng(0))
    scs = lqr_controller(x, u, input_cost=input_cost, solver="scs")
    clarabel = lqr_controller(x, u, input_cost=input_cost)
    assert scs.status in ("optimal", "optimal_inaccurate")
    assert scs.value == pytest.approx(clarabel.value, rel=1e-5)
    if not input_cost:
        poisoned = lqr_controller(x, u + 0.3 * np.sign(np.sin(np.arange(u.size))).reshape(u.shape),
                                  input_cost=False, solver="scs")
        np.testing.assert_array_equal(poisoned.q, scs.q)
