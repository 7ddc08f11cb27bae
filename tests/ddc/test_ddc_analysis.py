"""Closed-loop analysis: poles, responses and frequency data agree with python-control; state feedback."""

from __future__ import annotations

import json

import control
import numpy as np
import pytest
import scipy.linalg
from matplotlib.figure import Figure

from bilevel.ddc.analysis import (
    analyze_state_feedback,
    closed_loop,
    closed_loop_bode,
    closed_loop_poles,
    closed_loop_response,
    closed_loop_step,
)
from bilevel.ddc.bases import controller_tf, flexible_transmission_basis
from bilevel.ddc.plants import batch_reactor, flexible_transmission
from bilevel.errors import InvalidData

THETA = np.array([0.3343, -0.6132, 0.7285, -0.6628, 0.4827, -0.1252])


def test_closed_loop_matches_python_control_feedback():
    """Poles, step response and frequency response equal python-control's feedback(G K, 1)."""
    g = flexible_transmission()
    k = controller_tf(flexible_transmission_basis(), THETA, 0.05)
    reference = control.feedback(g * k, 1)
    poles = np.sort_complex(closed_loop_poles(g, k))
    np.testing.assert_allclose(poles, np.sort_complex(reference.poles()), atol=1e-8)
    step = closed_loop_step(g, k, n=300)
    assert isinstance(step, control.TimeResponseData) and step.outputs.shape == (300,)
    _, y_ref = control.forced_response(reference, T=np.arange(300) * 0.05, U=np.ones(300))
    np.testing.assert_allclose(step.outputs, y_ref, atol=1e-8)
    response = closed_loop_response(g, k, np.ones(300))
    np.testing.assert_allclose(response.output, y_ref, atol=1e-8)
    _, u_ref = control.forced_response(control.feedback(k, g), T=np.arange(300) * 0.05, U=np.ones(300))
    np.testing.assert_allclose(response.input, u_ref, atol=1e-8)
    assert step.time[1] == pytest.approx(0.05) and response.time[1] == pytest.approx(0.05) and response.stable
    omega = np.linspace(0.01, np.pi / 0.05, 50)
    np.testing.assert_allclose(closed_loop_bode(g, k, omega).magnitude.ravel(),
                               np.abs(reference(np.exp(1j * omega * 0.05))), rtol=1e-8)
    assert closed_loop(g, k).dt == 0.05


def test_unstable_loop_is_flagged_and_serialises():
    """A large proportional gain destabilises G = 1/(z - 0.5): pole at 0.5 - 2 = -1.5."""
    response = closed_loop_response(([1.0], [1.0, -0.5]), ([2.0], [1.0]), np.ones(20))
    assert not response.stable and response.spectral_radius == pytest.approx(1.5)
    payload = json.loads(response.to_json())
    assert payload["stable"] is False and payload["poles"] == [[-1.5, 0.0]]
    assert isinstance(response.plot(), Figure)


def test_step_response_on_a_plain_polynomial_loop():
    """G = 1/(z - 0.5), K = 2 (dt unspecified): y = 0, 2, -1, 3.5 (pole -1.5) on sample times 0, 1, 2; n < 1 is refused."""
    step = closed_loop_step(([1.0], [1.0, -0.5]), ([2.0], [1.0]), n=4)
    np.testing.assert_allclose(step.time, [0, 1, 2, 3])
    np.testing.assert_allclose(step.outputs, [0.0, 2.0, -1.0, 3.5])
    with pytest.raises(InvalidData, match="n >= 1"):
        closed_loop_step(([1.0], [1.0, -0.5]), ([2.0], [1.0]), n=0)


def test_ill_posed_loop_is_refused():
    """G K(inf) = -1 makes 1 + G K strictly proper: no causal closed loop exists."""
    with pytest.raises(InvalidData, match="ill-posed"):
        closed_loop_poles(([1.0, 0.0], [1.0, -0.5]), ([-1.0], [1.0]))


def test_state_feedback_gramian_and_h2():
    """W solves (A+BK) W (A+BK)^T - W + I = 0; with the LQR gain trace((Qx + K'RK) W) = trace(P_DARE)."""
    a, b = batch_reactor().A, batch_reactor().B
    p = scipy.linalg.solve_discrete_are(a, b, np.eye(4), np.eye(2))
    k = -np.linalg.solve(np.eye(2) + b.T @ p @ b, b.T @ p @ a)
    result = analyze_state_feedback(a, b, k, r=np.eye(2))
    acl = a + b @ k
    np.testing.assert_allclose(acl @ result.gramian @ acl.T - result.gramian + np.eye(4), 0, atol=1e-10)
    assert result.h2_norm**2 == pytest.approx(np.trace(p), rel=1e-10)
    assert result.stable and json.loads(result.to_json())["spectral_radius"] == result.spectral_radius
    open_loop = analyze_state_feedback(a, b, np.zeros((2, 4)))
    assert not open_loop.stable and open_loop.gramian is None and open_loop.h2_norm == np.inf
    assert json.loads(open_loop.to_json())["h2_norm"] == "inf"
