"""Time the VRFT fit (structured regressor + QR least squares) on the flexible transmission against N.

For each N prints the median wall time of the full ``fit_vrft`` call (validation, operators,
python-control controller object) and of its numerical core (Phi(y), L u, QR least squares on a
prebuilt regressor), each as t(N)/t(512) next to the N and N log N ratios (baseline: the N = 512
run in the same process). Asserts nothing.
"""

from __future__ import annotations

import statistics
import time
from collections.abc import Callable

import numpy as np

from bilevel.ddc import (
    fit_vrft,
    flexible_transmission,
    flexible_transmission_basis,
    flexible_transmission_prefilter,
    flexible_transmission_reference,
    least_squares,
    simulate,
    vrft_regressor,
    white_noise,
)

SIZES = (512, 2048, 8192, 32768, 65536)


def median_time(work: Callable[[], object], repeats: int) -> float:
    """Median wall time of `repeats` calls of work()."""
    times = []
    for _ in range(repeats):
        start = time.perf_counter()
        work()
        times.append(time.perf_counter() - start)
    return statistics.median(times)


def time_size(n: int, repeats: int, seed: int = 0) -> tuple[float, float]:
    """(full fit, numerical core) median times on noise-free white-input data of length n."""
    u = white_noise(n, np.random.default_rng(seed))
    y = simulate(flexible_transmission(), u)
    reference, basis = flexible_transmission_reference(), flexible_transmission_basis()
    prefilter = flexible_transmission_prefilter()
    regressor = vrft_regressor(reference, basis, prefilter)
    full = median_time(lambda: fit_vrft(u, y, reference, basis, prefilter=prefilter), repeats)
    core = median_time(lambda: least_squares(regressor(y), regressor.targets(u)), repeats)
    return full, core


def main() -> None:
    """Run the sweep and print one line per size."""
    time_size(SIZES[0], 5)  # warm-up (imports, caches)
    results = {n: time_size(n, 51 if n <= 8192 else 21) for n in SIZES}
    base_full, base_core = results[SIZES[0]]
    print(f"{'N':>6} {'fit [ms]':>9} {'fit ratio':>9} {'core [ms]':>9} {'core ratio':>10}"
          f" {'N ratio':>8} {'NlogN ratio':>11}")
    for n, (full, core) in results.items():
        nlogn = n * np.log(n) / (SIZES[0] * np.log(SIZES[0]))
        print(f"{n:>6} {1e3 * full:>9.3f} {full / base_full:>9.2f} {1e3 * core:>9.3f}"
              f" {core / base_core:>10.2f} {n / SIZES[0]:>8.1f} {nlogn:>11.1f}")


if __name__ == "__main__":
    main()
