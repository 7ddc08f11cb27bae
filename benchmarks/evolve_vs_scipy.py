"""evolve against scipy's differential_evolution (updating='deferred', the Willems DE baseline's mode): same algorithm,
other random stream, so the final values should share one distribution. Rastrigin in 8 variables, popsize 5 (40
members), 60 generations, no early stop, 300 seeds each; prints means, medians, Mann-Whitney U and KS p-values.
"""

from __future__ import annotations

import time

import numpy as np
import scipy.optimize
import scipy.stats

from bilevel.solvers.evolution import evolve

N, GENERATIONS, SEEDS = 8, 60, 300


def rastrigin(xs: np.ndarray) -> np.ndarray:
    """Rastrigin's function at the columns of xs."""
    return 10 * xs.shape[0] + np.sum(xs ** 2 - 10 * np.cos(2 * np.pi * xs), axis=0)


def main() -> None:
    print(f"# evolve_vs_scipy.py -- {time.strftime('%Y-%m-%d %H:%M:%S UTC', time.gmtime())}")
    lb, ub = -5.12 * np.ones(N), 5.12 * np.ones(N)
    ours = [evolve(rastrigin, lb, ub, np.random.default_rng(s), GENERATIONS, 5, 0.0, vectorized=True).fun
            for s in range(SEEDS)]
    theirs = [scipy.optimize.differential_evolution(rastrigin, list(zip(lb, ub)), maxiter=GENERATIONS, popsize=5,
                                                    tol=0.0, polish=False, rng=np.random.default_rng(10_000 + s),
                                                    vectorized=True, updating="deferred").fun for s in range(SEEDS)]
    print(f"final value mean: evolve {np.mean(ours):.3f}, scipy {np.mean(theirs):.3f}; median {np.median(ours):.3f}, "
          f"{np.median(theirs):.3f}; Mann-Whitney U p = {scipy.stats.mannwhitneyu(ours, theirs).pvalue:.2f}, "
          f"KS p = {scipy.stats.ks_2samp(ours, theirs).pvalue:.2f} ({SEEDS} seeds each)")


if __name__ == "__main__":
    main()
