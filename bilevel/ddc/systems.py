"""Discrete-time system descriptions: SISO systems coerced to (num, den) polynomials with exact arithmetic, and
state-feedback plants coerced to checked (A, B) matrices.

A SISO system may be given as a python-control ``TransferFunction`` or ``StateSpace`` or as a
``(num, den)`` pair of coefficient sequences in descending powers of z; a state-feedback plant as a
``StateSpace`` whose outputs are its states or as an ``(A, B)`` pair.
"""

from __future__ import annotations

from typing import Union

import control
import numpy as np
from numpy.typing import ArrayLike

from bilevel.errors import InvalidData

SystemLike = Union[control.TransferFunction, control.StateSpace, tuple[ArrayLike, ArrayLike]]


def _strip(poly: np.ndarray) -> np.ndarray:
    nonzero = np.flatnonzero(poly)
    return poly[nonzero[0]:] if nonzero.size else np.zeros(1)


def num_den(system: SystemLike) -> tuple[np.ndarray, np.ndarray]:
    """Numerator and monic denominator of a SISO system, descending powers of z, leading zeros stripped."""
    if isinstance(system, control.StateSpace):
        system = control.ss2tf(system)
    if isinstance(system, control.TransferFunction):
        if system.ninputs != 1 or system.noutputs != 1:
            raise InvalidData(
                f"expected a SISO system, got {system.noutputs} outputs x {system.ninputs} inputs; "
                "pass one channel, e.g. sys[0, 0]"
            )
        if system.isctime(strict=True):
            raise InvalidData(
                "expected a discrete-time system, got a continuous-time one; "
                "discretize it first, e.g. control.c2d(sys, Ts)"
            )
        num_list, den_list = control.tfdata(system)
        num, den = num_list[0][0], den_list[0][0]
    else:
        try:
            num, den = system
        except (TypeError, ValueError):
            raise InvalidData(
                f"cannot read a SISO system from {type(system).__name__}; pass a "
                "control.TransferFunction, control.StateSpace or a (num, den) pair"
            ) from None
    num = np.atleast_1d(np.asarray(num, dtype=float)).ravel()
    den = np.atleast_1d(np.asarray(den, dtype=float)).ravel()
    if not (np.all(np.isfinite(num)) and np.all(np.isfinite(den))):
        raise InvalidData("system coefficients contain NaN or inf; pass finite polynomials")
    num, den = _strip(num), _strip(den)
    if not np.any(den):
        raise InvalidData("system denominator is identically zero; pass a nonzero denominator")
    return num / den[0], den / den[0]


def series(*systems: SystemLike) -> tuple[np.ndarray, np.ndarray]:
    """(num, den) of the product of SISO systems, by exact polynomial multiplication (no cancellation)."""
    num, den = np.ones(1), np.ones(1)
    for system in systems:
        n, d = num_den(system)
        num, den = np.polymul(num, n), np.polymul(den, d)
    return num, den


def as_tf(system: SystemLike, dt: float | bool | None = None) -> control.TransferFunction:
    """The system as a python-control TransferFunction; dt defaults to the system's own, else True."""
    if dt is None:
        dt = system.dt if isinstance(system, control.lti.LTI) else True
    num, den = num_den(system)
    return control.tf(num, den, dt)


StatePlantLike = Union[control.StateSpace, tuple[ArrayLike, ArrayLike]]
"""A plant whose states are measured: a discrete-time python-control StateSpace with C = I and D = 0, or (A, B)."""


def state_matrices(plant: StatePlantLike) -> tuple[np.ndarray, np.ndarray]:
    """(A, B) of a state-feedback plant x_{t+1} = A x_t + B u_t, checked: discrete time, states measured, finite."""
    if isinstance(plant, control.StateSpace):
        if plant.isctime(strict=True):
            raise InvalidData("expected a discrete-time plant, got a continuous-time StateSpace; "
                              "discretize it first, e.g. control.c2d(sys, Ts)")
        n = plant.nstates
        if plant.C.shape != (n, n) or not np.array_equal(plant.C, np.eye(n)) or np.any(plant.D):
            raise InvalidData(f"the state-feedback learner measures the states: the plant needs C = I ({n} x {n}) and "
                              f"D = 0, got C of shape {plant.C.shape} and max |D| = {np.max(np.abs(plant.D)):g}; pass "
                              "a realization whose outputs are its states, e.g. control.ss(A, B, np.eye(n), 0, dt), "
                              "or the pair (A, B)")
        a, b = plant.A, plant.B
    elif isinstance(plant, control.lti.LTI):
        raise InvalidData(f"expected a StateSpace or an (A, B) pair, got a {type(plant).__name__}; convert it with "
                          "control.ss(sys) and check that its states are what you measure (C = I)")
    else:
        try:
            a, b = plant
            a, b = np.asarray(a, dtype=float), np.asarray(b, dtype=float)
        except (TypeError, ValueError):
            raise InvalidData(f"cannot read (A, B) from {type(plant).__name__}; pass a discrete-time "
                              "control.StateSpace with C = I, D = 0 or a pair of real arrays (A, B)") from None
    a, b = np.asarray(a, dtype=float), np.asarray(b, dtype=float)
    b = b.reshape(-1, 1) if b.ndim == 1 else b
    if a.ndim != 2 or a.shape[0] != a.shape[1] or b.ndim != 2 or b.shape[0] != a.shape[0] or not a.size or not b.size:
        raise InvalidData(f"(A, B) must be n x n and n x m; got A {a.shape} and B {b.shape}")
    if not (np.all(np.isfinite(a)) and np.all(np.isfinite(b))):
        raise InvalidData("the plant's A or B contains NaN or inf; pass finite matrices")
    return a, b
