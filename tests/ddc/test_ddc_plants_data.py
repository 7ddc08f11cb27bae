"""Plants of the paper, input signals and zero-initial-state simulation."""

from __future__ import annotations

import control
import numpy as np
import pytest

from bilevel.ddc.data import batch_reactor_data, paper_input, simulate, state_trajectory, step_pulse
from bilevel.ddc.plants import (
    batch_reactor,
    flexible_transmission,
    flexible_transmission_prefilter,
    flexible_transmission_reference,
)
from bilevel.ddc.systems import as_tf, num_den
from bilevel.errors import InvalidData


def test_flexible_transmission_models():
    """Landau et al. (1995) / Campi et al. (2002): G = B/A (Ts = 0.05), M_r = (1-a)^2/(z (z-a)^2),
    a = exp(-0.5), unit static gain; L = (1 - M_r) M_r."""
    num, den = num_den(flexible_transmission())
    np.testing.assert_allclose(den, [1, -1.41833, 1.58939, -1.31608, 0.88642])
    np.testing.assert_allclose(num, [0.28261, 0.50666])
    a = np.exp(-0.5)
    reference = flexible_transmission_reference()
    np.testing.assert_allclose(np.sort(reference.poles().real), [0, a, a], atol=1e-6)
    assert control.dcgain(reference) == pytest.approx(1.0)
    z = 0.3 + 0.2j
    m = reference(z)
    assert flexible_transmission_prefilter()(z) == pytest.approx((1 - m) * m)


def test_paper_inputs_and_simulation():
    """Scenario A: u_t = 1 for t in [5, 15]; scenario B: N(0, 1). simulate = python-control from rest."""
    u = paper_input("A", 512)
    assert u.sum() == 11 and u[5] == 1 and u[15] == 1 and u[4] == 0 and u[16] == 0
    np.testing.assert_array_equal(u, step_pulse(512))
    white = paper_input("B", 512, np.random.default_rng(0))
    np.testing.assert_array_equal(white, np.random.default_rng(0).standard_normal(512))
    g = flexible_transmission()
    _, expected = control.forced_response(g, T=np.arange(512) * 0.05, U=white)
    np.testing.assert_allclose(simulate(g, white), expected, atol=1e-9)
    np.testing.assert_allclose(simulate(control.ss(g), white), expected, atol=1e-9)
    with pytest.raises(InvalidData, match="rng"):
        paper_input("B", 10)
    with pytest.raises(InvalidData, match="scenario"):
        paper_input("C", 10)  # type: ignore[arg-type]


def test_batch_reactor_trajectory():
    """Walsh & Ye (2001) batch reactor as printed in the paper's appendix; X is n x (T+1), U is m x T."""
    plant = batch_reactor()
    assert plant.dt == 0.1 and plant.A[0, 0] == 1.178 and plant.B[2, 1] == -0.235
    x, u = batch_reactor_data(15, np.random.default_rng(0), random_x0=True)
    assert x.shape == (4, 16) and u.shape == (2, 15)
    np.testing.assert_allclose(x[:, 1:], plant.A @ x[:, :-1] + plant.B @ u, atol=1e-12)
    x_rest, _ = batch_reactor_data(15, np.random.default_rng(0))
    np.testing.assert_array_equal(x_rest[:, 0], 0.0)
    with pytest.raises(InvalidData, match="shapes"):
        state_trajectory(plant.A, plant.B, np.zeros((3, 5)))


def test_system_coercion():
    """(num, den), TransferFunction and StateSpace give the same monic (num, den); bad input is named."""
    tf = control.tf([2.0, 1.0], [2.0, -1.0, 0.5], 0.1)
    for system in (tf, control.ss(tf), ([2.0, 1.0], [2.0, -1.0, 0.5])):
        num, den = num_den(system)
        np.testing.assert_allclose(den, [1.0, -0.5, 0.25], atol=1e-12)
        np.testing.assert_allclose(num, [1.0, 0.5], atol=1e-12)
    assert as_tf(tf).dt == 0.1 and as_tf(([1.0], [1.0, 0.5])).dt is True
    with pytest.raises(InvalidData, match="discrete-time"):
        num_den(control.tf([1.0], [1.0, 1.0]))
    with pytest.raises(InvalidData, match="SISO"):
        num_den(batch_reactor())
    with pytest.raises(InvalidData, match="NaN"):
        num_den(([np.nan], [1.0]))
    with pytest.raises(InvalidData, match="cannot read"):
        num_den(3.0)  # type: ignore[arg-type]
