"""Random points inside declared bounds (multistart starts, convexity probes)."""

from __future__ import annotations

import numpy as np


def sample_in_bounds(lb: np.ndarray, ub: np.ndarray, rng: np.random.Generator, scale: float = 10.0) -> np.ndarray:
    """Uniform in finite boxes; lb + |N(0, scale)| / ub - |N(0, scale)| for one-sided; N(0, scale) if free."""
    lb, ub = np.asarray(lb, dtype=float), np.asarray(ub, dtype=float)
    z = rng.standard_normal(lb.shape) * scale
    u = rng.random(lb.shape)
    lo, hi = np.isfinite(lb), np.isfinite(ub)
    flb, fub = np.where(lo, lb, 0.0), np.where(hi, ub, 0.0)
    out = np.where(lo & hi, flb + u * (fub - flb), z)
    out = np.where(lo & ~hi, flb + np.abs(z), out)
    return np.where(~lo & hi, fub - np.abs(z), out)


def default_start(lb: np.ndarray, ub: np.ndarray, start: np.ndarray | None = None) -> np.ndarray:
    """The user's start if given, else the point of the box closest to the origin."""
    return np.clip(np.zeros_like(lb) if start is None else start, lb, ub)
