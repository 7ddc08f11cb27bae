"""Robust stability of a polynomial affine in parameters over a set, by zero exclusion on the unit circle.

p(z; d) = p0(z) + d' s(z) (coefficients highest power first) with d in a convex symmetric set D given by its support
function h(w) = max_{d in D} w'd. If p(.; 0) is Schur stable, the leading coefficient never vanishes on D and
p(z; d) != 0 for every |z| = 1 and d in D, every p(.; d) is Schur stable (the roots move continuously on the connected
D and cannot cross the circle). At z, the image {p(z; d)} is a convex set in C = R^2 whose distance from 0 is at
least u'p0(z) - h(S_z' u) for every unit u (S_z = [Re s(z), Im s(z)]'), each u a valid bound; between grid points
the image moves by at most |dp/dw| <= sum_m m (|c_m(0)| + h(+-e_m)) per radian, so a grid of spacing g is rigorous
where every grid point's distance exceeds that bound times g / 2.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Callable

import numpy as np

Support = Callable[[np.ndarray], np.ndarray]
"""h(W) for the columns w of W (k x m) -> (m,) support values of D."""


@dataclass(frozen=True)
class Sweep:
    """The sweep's outcome: the smallest guaranteed distance of 0 from the image over the circle (positive: zero
    excluded), the smallest grid distance, the Lipschitz bound, the grid spacing and the leading coefficient's
    smallest modulus over D."""

    excluded_by: float
    smallest_distance: float
    lipschitz: float
    spacing: float
    leading: float

    @property
    def proven(self) -> bool:
        return self.excluded_by > 0 and self.leading > 0


def sweep(base: np.ndarray, slopes: np.ndarray, support: Support, points: int, angles: int) -> Sweep:
    """Zero exclusion (module docstring) for p0 = base (n+1,), s = slopes (k, n+1), on `points` frequencies in
    [0, pi] (real coefficients: the lower half circle mirrors the upper), each with `angles` directions u spread over
    [-pi/2, pi/2] around arg p0(z)."""
    base, slopes = np.asarray(base, float), np.asarray(slopes, float)
    degree = base.size - 1
    width = support(np.hstack([slopes, -slopes]))  # h(+-e_m) of each coefficient
    spread = np.maximum(width[:degree + 1], width[degree + 1:])
    powers = np.arange(degree, -1, -1)
    lipschitz = float(np.sum(powers * (np.abs(base) + spread)))
    leading = float(abs(base[0]) - spread[0])
    w = np.linspace(0.0, np.pi, points)
    z = np.exp(1j * w)
    vander = z[:, None] ** powers[None, :]
    p0 = vander @ base
    s = vander @ slopes.T  # (points, k)
    offsets = np.linspace(-0.5 * np.pi, 0.5 * np.pi, angles)
    best = np.full(points, -np.inf)
    phase = np.angle(p0)
    for off in offsets:
        u = np.exp(1j * (phase + off))
        directions = (s.real * u.real[:, None] + s.imag * u.imag[:, None]).T  # S_z' u, (k, points)
        best = np.maximum(best, (p0.real * u.real + p0.imag * u.imag) - support(directions))
    spacing = float(w[1] - w[0])
    return Sweep(float(np.min(best) - lipschitz * spacing / 2), float(np.min(best)), lipschitz, spacing, leading)
