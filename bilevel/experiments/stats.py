"""Confidence intervals for sweep summaries: Wilson intervals for rates, t intervals for means."""

from __future__ import annotations

import numpy as np
from scipy import stats


def wilson_interval(successes: int, n: int, level: float = 0.95) -> tuple[float, float]:
    """Wilson score interval for a binomial proportion (well behaved at 0 and n successes)."""
    if n == 0:
        return (float("nan"), float("nan"))
    z = stats.norm.ppf(0.5 + level / 2)
    p = successes / n
    centre = (p + z * z / (2 * n)) / (1 + z * z / n)
    half = z * np.sqrt(p * (1 - p) / n + z * z / (4 * n * n)) / (1 + z * z / n)
    return (max(0.0, centre - half), min(1.0, centre + half))


def mean_interval(values: np.ndarray, level: float = 0.95) -> tuple[float, float, float]:
    """(mean, low, high): Student-t confidence interval of the mean."""
    values = np.asarray(values, dtype=float)
    values = values[np.isfinite(values)]
    if values.size == 0:
        return (float("nan"),) * 3
    m = float(values.mean())
    if values.size == 1:
        return (m, m, m)
    half = float(stats.t.ppf(0.5 + level / 2, values.size - 1) * values.std(ddof=1) / np.sqrt(values.size))
    return (m, m - half, m + half)


def median_interval(values: np.ndarray, level: float = 0.95) -> tuple[float, float, float]:
    """(median, low, high): the distribution-free interval of the median from order statistics (binomial(n, 1/2)
    ranks, at least `level` coverage; (-inf, inf) when n is too small for any); values may hold +inf."""
    values = np.sort(np.asarray(values, dtype=float))
    values = values[~np.isnan(values)]
    n = values.size
    if n == 0:
        return (float("nan"),) * 3
    median = float(np.median(values)) if np.isfinite(values[(n - 1) // 2]) and np.isfinite(values[n // 2]) \
        else float("inf")
    k = int(stats.binom.ppf((1 - level) / 2, n, 0.5))  # the largest k with P(B <= k - 1) <= (1 - level) / 2
    if k == 0:
        return (median, -float("inf"), float("inf"))
    return (median, float(values[k - 1]), float(values[n - k]))
