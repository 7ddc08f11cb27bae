"""Closed-loop analysis of learned controllers: unit-feedback loops G K (VRFT) and state feedback A + B K (Willems).

Computation returns data objects (python-control's where it has one); ``plot()`` builds a figure without showing it.
"""

from __future__ import annotations

import json
from dataclasses import dataclass

import control
import numpy as np
import scipy.linalg
import scipy.signal
from matplotlib.figure import Figure
from numpy.typing import ArrayLike

from bilevel.errors import InvalidData
from bilevel.ddc.systems import SystemLike, num_den


def _complex_pairs(values: np.ndarray) -> list[list[float]]:
    return [[float(v.real), float(v.imag)] for v in values]


def _pad_to(poly: np.ndarray, size: int) -> np.ndarray:
    return np.concatenate([np.zeros(size - poly.size), poly])


def _loop_polynomials(plant: SystemLike, controller: SystemLike) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(num_G num_K, den_G num_K, characteristic polynomial den_G den_K + num_G num_K)."""
    num_g, den_g = num_den(plant)
    num_k, den_k = num_den(controller)
    loop_num = np.polymul(num_g, num_k)
    char = np.polyadd(np.polymul(den_g, den_k), loop_num)
    nonzero = np.flatnonzero(np.abs(char) > 1e-14 * np.max(np.abs(char)))
    if nonzero.size == 0 or char.size - nonzero[0] < np.polymul(den_g, den_k).size:
        raise InvalidData(
            "the feedback loop is ill-posed: 1 + G K loses degree (G K(inf) = -1); "
            "use a strictly proper plant or controller"
        )
    return loop_num, np.polymul(den_g, num_k), char


def closed_loop_poles(plant: SystemLike, controller: SystemLike) -> np.ndarray:
    """Roots of den_G den_K + num_G num_K: the poles of the unit-feedback loop (no cancellation)."""
    return np.roots(_loop_polynomials(plant, controller)[2])


def closed_loop(plant: SystemLike, controller: SystemLike) -> control.TransferFunction:
    """Complementary sensitivity G K / (1 + G K) from reference to output."""
    loop_num, _, char = _loop_polynomials(plant, controller)
    dt = plant.dt if isinstance(plant, control.lti.LTI) else True
    return control.tf(loop_num, char, dt)


def closed_loop_bode(
    plant: SystemLike, controller: SystemLike, omega: ArrayLike | None = None
) -> control.FrequencyResponseData:
    """Frequency response of G K / (1 + G K) (python-control object: .magnitude, .phase, .omega)."""
    return control.frequency_response(closed_loop(plant, controller), omega)


@dataclass(frozen=True)
class ClosedLoopResponse:
    """Time response of the unit-feedback loop to a reference signal, with its stability summary."""

    time: np.ndarray
    reference: np.ndarray
    output: np.ndarray
    input: np.ndarray
    poles: np.ndarray
    spectral_radius: float
    stable: bool

    def plot(self) -> Figure:
        """Figure with output vs reference and the control input (not shown)."""
        fig = Figure(figsize=(7, 5))
        ax_y, ax_u = fig.subplots(2, 1, sharex=True)
        ax_y.step(self.time, self.reference, where="post", label="reference", linestyle="--")
        ax_y.step(self.time, self.output, where="post", label="output")
        ax_y.set_ylabel("y")
        ax_y.set_title(f"closed loop: spectral radius {self.spectral_radius:.4f}"
                       f" ({'stable' if self.stable else 'unstable'})")
        ax_y.legend()
        ax_u.step(self.time, self.input, where="post")
        ax_u.set_ylabel("u")
        ax_u.set_xlabel("time [s]")
        return fig

    def to_json(self) -> str:
        """JSON text with all fields (poles as [re, im] pairs)."""
        return json.dumps({
            "time": self.time.tolist(),
            "reference": self.reference.tolist(),
            "output": self.output.tolist(),
            "input": self.input.tolist(),
            "poles": _complex_pairs(self.poles),
            "spectral_radius": self.spectral_radius,
            "stable": self.stable,
        })


def closed_loop_response(
    plant: SystemLike, controller: SystemLike, reference: ArrayLike, dt: float | None = None
) -> ClosedLoopResponse:
    """Output y = GK/(1+GK) r and input u = K/(1+GK) r of the loop from rest (exact filtering)."""
    r = np.asarray(reference, dtype=float)
    if r.ndim != 1 or not np.all(np.isfinite(r)):
        raise InvalidData(f"reference must be a finite 1-D signal, got shape {r.shape}")
    loop_num, input_num, char = _loop_polynomials(plant, controller)
    if dt is None:
        dt = plant.dt if isinstance(plant, control.lti.LTI) and plant.dt not in (True, None) else 1.0
    poles = np.roots(char)
    rho = float(np.max(np.abs(poles))) if poles.size else 0.0
    return ClosedLoopResponse(
        time=np.arange(r.size) * float(dt),
        reference=r,
        output=scipy.signal.lfilter(_pad_to(loop_num, char.size), char, r),
        input=scipy.signal.lfilter(_pad_to(input_num, char.size), char, r),
        poles=poles,
        spectral_radius=rho,
        stable=rho < 1,
    )


def closed_loop_step(plant: SystemLike, controller: SystemLike, n: int = 200) -> control.TimeResponseData:
    """Unit-step response of G K / (1 + G K) over n samples, as python-control's TimeResponseData (.time, .outputs).

    Stability is closed_loop_poles'; for the control input or another reference use closed_loop_response.
    """
    if n < 1:
        raise InvalidData(f"the step response needs n >= 1 samples, got n={n}")
    loop = closed_loop(plant, controller)
    return control.step_response(loop, T=np.arange(n) * (1.0 if loop.dt is True else float(loop.dt)))


@dataclass(frozen=True)
class StateFeedbackAnalysis:
    """Closed loop x+ = (A + B K) x + xi: eigenvalues, stability, Gramian and H2 norm from xi."""

    eigenvalues: np.ndarray
    spectral_radius: float
    stable: bool
    gramian: np.ndarray | None
    h2_norm: float

    def to_json(self) -> str:
        """JSON text with all fields (eigenvalues as [re, im] pairs; an unstable loop has h2_norm inf)."""
        return json.dumps({
            "eigenvalues": _complex_pairs(self.eigenvalues),
            "spectral_radius": self.spectral_radius,
            "stable": self.stable,
            "gramian": None if self.gramian is None else self.gramian.tolist(),
            "h2_norm": self.h2_norm if np.isfinite(self.h2_norm) else "inf",
        })


def analyze_state_feedback(
    a: ArrayLike, b: ArrayLike, k: ArrayLike, qx: ArrayLike | None = None, r: ArrayLike | None = None
) -> StateFeedbackAnalysis:
    """Analyse u = K x: h2_norm^2 = trace((Qx + K^T R K) W), W = Acl W Acl^T + I (Qx = I, R = 0 by default)."""
    a, b, k = np.asarray(a, float), np.asarray(b, float), np.atleast_2d(np.asarray(k, float))
    n, m = b.shape
    if a.shape != (n, n) or k.shape != (m, n):
        raise InvalidData(f"shapes disagree: A {a.shape}, B {b.shape}, K {k.shape} (need n x n, n x m, m x n)")
    qx = np.eye(n) if qx is None else np.asarray(qx, float)
    r = np.zeros((m, m)) if r is None else np.asarray(r, float)
    acl = a + b @ k
    eigenvalues = np.linalg.eigvals(acl)
    rho = float(np.max(np.abs(eigenvalues)))
    if rho >= 1:
        return StateFeedbackAnalysis(eigenvalues, rho, False, None, float("inf"))
    gramian = scipy.linalg.solve_discrete_lyapunov(acl, np.eye(n))
    h2 = float(np.sqrt(np.trace((qx + k.T @ r @ k) @ gramian)))
    return StateFeedbackAnalysis(eigenvalues, rho, True, gramian, h2)
