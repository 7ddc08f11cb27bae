"""SISO discrete-time system descriptions: coercion to (num, den) polynomials and exact arithmetic.

A system may be given as a python-control ``TransferFunction`` or ``StateSpace`` or as a
``(num, den)`` pair of coefficient sequences in descending powers of z.
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
