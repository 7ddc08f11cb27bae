"""Robust stability of a polynomial affine in parameters over a set, by zero exclusion on the unit circle.

p(z; d) = p0(z) + d' s(z) (coefficients highest power first) with d in a convex set D containing 0 given by its
support function h(w) = max_{d in D} w'd (D need not be symmetric). If p(.; 0) is Schur stable, the leading
coefficient never vanishes on D and p(z; d) != 0 for every |z| = 1 and d in D, every p(.; d) is Schur stable (the roots
move continuously on the connected D and cannot cross the circle). At z, the image {p(z; d)} is a convex set in C = R^2
whose distance from 0 is at least u'p0(z) - h(-S_z' u) for every unit u (S_z = [Re s(z), Im s(z)]'; the smallest of
u'p(z; d) = u'p0(z) + (S_z' u)'d over D), each u a valid bound; between grid points the image moves by at most
L = sum_m m (|c_m(0)| + h(+-e_m)) per radian, so on [w_i, w_i+1] the distance is at least (b_i + b_i+1 - L (w_i+1 -
w_i)) / 2 for grid distances b_i, b_i+1. An interval whose bound is below KEEP times its ends' smaller distance while
both ends exclude zero is split into SPLIT pieces, up to DEPTH times (the fine grid is only
needed where the loop comes closest to the circle).
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
    excluded), the smallest grid distance, the Lipschitz bound, the coarse grid's spacing, the leading coefficient's
    smallest modulus over D and how many intervals were split."""

    excluded_by: float
    smallest_distance: float
    lipschitz: float
    spacing: float
    leading: float
    refined: int = 0
    nominal: float = float("nan")
    """The largest root modulus of p(.; 0) (np.roots): zero exclusion proves stability only from a stable member."""

    @property
    def proven(self) -> bool:
        return self.excluded_by > 0 and self.leading > 0 and self.nominal < 1


SPLIT = 16
DEPTH = 3
KEEP = 0.25


def sweep(base: np.ndarray, slopes: np.ndarray, support: Support, points: int, angles: int) -> Sweep:
    """Zero exclusion (module docstring) for p0 = base (n+1,), s = slopes (k, n+1), on `points` frequencies in
    [0, pi] (real coefficients: the lower half circle mirrors the upper), each with `angles` directions u spread over
    [-pi/2, pi/2] around arg p0(z), intervals split where the coarse grid's bound is not enough."""
    base, slopes = np.asarray(base, float), np.asarray(slopes, float)
    degree = base.size - 1
    width = support(np.hstack([slopes, -slopes]))  # h(+-e_m) of each coefficient
    spread = np.maximum(width[:degree + 1], width[degree + 1:])
    powers = np.arange(degree, -1, -1)
    lipschitz = float(np.sum(powers * (np.abs(base) + spread)))
    leading = float(abs(base[0]) - spread[0])
    distance = lambda w: _distances(base, slopes, support, powers, w, angles)  # noqa: E731
    w = np.linspace(0.0, np.pi, points)
    b = distance(w)
    lo, hi, b_lo, b_hi = w[:-1], w[1:], b[:-1], b[1:]
    smallest, settled, refined = float(np.min(b)), [], 0
    for level in range(DEPTH + 1):
        bound = 0.5 * (b_lo + b_hi - lipschitz * (hi - lo))
        split = (bound <= KEEP * np.minimum(b_lo, b_hi)) & (b_lo > 0) & (b_hi > 0) if level < DEPTH else \
            np.zeros(bound.size, bool)
        settled.append(bound[~split])
        if not split.any():
            break
        refined += int(split.sum())
        grid = lo[split, None] + (hi - lo)[split, None] * np.linspace(0.0, 1.0, SPLIT + 1)[None, :]
        inner = distance(grid[:, 1:-1].ravel()).reshape(-1, SPLIT - 1)
        smallest = min(smallest, float(np.min(inner)))
        ends = np.hstack([b_lo[split, None], inner, b_hi[split, None]])
        lo, hi, b_lo, b_hi = grid[:, :-1].ravel(), grid[:, 1:].ravel(), ends[:, :-1].ravel(), ends[:, 1:].ravel()
    nominal = float(np.max(np.abs(np.roots(base)), initial=0.0)) if base[0] != 0 else float("inf")
    return Sweep(float(min(np.min(x) for x in settled if x.size)), smallest, lipschitz, float(w[1] - w[0]), leading,
                 refined, nominal)


def _distances(base: np.ndarray, slopes: np.ndarray, support: Support, powers: np.ndarray, w: np.ndarray,
               angles: int) -> np.ndarray:
    """At each frequency w, the best of `angles` lower bounds u'p0(z) - h(-S_z' u) on the image's distance from 0."""
    best = np.full(w.size, -np.inf)
    for level, directions in _directions(base, slopes, powers, w, angles):
        best = np.maximum(best, level - support(-directions))
    return best


def _directions(base: np.ndarray, slopes: np.ndarray, powers: np.ndarray, w: np.ndarray, angles: int):
    """Per offset of u from arg p0(z) (`angles` of them over [-pi/2, pi/2]): (u'p0(z), S_z' u) at each frequency w,
    the level (points,) and the directions S_z' u (k, points) of the bound u'p0(z) - h(-S_z' u)."""
    z = np.exp(1j * w)
    vander = z[:, None] ** powers[None, :]
    p0 = vander @ base
    s = vander @ slopes.T  # (points, k)
    phase = np.angle(p0)
    for off in np.linspace(-0.5 * np.pi, 0.5 * np.pi, angles):
        u = np.exp(1j * (phase + off))
        yield p0.real * u.real + p0.imag * u.imag, (s.real * u.real[:, None] + s.imag * u.imag[:, None]).T


def closest(base: np.ndarray, slopes: np.ndarray, support: Support, points: int, angles: int, count: int,
            spread: int = 1) -> tuple[np.ndarray, list[tuple[int, int]]]:
    """The directions -S_z' u (k, m) (those the support function is taken along) deciding the sweep where it comes
    closest to excluding nothing: at the `count`
    frequencies of `points` in [0, pi] with the smallest local minima of the distance bound, the best of `angles`
    directions u and its `spread` neighbours on each side (any direction is valid to bound along; these are the ones
    that matter), with each one's (frequency index, angle index): the direction depends on nothing else."""
    base, slopes = np.asarray(base, float), np.asarray(slopes, float)
    powers = np.arange(base.size - 1, -1, -1)
    w = np.linspace(0.0, np.pi, points)
    found = list(_directions(base, slopes, powers, w, angles))
    bounds = np.array([level - support(-directions) for level, directions in found])  # (angles, points)
    best = bounds.max(axis=0)
    inner = np.r_[True, best[1:] < best[:-1]] & np.r_[best[:-1] <= best[1:], True]
    picked = [i for i in np.argsort(best) if inner[i]][:count]
    keys = []
    for i in picked:
        a = int(np.argmax(bounds[:, i]))
        keys += [(int(i), j) for j in range(max(a - spread, 0), min(a + spread, angles - 1) + 1)]
    return -np.array([found[j][1][:, i] for i, j in keys]).reshape(-1, slopes.shape[0]).T, keys
