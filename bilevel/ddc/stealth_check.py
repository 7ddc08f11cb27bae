"""An independent numpy check of Russo & Proutiere's stealth constraints on poisoned state-space data.

The constraints of their stealthy attack (L4DC 2023, arXiv 2211.08804, section 5; their code:
rssalessio/data-poisoning-linear-systems, example_stealthy_attack/algorithm.py, ComputeAttack._compute_problem), for
clean data (X: n x (T+1), U: m x T) and poisoned data (X + dX, U + dU), [A B] fitted by least squares:

- c_r = ||E'||_F^2 / ||E||_F^2 (E: the residuals X+ - [A B] [X; U]), |1 - c_r| <= delta;
- c_z = Z_d' / Z_d with Z_d = ||E_2||_F^2 / ||E||_F^2 - 1 (E_2: the residuals of X+ ~ A X, the input removed),
  |1 - c_z| <= delta;
- c_x = ||dX||_F / ||X||_F <= delta and c_u = ||dU||_F / ||U||_F <= delta;
- c_tau = ||C'_tau C'_0^-1||_F^2 / ||C_tau C_0^-1||_F^2 with C_tau = (1/T) sum_{t=0}^{T-1-tau} e_t e_{t+tau}',
  |1 - c_tau| <= delta for every tau = 1..s, s = 2 floor(0.025 T);
- every entry of dX and dU in [-box, box] (their SLSQP's bounds, box = 0.5).

Nothing here calls the attack's code (bilevel.ddc.stealth_statistics): the fits are numpy lstsq, the correlations
explicit index sums over t (einsum), so the verdict is a second computation of the same definitions.
"""

from __future__ import annotations

import numpy as np

from ..errors import InvalidData

BOX = 0.5
"""The authors' bound on every entry of dX and dU (their SLSQP's bounds)."""
CHECK_TOL = 1e-6
"""check_stealth's slack on every constraint (a solver's tolerance)."""


def _residuals(target: np.ndarray, regressors: np.ndarray) -> np.ndarray:
    coef = np.linalg.lstsq(regressors.T, target.T, rcond=None)[0]
    return target - coef.T @ regressors


def correlations(E: np.ndarray, lags: int) -> list[np.ndarray]:
    """C_0..C_lags of residuals E (n x T), C_tau = (1/T) sum_t e_t e_{t+tau}' (the authors' utils.correlate)."""
    T = E.shape[1]
    return [np.einsum("it,jt->ij", E[:, :T - tau], E[:, tau:]) / T for tau in range(lags + 1)]  # sum_t e_t e_{t+tau}'


def statistics(X: np.ndarray, U: np.ndarray, lags: int) -> dict[str, object]:
    """The authors' statistics of data (X, U): residual energy r, Z_d, [||C_tau C_0^-1||_F^2 for tau = 1..lags] and
    the fitted [A B]."""
    Y, Zx = X[:, 1:], X[:, :-1]
    D = np.vstack([Zx, U])
    E, E2 = _residuals(Y, D), _residuals(Y, Zx)
    r = float(np.sum(E ** 2))
    C = correlations(E, lags)
    C0inv = np.linalg.inv(C[0])
    AB = np.linalg.lstsq(D.T, Y.T, rcond=None)[0].T
    return {"r": r, "zd": float(np.sum(E2 ** 2)) / r - 1.0,
            "correlation": [float(np.linalg.norm(C[tau] @ C0inv, "fro") ** 2) for tau in range(1, lags + 1)],
            "AB": AB}


def check_stealth(X: np.ndarray, U: np.ndarray, dX: np.ndarray, dU: np.ndarray, delta: float, box: float = BOX,
                  tol: float = CHECK_TOL) -> dict[str, object]:
    """Every authors' constraint on the poisoning (dX, dU) of (X, U) (module docstring): the ratios, the largest
    violation beyond its bound (<= 0: satisfied), whether all hold within tol, and ||d[A B]||_2 from the clean fit."""
    X, U, dX, dU = (np.asarray(a, dtype=float) for a in (X, U, dX, dU))
    if X.ndim != 2 or U.ndim != 2 or X.shape[1] != U.shape[1] + 1 or dX.shape != X.shape or dU.shape != U.shape:
        raise InvalidData(f"check_stealth: need X (n x (T+1)), U (m x T) and dX, dU of their shapes, got X {X.shape}, "
                          f"U {U.shape}, dX {dX.shape}, dU {dU.shape}")
    T = U.shape[1]
    lags = 2 * int(np.floor(0.025 * T))
    clean, poisoned = statistics(X, U, lags), statistics(X + dX, U + dU, lags)
    ratios = {"c_r": poisoned["r"] / clean["r"], "c_z": poisoned["zd"] / clean["zd"],
              **{f"c_c{tau}": p / c for tau, (p, c) in
                 enumerate(zip(poisoned["correlation"], clean["correlation"]), start=1)}}
    norms = {"c_x": float(np.linalg.norm(dX) / np.linalg.norm(X)), "c_u": float(np.linalg.norm(dU) / np.linalg.norm(U))}
    excess = {**{k: abs(1 - v) - delta for k, v in ratios.items()}, **{k: v - delta for k, v in norms.items()},
              "box": float(max(np.abs(dX).max(initial=0), np.abs(dU).max(initial=0))) - box}
    worst = max(excess, key=excess.get)
    return {"ratios": ratios | norms, "lags": lags, "worst": worst, "violation": excess[worst],
            "stealthy": bool(excess[worst] <= tol),
            "norm2": float(np.linalg.norm(poisoned["AB"] - clean["AB"], 2)), "AB": poisoned["AB"]}
