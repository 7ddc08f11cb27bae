"""Benchmark plants and design models of the paper: flexible transmission (VRFT) and batch reactor (Willems)."""

from __future__ import annotations

import control
import numpy as np

FLEXIBLE_TRANSMISSION_DT = 0.05
BATCH_REACTOR_DT = 0.1


def flexible_transmission() -> control.TransferFunction:
    """Landau et al. (1995) flexible transmission, Ts = 0.05: G = B(z)/A(z) as in Campi et al. (2002)."""
    return control.tf(
        [0.28261, 0.50666],
        [1.0, -1.41833, 1.58939, -1.31608, 0.88642],
        FLEXIBLE_TRANSMISSION_DT,
    )


def flexible_transmission_reference(bandwidth: float = 10.0) -> control.TransferFunction:
    """Reference model M_r = (1-a)^2 / (z (z-a)^2), a = exp(-Ts * bandwidth) (a = exp(-0.5) by default)."""
    a = float(np.exp(-FLEXIBLE_TRANSMISSION_DT * bandwidth))
    return control.tf([(1 - a) ** 2], [1.0, -2 * a, a * a, 0.0], FLEXIBLE_TRANSMISSION_DT)


def flexible_transmission_prefilter(bandwidth: float = 10.0) -> control.TransferFunction:
    """VRFT prefilter L = (1 - M_r) M_r (Campi et al. 2002, white input: Phi_u = 1)."""
    reference = flexible_transmission_reference(bandwidth)
    return (1 - reference) * reference


def batch_reactor() -> control.StateSpace:
    """Walsh & Ye (2001) batch reactor, Ts = 0.1, as printed in the paper's appendix; C = I, D = 0."""
    a = np.array(
        [
            [1.178, 0.001, 0.511, -0.403],
            [-0.051, 0.661, -0.011, 0.061],
            [0.076, 0.335, 0.560, 0.382],
            [0.0, 0.335, 0.089, 0.849],
        ]
    )
    b = np.array(
        [
            [0.004, -0.087],
            [0.467, 0.001],
            [0.213, -0.235],
            [0.213, -0.016],
        ]
    )
    return control.ss(a, b, np.eye(4), np.zeros((4, 2)), BATCH_REACTOR_DT)
