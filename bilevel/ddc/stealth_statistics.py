"""The statistics of Russo & Proutiere's stealthy attack on least-squares identification, with their exact Jacobians.

Russo & Proutiere, "Analysis and Detectability of Offline Data Poisoning Attacks on Linear Systems", L4DC 2023
(arXiv 2211.08804), section 5 (the stealthy attack), as their code computes it (rssalessio/data-poisoning-linear-
systems, example_stealthy_attack/algorithm.py, ComputeAttack._compute_problem; utils.correlate). For the model
Y ~ theta Z with residuals E = Y - theta Z (n x N) and E_r = Y - theta_r Z_r of the model without the input rows:

- r = ||E||_F^2, the residual energy (their c_r = r' / r);
- Z_d = ||E_r||_F^2 / ||E||_F^2 - 1, the input-removed residual energy (their c_z = Z_d' / Z_d);
- f_tau = ||C_tau C_0^{-1}||_F^2, tau = 1..s, with C_tau = (1/N) sum_{t=0}^{N-1-tau} e_t e_{t+tau}' (note the order:
  the transpose of bilevel.ddc.residual_tests.autocovariances' R_tau) and s = 2 floor(0.025 N) (their c_c).

`StealthStatistics` evaluates [r, Z_d, f_1..f_s] and their Jacobian in (Y, Z, theta, theta_r) at once: one inverse of
C_0 per point, the lagged products shared, each derivative by a few n x n and n x N products (below). It is the
attack's code; bilevel.ddc.stealth_check re-computes the same statistics independently for the verdict.

Derivatives: with P = C_0^{-1} and M = C_tau P, d f_tau = <G_tau, dC_tau> + <G_0, dC_0> with G_tau = 2 M P and
G_0 = -2 P C_tau' M P; C_tau = A B' / N (A = E[:, :N-tau], B = E[:, tau:]) gives d/dA = G_tau B / N and d/dB =
G_tau' A / N; C_0 = E E' / N gives d/dE = (G_0 + G_0') E / N. Through E = Y - theta Z: d/dY = g, d/dtheta = -g Z',
d/dZ = -theta' g (and the same for E_r on the kept rows of Z).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any, Callable

import casadi as ca
import numpy as np

from ..errors import InvalidData

NAMES = ("residuals", "zd")
"""The statistics before the lags, in output order; the lags follow as correlation_1..correlation_s."""


def authors_lags(N: int) -> int:
    """s = 2 floor(0.025 N), the number of lags of the authors' correlation constraints (algorithm.py: num_lags =
    int(0.025 T), s = 2 num_lags)."""
    return 2 * math.floor(0.025 * N)


def statistic_names(lags: int) -> tuple[str, ...]:
    """The names of the outputs of StealthStatistics with `lags` lags."""
    return NAMES + tuple(f"correlation_{tau}" for tau in range(1, lags + 1))


@dataclass(frozen=True)
class StealthStatistics:
    """[r, Z_d, f_1..f_s] of Y (n x N) ~ theta Z (k x N) and of Y ~ theta_r Z[keep] (module docstring)."""

    n: int
    k: int
    N: int
    keep: tuple[int, ...]
    lags: int

    def __post_init__(self) -> None:
        if not 0 < self.lags < self.N - self.k or not 0 < len(self.keep) < self.k:
            raise InvalidData(f"stealth statistics: need 0 < lags < N - k and 0 < kept rows < k, got lags {self.lags},"
                              f" N {self.N}, k {self.k}, {len(self.keep)} kept rows: record a longer experiment")

    @property
    def size(self) -> int:
        """The number of statistics, 2 + lags."""
        return 2 + self.lags

    def evaluate(self, Y: np.ndarray, Z: np.ndarray, theta: np.ndarray, theta_r: np.ndarray,
                 jacobian: bool = False) -> tuple[np.ndarray, tuple[np.ndarray, ...] | None]:
        """The statistics, and with jacobian their derivatives in (Y, Z, theta, theta_r) as arrays of shape
        (size, *input shape) (row i: the gradient of statistic i)."""
        N, keep = self.N, list(self.keep)
        Zr = Z[keep]
        E, Er = Y - theta @ Z, Y - theta_r @ Zr
        r, rr, P, C, M = _parts(E, Er, self.lags, lambda A: float(np.sum(A * A)), np.linalg.inv)
        values = np.array([r, rr / r - 1.0, *(float(np.sum(m * m)) for m in M)])
        if not jacobian:
            return values, None
        gE = np.zeros((self.size, self.n, N))
        gE[0] = 2 * E
        gE[1] = -2 * rr / r ** 2 * E
        for i, (t, c, m) in enumerate(zip(range(1, self.lags + 1), C, M), start=2):
            g = 2 * m @ P
            g0 = -2 * P @ c.T @ m @ P
            gE[i] = (g0 + g0.T) @ E / N
            gE[i, :, :N - t] += g @ E[:, t:] / N
            gE[i, :, t:] += g.T @ E[:, :N - t] / N
        gEr = 2 * Er / r
        dY = gE.copy()
        dY[1] += gEr
        dZ = -np.einsum("ak,iaN->ikN", theta, gE)
        dZ[1, keep] -= theta_r.T @ gEr
        dtheta = -np.einsum("iaN,kN->iak", gE, Z)
        dtheta_r = np.zeros((self.size, *theta_r.shape))
        dtheta_r[1] = -gEr @ Zr.T
        return values, (dY, dZ, dtheta, dtheta_r)

    def expression(self, Y: ca.SX | ca.MX, Z: ca.SX | ca.MX, theta: ca.SX | ca.MX, theta_r: ca.SX | ca.MX
                   ) -> ca.SX | ca.MX:
        """[r, Z_d, f_1..f_s] as a CasADi column of expressions (SX or MX) of (Y, Z, theta, theta_r): the same
        formulas as evaluate (_parts), for a compiled problem whose derivatives CasADi takes (method reduced with
        compiled=True)."""
        Zr = Z[list(self.keep), :]
        E, Er = Y - ca.mtimes(theta, Z), Y - ca.mtimes(theta_r, Zr)
        r, rr, _, _, M = _parts(E, Er, self.lags, ca.sumsqr, ca.inv)
        return ca.vertcat(r, rr / r - 1.0, *(ca.sumsqr(m) for m in M))


def _parts(E: Any, Er: Any, lags: int, sumsq: Callable[[Any], Any], inv: Callable[[Any], Any]) -> tuple[Any, ...]:
    """(r, ||E_r||_F^2, P = C_0^{-1}, [C_1..C_s], [C_tau P]) of residuals E, E_r (n x N), numpy arrays or CasADi
    expressions alike (sumsq and inv of their kind; @ and slicing are shared): the one definition of the statistics."""
    N = E.shape[1]
    P = inv(E @ E.T / N)
    C = [E[:, :N - t] @ E[:, t:].T / N for t in range(1, lags + 1)]
    return sumsq(E), sumsq(Er), P, C, [c @ P for c in C]
