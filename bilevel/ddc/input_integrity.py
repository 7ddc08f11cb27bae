"""The defender's input-integrity check: does a recorded input match the spectrum of the excitation it was designed as?

Statistic: the Whittle deviance D = sum_k (r_k - 1 - log r_k), r_k = I(w_k) / S(w_k), of the periodogram I of the
recorded input against its known spectrum S at the Fourier frequencies 0 < w_k < pi where S is not negligible (per
input channel, summed). D >= 0, zero when the periodogram equals the spectrum; for a Gaussian input of spectrum S the
r_k are about i.i.d. Exp(1). It sees both a changed power and a changed colour; its threshold is calibrated on clean
data sets (bilevel.experiments.defenses_detection), not taken from an asymptotic law.
"""

from __future__ import annotations

import numpy as np

from ..errors import InvalidData
from .systems import SystemLike, num_den

NEGLIGIBLE = 1e-6
"""Frequencies where S is below this fraction of its maximum are left out (a zero of the prefilter, e.g. at w = 0)."""


def filtered_white_spectrum(system: SystemLike | None, n: int, std: float = 1.0) -> np.ndarray:
    """S(w_k) = std^2 |H(e^{j w_k})|^2 at w_k = 2 pi k / n, k = 0..n//2 (H = 1 for None: white noise)."""
    w = 2 * np.pi * np.arange(n // 2 + 1) / n
    if system is None:
        return np.full(w.size, std ** 2)
    num, den = num_den(system)
    z = np.exp(1j * w)
    return std ** 2 * np.abs(np.polyval(num, z) / np.polyval(den, z)) ** 2


def whittle_deviance(u: np.ndarray, spectrum: np.ndarray) -> float:
    """D of the recorded input u (n samples, or channels x n) against the spectrum at its rfft frequencies."""
    u = np.atleast_2d(np.asarray(u, dtype=float))
    n = u.shape[1]
    if spectrum.shape != (n // 2 + 1,) or not np.all(np.isfinite(u)):
        raise InvalidData(f"input integrity: u must be finite with n = {n} samples and the spectrum n // 2 + 1 = "
                          f"{n // 2 + 1} values, got {spectrum.shape}")
    k = np.arange(1, (n - 1) // 2 + 1)
    k = k[spectrum[k] > NEGLIGIBLE * spectrum.max()]
    periodogram = np.abs(np.fft.rfft(u, axis=1)[:, k]) ** 2 / n
    r = periodogram / spectrum[k]
    return float(np.sum(r - 1 - np.log(np.maximum(r, 1e-300))))
