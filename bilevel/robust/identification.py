"""Least-squares identification + certainty-equivalence LQR as a certificate target, its mechanisms "lyapunov" and
"directional".

Learner: [A B] = argmin ||X+ - [A B] [X; U]||_F on T poisoned states and inputs, then u = K x, the LQR gain of the
model (weights Q = q I, R = r I); judged by the true plant's loop A + B K. Budget: ||dX||_F <= delta ||X||_F and
||dU||_F <= delta ||U||_F. The attack is the engine's on the registered ident-ss problem, objective ce-lqr.

Mechanism "lyapunov", three proven steps:
1. The model: Theta_a - Theta0 = [E0 dZ' + (dY - Theta0 dZ) Z_a'] (Z_a Z_a')^-1 (E0 the clean residual, E0 Z' = 0),
   so ||Theta_a - Theta0||_F <= ||E0|| r_Z / s^2 + ||[I, -Theta0]|| sqrt(2 r_X^2 + r_U^2) / s =: e1 with
   s = sigma_min(Z) - r_Z > 0. Tighter where the poisoning moves [A B] along few directions: with Z' = Q R and
   D = dZ' R^-1 (||D|| <= eta = r_Z / sigma_min(Z) < 1), Theta_a - Theta0 = [E0 D + V (Q + D)] (A'A)^-1 R^-T,
   A = Q + D, V = dY - Theta0 dZ; its linear part [E0 D + V Q] R^-T is a linear map of (dX, dU) whose exact operator
   norms bound it, and the rest is at most ((||E0|| eta + ||V||) ((1 - eta)^-2 - 1) + ||V|| eta (1 - eta)^-2) /
   sigma_min(Z). eps is the smaller of the two bounds.
2. The gain: for every model in that ball, Y <= P(Theta) <= X (P the model's Riccati solution): X >= P_K0(Theta) (K0's
   cost matrix, a robust Lyapunov LMI: Petersen's lemma on the norm-bounded model error) and Y <= P (any Y with
   [Theta'Y Theta + diag(Q - Y, R)] >= 0 bounds it from below, made robust the same way); one SDP (cvxpy + Clarabel)
   minimizes t = max(lambda_max(X - P0), lambda_max(P0 - Y)), so ||P - P0|| <= t, linear in eps. The gain error is
   exactly K - K0 = -M^-1 W, M = R + B'PB, W = B'P Theta F + R K0 (F = [I; K0]); expanding W around (Theta0, P0) with
   B = B0 + dB, Theta F = Acl0 + dTheta F, P = P0 + E bounds ||W|| by ||W0|| + eps ||l|| (l: dTheta -> dB'P0 Acl0 +
   B0'P0 dTheta F, its exact operator norm on the Frobenius ball) + eps^2 ||F|| ||P0|| + ||B0'E Acl0|| +
   eps t (||Acl0|| + (||B0|| + eps) ||F||), where ||B0'E Acl0|| <= ||B0'C Acl0|| + ||H^1/2 B0|| ||H^1/2 Acl0||
   (C, H the sandwich's centre and half-width: E - C lies in [-H, H]); lambda_min(M) >= r + (sigma_min(Y^1/2 B0) -
   ||Y^1/2|| eps)^2. So ||K - K0|| <= eps_K, linear in eps (the earlier route through the cost difference identity
   grew like sqrt(eps)).
3. The true loop: A + B (K0 + D_K) is Schur stable for every ||D_K|| <= eps_K (a robust Lyapunov LMI, Petersen again).
Mechanism "directional" (one input, tried first) keeps the shapes lyapunov's balls lose:
- the model set: the fit's linear image of the two budget balls lies in the ellipsoid v'S^-1 v <= 1 with S = (1 + beta)
  S_X + (1 + 1/beta) S_U (the outer ellipsoid of a Minkowski sum), so Theta - Theta0 = sum_j w_j D_j + D_r, ||w|| <= 1,
  ||D_r|| <= rest; the sandwich's robust LMIs take that structure (repeated-scalar multipliers: sum_j p_j'L p_j <= q'L q
  for p = w kron q) and also minimize the width X - Y seen through B0 and Acl0;
- the gains: W - W0 = l(dTheta) + B0'E Acl0 + dB'P0 dTheta F + dB'E Acl0 + B0'E dTheta F + dB'E dTheta F exactly. l on
  the fit's linear image is the image of two balls under an exact linear map (support function sqrt(w'L L'w)), l of
  the rest a ball; with E = C + S, -H <= S <= H (the sandwich's centre and half-width, |x'Sy| <= ||H^1/2 x|| ||H^1/2
  y||), -B0'E Acl0 w <= -(B0'C Acl0) w + ||H^1/2 B0|| ||H^1/2 Acl0 w|| (or ||B0|| t ||Acl0 w||), and the second-order
  terms are bounded per direction w the same way with ||F w||; K - K0 = -W / M with M = R + B'PB between bounds from the
  sandwich. That is a convex set of gain errors d given by its support function;
- the loop: with one input det(zI - A - B (K0 + d')) is affine in d, so zero exclusion on the unit circle over that
  set (bilevel.robust.zero_exclusion, Lipschitz-rigorous between grid points) proves every reachable gain stabilizing
  once the clean data's gain (d = 0) is (checked by eigenvalues): exact for the set, where step 3's Lyapunov LMI asks
  for one quadratic Lyapunov function for a ball.
Mechanism "affine" (one input, tried after "directional": about 20 times its CPU time) is a sandwich that follows P with
the model. The model set is one ellipsoid dTheta = sum_j a_j D_j, ||a|| <= 1, the outer ellipsoid of the Minkowski sum
of the fit's linear images of the two budget balls and of its nonlinear part (S = sum_i S_i / p_i, p_i proportional to
sqrt(tr S_i)). The nonlinear part is bounded by its exact expansion (SecondOrder): with Z0' = Q R, D = dZ' R^-1,
V = dY - Theta0 dZ, L1 = E0 D + V Q and N = Q'D + D'Q + D'D, dTheta = [L1 + V D] (I + N)^-1 R^-T, whose second-order
part dTheta_2 = [V D - L1 (Q'D + D'Q)] R^-T is a quadratic form in the poisoning per model entry: each entry lies in
[-h_i, h_i] (S-procedure over the two balls, h ~ delta^2; the box's min-trace outer ellipsoid joins the sum), and the
rest [-L1 D'D - V D N + (L1 + V D) N^2 (I + N)^-1] R^-T in a ball by norms (||D|| <= eta < 1, N = A'A - I, A = Q + D).
This replaced a ball around the whole nonlinear part (step 1's rest), 4.1 times the second-order box's diagonal
and 13 times the rest beyond it (0.030, 0.0073, 0.0023 on the first data set at delta 0.0055).
- First order: E1(D) solves E1 - Acl0'E1 Acl0 = (DF)'P0 Acl0 + Acl0'P0 (DF) (the Riccati solution's Frechet
  derivative, one Lyapunov solve per unit model), W1(D) = l(D) + B0'E1(D) Acl0 and k1(D) = -M0^-1 W1(D) (M0 = R +
  B0'P0 B0) the gain's.
- The affine sandwich: Yc + E1(dTheta) <= P(Theta) <= Xc + E1(dTheta) for every model of the ellipsoid. Upper: with
  K^ = K0 + k1(dTheta) and X = Xc + E1(dTheta), [[diag(X - Q, -R) + sym(Lam [K^, -I]), Theta'G'], [G Theta,
  G + G' - X]] >= 0 gives X >= Q + K^'R K^ + (Theta F^)'X (Theta F^), F^ = [I; K^] (at the vector (x, K^x,
  -Theta F^ x) Finsler's Lam term vanishes and G's terms cancel), so with X >= Y >= 0 the gain K^ stabilizes the
  model and P <= P_K^ <= X. Lower: [[diag(Q - Y, R) + sym(Theta'H), H'], [H, Y]] >= 0 gives (vector (z, -Theta z))
  diag(Q - Y, R) + Theta'Y Theta >= 0, the Bellman inequality, so x'Y x <= the optimal cost x'P x. Both LMIs are
  affine in a: F0 + sum_j a_j F_j >= 0 for ||a|| <= 1 follows from [[F0 - L, A'], [A, I kron L]] >= 0, L >= 0,
  A_j = F_j / 2 + S_j with S_j skew (the vector (xi, -a kron xi); A_j' + A_j = F_j for any skew S_j, and the free
  S_j keep the relaxation's loss second order in the set's size where a common multiplier loses first order). One
  SDP (cvxpy + Clarabel), minimizing the box's width as sandwich does; Xc >= Yc. Then e = P - P0 - E1(dTheta) =
  C + S, -H <= S <= H (C, H the box's centre and half-width), ||e|| <= t_e.
- The gain, exactly: W - W0 = W1(dTheta) + B0'e Acl0 + T2, T2 = [dB'P0 dTheta F + dB'E1 Acl0 + B0'E1 dTheta F] +
  dB'E1 dTheta F + [dB'e Acl0 + B0'e dTheta F + dB'e dTheta F] (E1 = E1(dTheta)). Along u: W1's part is the image
  of the two budget balls under an exact linear map, plus W1 of the second-order part in the box |.| <= g (the
  S-procedure on the forms W1 maps them to; support g'|u|), plus ||W1|| times the rest beyond it; -B0'e Acl0 u <=
  -(B0'C Acl0) u + ||H^1/2 B0|| ||H^1/2 Acl0 u|| (or ||B0|| t_e ||Acl0 u||); the bracketed quadratic part is
  a'Q_u a with Q_u symmetric k x k, at most max |eig Q_u|; the cubic term at most ||dB|| ||E1|| ||dTheta F u|| (each
  the largest over the ellipsoid, ||dTheta F u|| by the spectral norm of [D_j F u]_j); the e terms by ||dB||
  (||C Acl0 u|| + ||H^1/2|| ||H^1/2 Acl0 u||) + (||e B0|| + ||dB|| t_e) ||dTheta F u||. M = R + B'PB = M0 + [2 B0'P0
  dB + B0'E1 B0] + [dB'P0 dB + 2 dB'E1 B0] + dB'E1 dB + B'e B lies in [m_lo, m_hi] by the same bounds (the linear part
  by its coefficients' norm, the quadratic by eigenvalues). K - K0 = -W / M then lies in a convex set given by its
  support function, and zero exclusion proves the true loop as in "directional".
The re-check recomputes step 1 from SVDs (the linear map built the whitened way), t and eps_K from numpy eigenvalues
of X - P0, P0 - Y, X - Y and Y at the SDP's solution, and checks every LMI there by numpy eigenvalues with a margin
above rounding; for "directional", the ellipsoid from the whitened maps, the multipliers L1, L2 >= 0, l's matrix from
Kronecker products, the loop polynomial from np.poly and the sweep on a grid twice as fine with twice the directions;
for "affine", E1 and W1 from Kronecker products, the model maps and ellipsoid the whitened way, the second-order forms
from the normal equations (dTheta_2 = [dY dZ' - dTheta_1 (Z0 dZ' + dZ Z0') - Theta0 dZ dZ'] G0^-1), the affine LMIs by
numpy eigenvalues at the SDP's solution (margin above rounding), L >= 0, S_j skew, m_lo > 0 and the sweep again.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field
from typing import Any

import cvxpy as cp
import numpy as np
from scipy.linalg import solve_discrete_lyapunov

from ..ddc.model_based import lqr_gain
from ..defaults import param
from ..errors import ModelError
from ..lower.quadratic import solve_quietly
from ..problems.identification import declare
from ..problems.identification_instance import IdentificationAttack, least_squares_fit
from ..solvers.registry import solve
from ..spectral_radius import radius
from .target import Signals, Target, register_mechanism, register_target
from .verdict import Check, Evidence, Proof
from .zero_exclusion import sweep

PATH = (0.002, 0.005, 0.01, 0.02, 0.05, 0.1)
"""The attack's budget path before bisection (the defenses frontier's identification path)."""
STRICT = 1e-7
"""Every LMI is solved with this much room (times its scale), so that the numpy re-check passes above rounding."""
SYMMETRIC = ("Xc", "Yc")
"""The affine sandwich's symmetric matrix variables."""


def _fit(atk: IdentificationAttack, signals: Signals) -> np.ndarray:
    Y, Z = atk.regression(signals)
    return least_squares_fit(Y, Z)


def ce_radius(atk: IdentificationAttack, theta: np.ndarray) -> float:
    """The true loop's spectral radius under the model's certainty-equivalence LQR gain (inf if the model's Riccati
    equation has no stabilizing solution)."""
    A, B = atk.setting.state_space
    n = A.shape[0]
    q, r = atk.lqr_weights
    try:
        K, _ = lqr_gain(theta[:, :n], theta[:, n:], q * np.eye(n), r * np.eye(B.shape[1]))
    except (np.linalg.LinAlgError, ValueError):
        return float("inf")
    return radius(A + B @ K)


def identification_target(atk: IdentificationAttack, starts: int = 1, **options: Any) -> Target:
    """The Target of a state-space identification instance (module docstring)."""
    if atk.learner != "ss":
        raise ModelError(f"certificates cover the state-space learner (ident-ss) with certainty-equivalence LQR, not "
                         f"{atk.learner!r}: build the instance with attack_instance('ss', ...)")

    def engine(delta: float, seed: int) -> Signals:
        instance = IdentificationAttack(atk.setting, "ss", dict(atk.signals), {"X": delta, "U": delta}, "ce-lqr",
                                        None, atk.lags, atk.orders, atk.lqr_weights)
        result = solve(declare(instance), starts=starts, seed=seed)
        return {"X": np.asarray(result.x["dX"], float), "U": np.asarray(result.x["dU"], float)}

    return Target(f"ident-ss-T{atk.signals['U'].shape[1]}", "ident-ce-lqr", atk, dict(atk.signals),
                  {k: float(np.linalg.norm(v)) for k, v in atk.signals.items()}, lambda s: _fit(atk, s),
                  lambda theta: ce_radius(atk, theta), {"engine": engine}, PATH, options=options)


def _pokes(atk: IdentificationAttack) -> tuple[np.ndarray, np.ndarray, int]:
    """(dY, dZ, nx): the regression's change at each unit poisoning, X's entries first then U's (row-major), stacked
    (N, n, T) and (N, n + m, T), and X's count."""
    T = atk.signals["U"].shape[1]
    dY, dZ = [], []
    for name in ("X", "U"):
        for k in range(atk.signals[name].size):
            d = {key: np.zeros(v.shape) for key, v in atk.signals.items()}
            d[name].flat[k] = 1.0
            dY.append(d["X"][:, 1:T + 1])
            dZ.append(np.vstack([d["X"][:, :T], d["U"]]))
    return np.array(dY), np.array(dZ), atk.signals["X"].size


def model_maps(atk: IdentificationAttack, whitened: bool = False) -> tuple[np.ndarray, np.ndarray]:
    """The linear part of the poisoned fit, dTheta_lin = [E0 dZ' + (dY - Theta0 dZ) Z0'] G0^-1, as matrices from vec(dX)
    and vec(dU) to vec(dTheta); whitened: the same map computed as [E0 D + V Q] R^-T (Z0' = Q R, D = dZ' R^-1), the
    re-check's second route."""
    Y0, Z0 = atk.regression(atk.signals)
    theta0 = least_squares_fit(Y0, Z0)
    E0 = Y0 - theta0 @ Z0
    Qz, Rz = np.linalg.qr(Z0.T)
    G0inv = np.linalg.inv(Z0 @ Z0.T)
    dYs, dZs, nx = _pokes(atk)
    cols = []
    for dY, dZ in zip(dYs, dZs):
        V = dY - theta0 @ dZ
        if whitened:
            D = np.linalg.solve(Rz.T, dZ).T
            cols.append(np.linalg.solve(Rz, (E0 @ D + V @ Qz).T).T.ravel())
        else:
            cols.append(((E0 @ dZ.T + V @ Z0.T) @ G0inv).ravel())
    cols = np.array(cols).T
    return cols[:, :nx], cols[:, nx:]


def _fit_parts(atk: IdentificationAttack, delta: float) -> tuple[float, float, float, float]:
    """(products, rest, s, r_Z) of step 1 at budget delta: the norm-product bound, the bound on the fit's part beyond
    its linear map (module docstring), the poisoned regressor's smallest singular value bound s and r_Z."""
    Y, Z = atk.regression(atk.signals)
    theta0 = least_squares_fit(Y, Z)
    E0 = Y - theta0 @ Z
    r_X, r_U = delta * np.linalg.norm(atk.signals["X"]), delta * np.linalg.norm(atk.signals["U"])
    r_Z = float(np.hypot(r_X, r_U))
    sigma = float(np.linalg.svd(Z, compute_uv=False)[-1])
    s = sigma - r_Z
    if s <= 0:
        return float("inf"), float("inf"), s, r_Z
    e0 = float(np.linalg.svd(E0, compute_uv=False)[0])
    lin_V = float(np.linalg.svd(np.hstack([np.eye(theta0.shape[0]), -theta0]), compute_uv=False)[0]
                  * np.sqrt(2 * r_X ** 2 + r_U ** 2))
    eta = r_Z / sigma
    rest = ((e0 * eta + lin_V) * ((1 - eta) ** -2 - 1) + lin_V * eta * (1 - eta) ** -2) / sigma
    return e0 * r_Z / s ** 2 + lin_V / s, float(rest), s, r_Z


SPLITS = (0.5, 1.0, 2.0)
"""SecondOrder.bound tries the S-procedure's weights w = 1 - s (1 - w0) for these s, w0 = X's share of the squared
radii (the best on the reproduction's first data set lies between w0 and 1 - (1 - w0) / 2; any w in (0, 1) is
sound)."""


@dataclass(frozen=True)
class SecondOrder:
    """The poisoned fit's second-order part as quadratic forms: entry i of dTheta_2 (row-major) is z'forms[i]z, z the
    poisoning scaled to the unit balls at delta = 1 (X's nx entries over ||X||_F, then U's over ||U||_F); at budget
    delta the forms scale by delta^2. cubic(delta) bounds (Frobenius) everything beyond the second order."""

    forms: np.ndarray   # (n (n + m), N, N)
    nx: int
    sigma: float        # sigma_min(Z0)
    linear: np.ndarray  # operator norms at delta = 1 of the maps a_X, a_U -> E0 D + V Q and -> V (Frobenius)
    scale: np.ndarray   # (||X||_F, ||U||_F)
    cache: dict = field(default_factory=dict)

    def bound(self, C: np.ndarray) -> np.ndarray:
        """For each row c of C: h >= |z' (sum_i c_i forms_i) z| over ||z_X||, ||z_U|| <= 1 at delta = 1 (S-procedure:
        G <= lam diag(I / w, I / (1 - w)) after scaling gives z'Gz <= lam; the best w of SPLITS' per sign)."""
        key = C.tobytes()
        if key in self.cache:
            return self.cache[key]
        G = np.einsum("ci,ikl->ckl", C, self.forms)
        up = lo = np.full(len(C), np.inf)
        w0 = self.scale[0] ** 2 / float(self.scale @ self.scale)
        for w in [1 - split * (1 - w0) for split in SPLITS]:
            d = np.where(np.arange(G.shape[1]) < self.nx, 1 / np.sqrt(w), 1 / np.sqrt(1 - w))
            lam = np.linalg.eigvalsh(d[None, :, None] * G * d[None, None, :])
            up, lo = np.minimum(up, np.maximum(lam[:, -1], 0.0)), np.minimum(lo, np.maximum(-lam[:, 0], 0.0))
        self.cache[key] = np.maximum(up, lo)
        return self.cache[key]

    def cubic(self, delta: float) -> float:
        """A bound on ||dTheta - dTheta_1 - dTheta_2||_F over the budget: with L1 = E0 D + V Q and N = Q'D + D'Q + D'D
        = A'A - I (A = Q + D, ||D|| <= eta < 1, so N's eigenvalues lie in [(1 - eta)^2 - 1, (1 + eta)^2 - 1]), the rest
        is [-L1 D'D - V D N + (L1 + V D) N^2 (I + N)^-1] R^-T, and ||N^2 (I + N)^-1|| is the larger of x^2 / (1 + x)
        at the two ends (convex in x > -1); inf where eta >= 1."""
        r = delta * self.scale
        eta = float(np.hypot(*r)) / self.sigma
        if eta >= 1:
            return float("inf")
        ends = np.array([(1 - eta) ** 2 - 1, (1 + eta) ** 2 - 1])
        nu, tail = float(ends[1]), float(np.max(ends ** 2 / (1 + ends)))
        ell, v = self.linear @ r
        return float((ell * eta ** 2 + v * eta * nu + (ell + v * eta) * tail) / self.sigma)


_SECOND: dict[tuple, SecondOrder] = {}


def second_order(atk: IdentificationAttack, normal: bool = False) -> SecondOrder:
    """The SecondOrder of the fit (cached per data and route): with Z0' = Q R, D = dZ' R^-1, V = dY - Theta0 dZ and
    L1 = E0 D + V Q, dTheta_2 = [V D - L1 (Q'D + D'Q)] R^-T; normal: the re-check's route from the normal equations,
    dTheta_2 = [dY dZ' - dTheta_1 (Z0 dZ' + dZ Z0') - Theta0 dZ dZ'] G0^-1."""
    key = (atk.signals["X"].tobytes(), atk.signals["U"].tobytes(), normal)
    if key in _SECOND:
        return _SECOND[key]
    Y0, Z0 = atk.regression(atk.signals)
    theta0 = least_squares_fit(Y0, Z0) if not normal else np.linalg.lstsq(Z0.T, Y0.T, rcond=None)[0].T
    E0 = Y0 - theta0 @ Z0
    dY, dZ, nx = _pokes(atk)
    scale = np.array([np.linalg.norm(atk.signals["X"]), np.linalg.norm(atk.signals["U"])])
    z = np.where(np.arange(len(dY)) < nx, scale[0], scale[1])
    V = dY - np.einsum("ij,kjt->kit", theta0, dZ)
    Qz, Rz = np.linalg.qr(Z0.T)
    D = np.einsum("kjt,jm->ktm", dZ, np.linalg.inv(Rz))
    L1 = np.einsum("it,ktj->kij", E0, D) + np.einsum("kit,tj->kij", V, Qz)
    if normal:
        G0inv = np.linalg.inv(Z0 @ Z0.T)
        lin = np.einsum("it,kjt->kij", E0, dZ) + np.einsum("kit,jt->kij", V, Z0)
        lin = np.einsum("kij,jm->kim", lin, G0inv)
        G1 = np.einsum("jt,lmt->ljm", Z0, dZ)
        G1 = G1 + G1.transpose(0, 2, 1)
        B = (np.einsum("kit,ljt->klij", dY, dZ) - np.einsum("kij,ljm->klim", lin, G1)
             - np.einsum("ij,kjt,lmt->klim", theta0, dZ, dZ))
        B = np.einsum("klij,jm->klim", B, G0inv)
    else:
        M = np.einsum("tj,ktm->kjm", Qz, D)
        B = np.einsum("kit,ltj->klij", V, D) - np.einsum("kij,ljm->klim", L1, M + M.transpose(0, 2, 1))
        B = np.einsum("klij,mj->klim", B, np.linalg.inv(Rz))
    B = 0.5 * (B + B.transpose(1, 0, 2, 3)) * z[:, None, None, None] * z[None, :, None, None]
    op = lambda F: [_norm(F[:nx].reshape(nx, -1).T), _norm(F[nx:].reshape(len(F) - nx, -1).T)]  # noqa: E731
    found = SecondOrder(np.moveaxis(B.reshape(len(z), len(z), -1), 2, 0), nx,
                        float(np.linalg.svd(Z0, compute_uv=False)[-1]), np.array([op(L1), op(V)]), scale)
    if len(_SECOND) >= 8:
        _SECOND.pop(next(iter(_SECOND)))
    _SECOND[key] = found
    return found


def model_radius(atk: IdentificationAttack, delta: float, whitened: bool = False) -> tuple[float, float]:
    """(eps, s) of step 1: the certified radius of the model ball (Frobenius, hence spectral) and the poisoned
    regressor's smallest singular value bound (eps inf where s <= 0); eps is the smaller of the norm-product bound and
    the linear part's exact operator norm plus a bound on the rest (module docstring)."""
    products, rest, s, _ = _fit_parts(atk, delta)
    if s <= 0:
        return float("inf"), s
    r_X, r_U = delta * np.linalg.norm(atk.signals["X"]), delta * np.linalg.norm(atk.signals["U"])
    GX, GU = model_maps(atk, whitened)
    linear = float(np.linalg.svd(GX, compute_uv=False)[0] * r_X + np.linalg.svd(GU, compute_uv=False)[0] * r_U)
    return float(min(products, linear + rest)), s


@dataclass(frozen=True)
class Clean:
    """The clean model's numbers every step uses: Theta0, its LQR gain K0 and cost matrix P0 (any symmetric P0 and
    K0 serve: the gain bound carries K0's residual W0), F = [I; K0], the model's loop Acl0 = Theta0 F and W0."""

    theta0: np.ndarray
    K0: np.ndarray
    P0: np.ndarray
    F: np.ndarray
    Acl0: np.ndarray
    W0: np.ndarray


def clean(atk: IdentificationAttack, theta0: np.ndarray) -> Clean:
    """The Clean numbers of the model theta0 (lqr_gain's K0 and P0)."""
    n = theta0.shape[0]
    m = theta0.shape[1] - n
    q, r = atk.lqr_weights
    K0, P0 = lqr_gain(theta0[:, :n], theta0[:, n:], q * np.eye(n), r * np.eye(m))
    P0 = _sym(P0)
    F = np.vstack([np.eye(n), K0])
    Acl0 = theta0 @ F
    return Clean(theta0, K0, P0, F, Acl0, theta0[:, n:].T @ P0 @ Acl0 + r * K0)


def _root(M: np.ndarray) -> np.ndarray:
    """The symmetric square root of a symmetric matrix's positive part."""
    lam, V = np.linalg.eigh(_sym(M))
    return V @ np.diag(np.sqrt(np.maximum(lam, 0.0))) @ V.T


def _norm(M: np.ndarray) -> float:
    return float(np.linalg.svd(np.atleast_2d(M), compute_uv=False)[0])


def cost_radius(c: Clean, X: np.ndarray, Y: np.ndarray) -> float:
    """t = max(lambda_max(X - P0), lambda_max(P0 - Y)): Y <= P <= X gives ||P - P0|| <= t."""
    return max(float(np.linalg.eigvalsh(_sym(X - c.P0))[-1]), float(np.linalg.eigvalsh(_sym(c.P0 - Y))[-1]), 0.0)


def gain_radius(c: Clean, r: float, eps: float, X: np.ndarray, Y: np.ndarray) -> float:
    """Step 2's bound on ||K(Theta) - K0|| over the model ball ||Theta - Theta0||_F <= eps, given every model's Riccati
    solution P within Y <= P <= X, Y >= 0 (module docstring)."""
    n = c.theta0.shape[0]
    B0 = c.theta0[:, n:]
    t = cost_radius(c, X, Y)
    f, a, b = _norm(c.F), _norm(c.Acl0), _norm(B0)
    H, C = 0.5 * _sym(X - Y), 0.5 * _sym(X + Y) - c.P0  # P - P0 = C + S with -H <= S <= H
    centre = _norm(B0.T @ C @ c.Acl0) + _norm(_root(H) @ B0) * _norm(_root(H) @ c.Acl0)
    w = (_norm(c.W0) + eps * _norm(first_order_map(c)) + _second_order(c, eps, t) + min(centre, b * t * a))
    return w / _gain_denominators(c, r, eps, X, Y)[0]


def first_order_map(c: Clean) -> np.ndarray:
    """The matrix of l: dTheta -> dB'P0 Acl0 + B0'P0 dTheta F (row-major vec to row-major vec), the part of the gain
    equation's residual W linear in the model with the Riccati solution held at P0."""
    n = c.theta0.shape[0]
    B0 = c.theta0[:, n:]
    units = np.eye(c.theta0.size).reshape(-1, *c.theta0.shape)
    return np.array([(D[:, n:].T @ c.P0 @ c.Acl0 + B0.T @ c.P0 @ D @ c.F).ravel() for D in units]).T


def _second_order(c: Clean, eps: float, t: float) -> float:
    """The bound on W's terms of second order, dB'P0 dTheta F + dB'E Acl0 + B0'E dTheta F + dB'E dTheta F, over the
    model ball eps with ||E|| <= t: eps^2 ||F|| ||P0|| + eps t (||Acl0|| + (||B0|| + eps) ||F||)."""
    n = c.theta0.shape[0]
    f, a, b = _norm(c.F), _norm(c.Acl0), _norm(c.theta0[:, n:])
    return eps ** 2 * f * _norm(c.P0) + eps * t * (a + (b + eps) * f)


def _gain_denominators(c: Clean, r: float, eps: float, X: np.ndarray, Y: np.ndarray) -> tuple[float, float]:
    """Bounds lo <= lambda(M) <= hi of M = R + B'PB over the model ball, from Y <= P <= X: lo = r + (sigma_min(Y^1/2 B0)
    - ||Y^1/2|| eps)_+^2, hi = r + (||X^1/2 B0|| + ||X^1/2|| eps)^2."""
    n = c.theta0.shape[0]
    B0 = c.theta0[:, n:]
    low = float(np.linalg.svd(_root(Y) @ B0, compute_uv=False)[-1]) - _norm(_root(Y)) * eps
    return r + max(low, 0.0) ** 2, r + (_norm(_root(X) @ B0) + _norm(_root(X)) * eps) ** 2


@dataclass(frozen=True)
class ModelShape:
    """The model set as an ellipsoid plus a ball: Theta - Theta0 = sum_j w_j D_j + D_r, ||w|| <= 1, ||D_r|| <= rho (the
    D_j side by side in `D`, n x (n + m) k), from the fit's linear image of the budget (model_shape)."""

    D: np.ndarray
    k: int
    rho: float


def model_shape(atk: IdentificationAttack, delta: float, maps: tuple[np.ndarray, np.ndarray], ball: bool = False,
                second: tuple[np.ndarray, float] | None = None) -> ModelShape:
    """The ModelShape at budget delta: the image GX a_X + GU a_U of the two balls lies in the ellipsoid v'S^-1 v <= 1,
    S = (1 + beta) S_X + (1 + 1/beta) S_U (S_X = r_X^2 GX GX', beta = sqrt(tr S_U / tr S_X)), whose semi-axes give the
    D_j; the fit's part beyond its linear map is the ball (step 1's rest). ball: the ball joins the ellipsoid (rho 0);
    second = (h, c): so do, in its place, the box |dTheta_2 entries| <= h (its min-trace outer ellipsoid, semi-axes
    sqrt(h_i sum h)) and the ball c beyond the second order (SecondOrder)."""
    theta0 = atk.theta0
    r_X, r_U = delta * np.linalg.norm(atk.signals["X"]), delta * np.linalg.norm(atk.signals["U"])
    S_X, S_U = r_X ** 2 * maps[0] @ maps[0].T, r_U ** 2 * maps[1] @ maps[1].T
    if second is not None:
        h, cubic = second
        parts = [S_X, S_U, np.diag(h * h.sum()), cubic ** 2 * np.eye(S_X.shape[0])]
        parts = [S for S in parts if np.trace(S) > 0]
        ball = True
    else:
        rest = _fit_parts(atk, delta)[1]
        parts = [S_X, S_U] + ([rest ** 2 * np.eye(S_X.shape[0])] if ball else [])
    roots = [float(np.sqrt(np.trace(S))) for S in parts]
    lam, V = np.linalg.eigh(_sym(sum(S * sum(roots) / root for S, root in zip(parts, roots))))
    axes = V * np.sqrt(np.maximum(lam, 0.0))
    D = np.hstack([axes[:, j].reshape(theta0.shape) for j in range(axes.shape[1])])
    return ModelShape(D, axes.shape[1], 0.0 if ball else rest)


def _blocks(atk: IdentificationAttack, c: Clean, eps: float, X, Y, mu1, mu2, t, Z, mu3, eps_K, tau, lib,
            shape: ModelShape | None = None, L1=None, L2=None) -> list:
    """The LMI matrices (cvxpy expressions with lib=cp, numbers with lib=np): robust upper bound X on K0's cost matrix,
    robust lower bound Y on the optimal one, X - P0 <= t I, P0 - Y <= t I, and the true loop's robust Lyapunov LMI. With
    a shape the model error is its ellipsoid (multipliers L1 on x, L2 on z: sum_j p_j'L p_j <= q'L q for p = w kron q,
    ||w|| <= 1; the upper LMI's channel is the loop's, D_j F x) plus its ball of radius rho in place of the ball eps,
    its channel scaled by rho (mu1, mu2 then stand for mu1 rho^2, mu2 rho^2: the same LMI by a congruence, better
    scaled)."""
    A, B = atk.setting.state_space
    n, m = B.shape
    q, r = atk.lqr_weights
    Qc = q * np.eye(n) + r * c.K0.T @ c.K0
    H = np.hstack([c.F, np.zeros((n + m, n))])
    bmat = lib.bmat if lib is cp else np.block
    zero = lambda a, b: np.zeros((a, b))  # noqa: E731
    th = c.theta0
    diag = bmat([[q * np.eye(n) - Y, zero(n, m)], [zero(m, n), r * np.eye(m)]])
    if shape is None:
        upper = bmat([[bmat([[X - Qc, c.Acl0.T @ X], [X @ c.Acl0, X]]) - mu1 * eps ** 2 * (H.T @ H),
                       bmat([[zero(n, n)], [X]])], [bmat([[zero(n, n), X]]), mu1 * np.eye(n)]])
        lower = bmat([[th.T @ Y @ th + diag - mu2 * eps ** 2 * np.eye(n + m), th.T @ Y], [Y @ th, mu2 * np.eye(n)]])
    else:
        kron = lib.kron
        w, v = (n + m) * shape.k, n * shape.k
        DF = np.hstack([shape.D[:, j * (n + m):(j + 1) * (n + m)] @ c.F for j in range(shape.k)])  # Acl's directions
        XD, YD = X @ DF, th.T @ Y @ shape.D
        rho = shape.rho
        Hn = np.hstack([np.eye(n), zero(n, n)])
        upper = bmat([[bmat([[X - Qc, c.Acl0.T @ X], [X @ c.Acl0, X]]) - mu1 * (H.T @ H) - Hn.T @ L1 @ Hn,
                       bmat([[zero(n, n)], [rho * X]]), bmat([[zero(n, v)], [XD]])],
                      [bmat([[zero(n, n), rho * X]]), mu1 * np.eye(n), zero(n, v)],
                      [bmat([[zero(v, n), XD.T]]), zero(v, n), kron(np.eye(shape.k), L1)]])
        lower = bmat([[th.T @ Y @ th + diag - mu2 * np.eye(n + m) - L2, rho * th.T @ Y, YD],
                      [rho * Y @ th, mu2 * np.eye(n), zero(n, w)], [YD.T, zero(w, n), kron(np.eye(shape.k), L2)]])
    above = t * np.eye(n) - (X - c.P0)
    below = t * np.eye(n) - (c.P0 - Y)
    Ac = A + B @ c.K0
    Hl = np.hstack([np.eye(n), zero(n, n)])
    loop = bmat([[bmat([[Z - tau * np.eye(n), Ac.T @ Z], [Z @ Ac, Z]]) - mu3 * eps_K ** 2 * (Hl.T @ Hl),
                  bmat([[zero(n, m)], [Z @ B]])], [bmat([[zero(m, n), B.T @ Z]]), mu3 * np.eye(m)]])
    return [upper, lower, above, below, loop]


def _sym(M):
    return 0.5 * (M + M.T)


def sandwich(atk: IdentificationAttack, c: Clean, eps: float, shaped: bool = False,
             shape: ModelShape | None = None) -> dict[str, Any] | None:
    """{X, Y, mu1, mu2 (and L1, L2 with a shape)} of step 2: Y <= P(Theta) <= X for every model in the ball
    ||Theta - Theta0|| <= eps, or in the shape's ellipsoid plus ball (robust LMIs: Petersen's lemma, the repeated
    multipliers of _blocks), minimizing t = max(lambda_max(X - P0), lambda_max(P0 - Y)) and, shaped, also the width
    X - Y seen through B0 and Acl0 (lambda_max of B0'(X - Y)B0 and of Acl0'(X - Y)Acl0: the terms that dominate the
    directional gain set); None if the SDP finds none."""
    n = c.theta0.shape[0]
    B0 = c.theta0[:, n:]
    X, Y = cp.Variable((n, n), symmetric=True), cp.Variable((n, n), symmetric=True)
    mu1, mu2, t = cp.Variable(nonneg=True), cp.Variable(nonneg=True), cp.Variable()
    L1, L2 = (None, None) if shape is None else (cp.Variable((n, n), symmetric=True),
                                                   cp.Variable((c.F.shape[0],) * 2, symmetric=True))
    upper, lower, above, below, _ = _blocks(atk, c, eps, X, Y, mu1, mu2, t, np.eye(n), 1.0, 0.0, 0.0, cp, shape, L1,
                                            L2)
    room = STRICT * (1.0 + float(np.max(np.abs(c.P0))))
    cons = [_sym(upper) >> room * np.eye(upper.shape[0]), _sym(lower) >> room * np.eye(lower.shape[0]),
            _sym(above) >> room * np.eye(n), _sym(below) >> room * np.eye(n), Y >> room * np.eye(n), mu1 >= room,
            mu2 >= room]
    objective = t
    if shape is not None:
        cons += [L1 >> 0, L2 >> 0]
    if shaped:
        t_B, t_A = cp.Variable(), cp.Variable()
        cons += [_sym(B0.T @ (X - Y) @ B0) << t_B * np.eye(B0.shape[1]),
                 _sym(c.Acl0.T @ (X - Y) @ c.Acl0) << t_A * np.eye(n)]
        objective = objective + t_B + t_A
    try:
        solve_quietly(cp.Problem(cp.Minimize(objective), cons), solver=cp.CLARABEL)  # the numpy re-check decides
    except cp.SolverError:
        return None
    found = {"X": X, "Y": Y, "mu1": mu1, "mu2": mu2, **({} if shape is None else {"L1": L1, "L2": L2})}
    if any(v.value is None for v in found.values()):
        return None
    return {k: _sym(v.value) if v.ndim == 2 else float(v.value) for k, v in found.items()}


def riccati_maps(c: Clean, kron: bool = False) -> tuple[list[np.ndarray], np.ndarray]:
    """The Riccati solution's Frechet derivative on the unit models: E1(D) solves E1 - Acl0'E1 Acl0 = (DF)'P0 Acl0 +
    Acl0'P0 (DF) (one Lyapunov solve per direction; kron: by Kronecker products, the re-check's route), and the matrix
    of D -> W1(D) = l(D) + B0'E1(D) Acl0 (row-major vecs), the first-order change of the gain equation's residual W
    with P following the model: K's first-order change is -M0^-1 W1."""
    n = c.theta0.shape[0]
    B0 = c.theta0[:, n:]
    units = np.eye(c.theta0.size).reshape(-1, *c.theta0.shape)
    lyap = np.eye(n * n) - np.kron(c.Acl0.T, c.Acl0.T)
    E1 = []
    for D in units:
        G = (D @ c.F).T @ c.P0 @ c.Acl0
        G = G + G.T
        E1.append(_sym(np.linalg.solve(lyap, G.ravel()).reshape(n, n) if kron
                       else solve_discrete_lyapunov(c.Acl0.T, G, method="bilinear")))
    lmap = _first_order_map_kron(c) if kron else first_order_map(c)
    return E1, lmap + np.array([(B0.T @ E @ c.Acl0).ravel() for E in E1]).T


def model_channels(shape: ModelShape, theta_shape: tuple[int, int]) -> list[list[np.ndarray]]:
    """The model set as channels of semi-axes, each ||w_c|| <= 1: the shape's ellipsoid (its D_j) and its ball (rho
    times the unit models: ||D_r||_F <= rho is ||w|| <= 1 on them)."""
    nm = theta_shape[1]
    ellipsoid = [shape.D[:, j * nm:(j + 1) * nm] for j in range(shape.k)]
    units = np.eye(theta_shape[0] * nm).reshape(-1, *theta_shape)
    return [ellipsoid] + ([[shape.rho * U for U in units]] if shape.rho > 0 else [])


def _affine_blocks(c: Clean, q: float, r: float, channels: list, E1: list, k1: list, Xc, Yc, G, H, Lam, L1: list,
                   L2: list, skew1: list, skew2: list, lib) -> list:
    """The affine sandwich's LMI matrices (cvxpy expressions with lib=cp, numbers with lib=np; module docstring):
    upper (X(w) = Xc + E1(w) bounds the cost of the gain K0 + k1(w) on every model: Finsler's multiplier Lam for
    u = K x, de Oliveira's slack G), lower (Y(w) = Yc + E1(w) satisfies every model's Bellman inequality, slack H) and
    Xc - Yc. Each LMI is F0 + sum_c sum_j w_cj F_cj for ||w_c|| <= 1 per channel c (model_channels; E1[c][j],
    k1[c][j] at its semi-axes), with the full-block multipliers [[F0 - sum_c L_c, A_c'...], [A_c, I kron L_c]],
    A_cj = F_cj / 2 + skew_cj (skew_cj = -skew_cj')."""
    n, nm = c.theta0.shape
    m = nm - n
    bmat = lib.bmat if lib is cp else np.block
    zero = lambda a, b: np.zeros((a, b))  # noqa: E731
    pad = lambda E: bmat([[E, zero(n, m)], [zero(m, n), zero(m, m)]])  # noqa: E731
    N = 2 * n + m

    def robust(F0, Fc, L, skew):
        sizes = [N * len(F) for F in Fc]
        cols = [bmat([[0.5 * F[j] + S[j]] for j in range(len(F))]) for F, S in zip(Fc, skew)]
        rows = [[F0 - sum(L), *[A.T for A in cols]]]
        for i, A in enumerate(cols):
            rows.append([A] + [lib.kron(np.eye(len(Fc[i])), L[i]) if i == j else zero(sizes[i], sizes[j])
                               for j in range(len(cols))])
        return bmat(rows)
    # upper, xi = [x; u; y]
    fin = Lam @ np.hstack([c.K0, -np.eye(m)])
    F0 = bmat([[bmat([[Xc - q * np.eye(n), zero(n, m)], [zero(m, n), -r * np.eye(m)]]) + fin + fin.T,
                c.theta0.T @ G.T], [G @ c.theta0, G + G.T - Xc]])
    Fc = []
    for axes, Es, ks in zip(channels, E1, k1):
        Fj = []
        for D, E, k in zip(axes, Es, ks):
            fin = Lam @ np.hstack([k, zero(m, m)])
            Fj.append(bmat([[pad(E) + fin + fin.T, D.T @ G.T], [G @ D, -E]]))
        Fc.append(Fj)
    upper = robust(F0, Fc, L1, skew1)
    # lower, xi = [zeta; z]
    TH = c.theta0.T @ H
    F0 = bmat([[bmat([[q * np.eye(n) - Yc, zero(n, m)], [zero(m, n), r * np.eye(m)]]) + TH + TH.T, H.T], [H, Yc]])
    Fc = [[bmat([[-pad(E) + D.T @ H + H.T @ D, zero(nm, n)], [zero(n, nm), E]]) for D, E in zip(axes, Es)]
          for axes, Es in zip(channels, E1)]
    lower = robust(F0, Fc, L2, skew2)
    return [upper, lower, Xc - Yc]


def _affine_inputs(c: Clean, r: float, channels: list, E1: list, Wmap: np.ndarray) -> tuple[list, list]:
    """(E1_cj, k1_cj) at the channels' semi-axes D_cj: E1(D_cj) and k1(D_cj) = -M0^-1 W1(D_cj)."""
    n, nm = c.theta0.shape
    B0 = c.theta0[:, n:]
    M0 = r * np.eye(nm - n) + B0.T @ c.P0 @ B0
    E_all = np.array([E.ravel() for E in E1]).T
    return ([[_sym((E_all @ D.ravel()).reshape(n, n)) for D in axes] for axes in channels],
            [[-np.linalg.solve(M0, (Wmap @ D.ravel()).reshape(nm - n, n)) for D in axes] for axes in channels])


def affine_sandwich(atk: IdentificationAttack, c: Clean, shape: ModelShape, E1: list, Wmap: np.ndarray
                    ) -> dict[str, Any] | None:
    """{Xc, Yc, G, H, Lam, L1, L2, skew1, skew2}: Yc + E1(dTheta) <= P(Theta) <= Xc + E1(dTheta) for every model
    Theta0 + dTheta of the shape (module docstring), minimizing the box's width (as sandwich does); None if the SDP
    finds none."""
    n, nm = c.theta0.shape
    q, r = atk.lqr_weights
    B0 = c.theta0[:, n:]
    channels = model_channels(shape, c.theta0.shape)
    E1c, k1c = _affine_inputs(c, r, channels, E1, Wmap)
    Xc, Yc = cp.Variable((n, n), symmetric=True), cp.Variable((n, n), symmetric=True)
    G, H, Lam = cp.Variable((n, n)), cp.Variable((n, nm)), cp.Variable((nm, nm - n))
    N = 2 * n + nm - n
    L1, L2 = [[cp.Variable((N, N), symmetric=True) for _ in channels] for _ in range(2)]
    S1, S2 = [[[cp.Variable((N, N)) for _ in axes] for axes in channels] for _ in range(2)]
    skew1, skew2 = [[[S - S.T for S in Sc] for Sc in Ss] for Ss in (S1, S2)]
    upper, lower, gap = _affine_blocks(c, q, r, channels, E1c, k1c, Xc, Yc, G, H, Lam, L1, L2, skew1, skew2, cp)
    room = STRICT * (1.0 + float(np.max(np.abs(c.P0))))
    t, t_B, t_A = cp.Variable(), cp.Variable(), cp.Variable()
    cons = [_sym(upper) >> room * np.eye(upper.shape[0]), _sym(lower) >> room * np.eye(lower.shape[0]),
            _sym(gap) >> room * np.eye(n), *[L >> 0 for L in L1 + L2],
            Xc - c.P0 << t * np.eye(n), c.P0 - Yc << t * np.eye(n),
            _sym(B0.T @ (Xc - Yc) @ B0) << t_B * np.eye(nm - n), _sym(c.Acl0.T @ (Xc - Yc) @ c.Acl0) << t_A * np.eye(n)]
    try:
        solve_quietly(cp.Problem(cp.Minimize(t + t_B + t_A), cons), solver=cp.CLARABEL)  # the numpy re-check decides
    except cp.SolverError:
        return None
    found = {"Xc": Xc, "Yc": Yc, "G": G, "H": H, "Lam": Lam}
    if any(v.value is None for v in [*found.values(), *L1, *L2, *[S for Ss in S1 + S2 for S in Ss]]):
        return None
    out = {k: _sym(v.value) if k in SYMMETRIC else np.asarray(v.value, float) for k, v in found.items()}
    skew = lambda Ss: [[np.asarray(S.value - S.value.T) for S in Sc] for Sc in Ss]  # noqa: E731
    return {**out, "L1": [_sym(L.value) for L in L1], "L2": [_sym(L.value) for L in L2], "skew1": skew(S1),
            "skew2": skew(S2)}


def lyapunov(target: Target, delta: float, options: dict[str, Any]) -> Evidence | None:
    """Mechanism "lyapunov" (module docstring)."""
    atk = target.declaration
    t0 = time.perf_counter()
    eps, s = model_radius(atk, delta)
    if not np.isfinite(eps):
        return Evidence("lyapunov", Proof.UNKNOWN, f"the poisoned regressor may be singular (s = {s:.3g})", {"s": s},
                        Check(False, "nothing to check"), time.perf_counter() - t0)
    Y0, Z0 = atk.regression(atk.signals)
    c = clean(atk, least_squares_fit(Y0, Z0))
    n = c.theta0.shape[0]
    r = atk.lqr_weights[1]
    numbers: dict[str, float] = {"eps_model": eps, "s": s}
    found = sandwich(atk, c, eps)
    if found is None:
        return Evidence("lyapunov", Proof.UNKNOWN, "the gain bound's SDP found no robust cost bounds", numbers,
                        Check(False, "nothing to check"), time.perf_counter() - t0)
    X, Yv, mu1, mu2 = found["X"], found["Y"], found["mu1"], found["mu2"]
    eps_K = gain_radius(c, r, eps, X, Yv)
    numbers.update(t_cost=cost_radius(c, X, Yv), eps_K=eps_K)
    if not np.isfinite(eps_K):
        return Evidence("lyapunov", Proof.UNKNOWN, "the gain bound is infinite", numbers,
                        Check(False, "nothing to check"), time.perf_counter() - t0)
    Z, mu3, tau = cp.Variable((n, n), symmetric=True), cp.Variable(nonneg=True), cp.Variable()
    loop = _blocks(atk, c, eps, X, Yv, 1.0, 1.0, 0.0, Z, mu3, eps_K * (1 + 1e-6), tau, cp)[4]
    cons = [_sym(loop) >> 0, Z >> np.eye(n), Z << 1e6 * np.eye(n), tau <= 1.0]
    try:
        solve_quietly(cp.Problem(cp.Maximize(tau), cons), solver=cp.CLARABEL)
    except cp.SolverError:
        Z.value = None
    numbers.update(tau=float("nan") if tau.value is None else float(tau.value))
    if Z.value is None or tau.value is None or tau.value <= 0:
        return Evidence("lyapunov", Proof.UNKNOWN, f"no robust Lyapunov function for gain errors up to {eps_K:.3g}",
                        numbers, Check(False, "nothing to check"), time.perf_counter() - t0)
    solution = {"X": X, "Y": Yv, "mu1": mu1, "mu2": mu2, "Z": Z.value, "mu3": float(mu3.value), "tau": float(tau.value)}
    check = recheck(atk, delta, solution)
    return Evidence("lyapunov", Proof.PROVEN, f"no poisoning with ||dX||_F <= {delta:.6g} ||X||_F, ||dU||_F <= "
                    f"{delta:.6g} ||U||_F destabilizes the true loop under certainty-equivalence LQR (model ball "
                    f"{eps:.3g}, gain ball {eps_K:.3g}, robust Lyapunov decrease {float(tau.value):.3g})", numbers,
                    check, time.perf_counter() - t0)


def _refit_clean(atk: IdentificationAttack) -> Clean:
    """The clean numbers from a numpy lstsq re-fit (the re-checks' own, not least_squares_fit)."""
    Y0, Z0 = atk.regression(atk.signals)
    return clean(atk, np.linalg.lstsq(Z0.T, Y0.T, rcond=None)[0].T)


def _smallest_eigs(mats: list, names: tuple[str, ...]) -> tuple[dict[str, float], dict[str, bool]]:
    """Each matrix's smallest eigenvalue (numpy) and whether it clears the check margin times the matrix's size."""
    margin = param("robust.check_margin")
    eigs = {name: float(np.linalg.eigvalsh(_sym(M))[0]) for name, M in zip(names, mats)}
    return eigs, {name: eigs[name] >= margin * float(np.max(np.abs(M))) for name, M in zip(names, mats)}


def recheck(atk: IdentificationAttack, delta: float, sol: dict[str, Any]) -> Check:
    """Step 1 again from SVDs (model_radius is that computation; its inputs re-fitted by numpy lstsq), t from numpy
    eigenvalues of X - P0 and P0 - Y (and X - Y >= 0), the gain bound from them, and every LMI's smallest eigenvalue
    by numpy with a margin above rounding."""
    c = _refit_clean(atk)
    eps, _ = model_radius(atk, delta, whitened=True)
    eps = eps * (1 + 1e-9)
    X, Y = _sym(sol["X"]), _sym(sol["Y"])
    t = cost_radius(c, X, Y) * (1 + 1e-9)
    eps_K = gain_radius(c, atk.lqr_weights[1], eps, X, Y) * (1 + 1e-9)
    mats = _blocks(atk, c, eps, X, Y, sol["mu1"], sol["mu2"], t, _sym(sol["Z"]), sol["mu3"], eps_K, sol["tau"], np)
    eigs, ok = _smallest_eigs(mats, ("upper", "lower", "above", "below", "loop"))
    passed = ok["upper"] and ok["lower"] and ok["loop"] and min(eigs["above"], eigs["below"]) >= 0 \
        and float(np.linalg.eigvalsh(Y)[0]) >= 0 and float(np.linalg.eigvalsh(X - Y)[0]) >= 0 \
        and np.isfinite(eps_K) and sol["mu1"] > 0 and sol["mu2"] > 0 and sol["mu3"] > 0 and sol["tau"] > 0
    return Check(passed, "numpy eigenvalues of the LMIs at the SDP's solution (smallest, against a margin of "
                 f"{param('robust.check_margin'):.0e} times each matrix's size): "
                 + ", ".join(f"{k} {v:.3g}" for k, v in eigs.items()),
                 {**{f"min_eig_{k}": v for k, v in eigs.items()}, "eps_K": eps_K, "eps_model": eps, "t_cost": t})


@dataclass(frozen=True)
class GainSet:
    """A convex outer set of the gain errors d = (K - K0)' over the budget (one input), by its support function: K - K0
    = -W / M with M in [m_lo, m_hi] and W - W0 = l(dTheta) + B0'E Acl0 + dB'P0 dTheta F + dB'E Acl0 + B0'E dTheta F
    + dB'E dTheta F (module docstring), E = P - P0 = C + S with -H <= S <= H, ||E|| <= t, ||dTheta|| <= eps."""

    gram_X: np.ndarray   # l's image of the X ball: L_X L_X' (n x n)
    gram_U: np.ndarray   # and of the U ball
    ball: float          # ||W0|| + ||l|| times the fit's nonlinear part
    centre: np.ndarray   # B0'C Acl0 as a vector
    half_B: float        # ||H^1/2 B0||
    half: float          # ||H^1/2||
    half_A: np.ndarray   # H^1/2 Acl0
    CA: np.ndarray       # C Acl0
    acl0: np.ndarray     # Acl0
    F: np.ndarray        # [I; K0]
    eps: float
    t: float
    b: float             # ||B0||
    p: float             # ||P0||
    e_B: float           # bound on ||E B0||: min(||C B0|| + ||H^1/2|| ||H^1/2 B0||, t ||B0||)
    m_lo: float
    m_hi: float

    def support(self, W: np.ndarray) -> np.ndarray:
        """An upper bound on max over the set of w'd for each column w of W (n x k), sharp on l's image."""
        def quad(G):
            return np.sqrt(np.maximum(np.einsum("im,ij,jm->m", W, G, W), 0.0))

        def norm(M):
            return np.linalg.norm(M @ W, axis=0)
        a_w, f_w, h_w = norm(self.acl0), norm(self.F), norm(self.half_A)
        e_term = np.minimum(-self.centre @ W + self.half_B * h_w, self.b * self.t * a_w)  # B0'E Acl0 w
        second = self.eps * (self.eps * (self.p + self.t) * f_w + self.e_B * f_w
                             + np.minimum(norm(self.CA) + self.half * h_w, self.t * a_w))
        g = quad(self.gram_X) + quad(self.gram_U) + self.ball * np.linalg.norm(W, axis=0) + e_term + second
        return np.maximum(g / self.m_lo, g / self.m_hi)


def gain_set(atk: IdentificationAttack, c: Clean, delta: float, eps: float, X: np.ndarray, Y: np.ndarray,
             maps: tuple[np.ndarray, np.ndarray], lmap: np.ndarray) -> GainSet:
    """The GainSet at budget delta from the model ball eps, the sandwich Y <= P <= X, the fit's linear maps (GX, GU)
    and l's matrix (first_order_map)."""
    n = c.theta0.shape[0]
    B0 = c.theta0[:, n:]
    r_X, r_U = delta * np.linalg.norm(atk.signals["X"]), delta * np.linalg.norm(atk.signals["U"])
    _, rest, _, _ = _fit_parts(atk, delta)
    t = cost_radius(c, X, Y)
    H, C = 0.5 * _sym(X - Y), 0.5 * _sym(X + Y) - c.P0
    root = _root(H)
    LX, LU = lmap @ maps[0] * r_X, lmap @ maps[1] * r_U
    m_lo, m_hi = _gain_denominators(c, atk.lqr_weights[1], eps, X, Y)
    half_B = _norm(root @ B0)
    return GainSet(LX @ LX.T, LU @ LU.T, _norm(c.W0) + _norm(lmap) * rest, (B0.T @ C @ c.Acl0).ravel(), half_B,
                   _norm(root), root @ c.Acl0, C @ c.Acl0, c.Acl0, c.F, eps, t, _norm(B0), _norm(c.P0),
                   min(_norm(C @ B0) + _norm(root) * half_B, t * _norm(B0)), m_lo, m_hi)


@dataclass(frozen=True)
class AffineGainSet:
    """A convex outer set of the gain errors d = (K - K0)' over the budget (one input) from the affine sandwich, by its
    support function: K - K0 = -W / M, W - W0 = W1(dTheta) + B0'e Acl0 + T2 exactly (module docstring), the model
    set the ellipsoid dTheta = sum_j a_j D_j, ||a|| <= 1, with the fit's exact linear image inside it."""

    WX: np.ndarray        # W1's image of the X ball (n x X's size)
    WU: np.ndarray        # and of the U ball
    ball: float           # ||W0|| + ||W1|| times the fit's nonlinear part
    centre: np.ndarray    # B0'C Acl0 (C the box's centre)
    half_B: float         # ||H^1/2 B0|| (H the box's half-width)
    half: float           # ||H^1/2||
    half_A: np.ndarray    # H^1/2 Acl0
    CA: np.ndarray        # C Acl0
    e_B: float            # ||C B0|| + ||H^1/2|| ||H^1/2 B0|| >= ||e B0||
    t_e: float            # ||e|| <= t_e
    acl0: np.ndarray
    b: float              # ||B0||
    quad: np.ndarray      # T2's quadratic part, (n, k, k): u'Q(D_i, D_j) symmetrized, per unit u
    DF: np.ndarray        # (n, n, k): [D_j F e_l]_j per unit e_l
    ext_B: float          # max ||dB|| over the ellipsoid
    ext_E: float          # max ||E1(dTheta)|| over the ellipsoid
    m_lo: float
    m_hi: float
    box: np.ndarray | None = None  # |W1(dTheta_2)| <= box entrywise (None: the ball holds the whole nonlinear part)

    def support(self, U: np.ndarray) -> np.ndarray:
        """An upper bound on max over the set of u'd for each column u of U (n x p)."""
        col = lambda M: np.linalg.norm(M, axis=0)  # noqa: E731
        ext_F = np.sqrt(np.maximum(np.linalg.eigvalsh(_gram_rows(np.einsum("lik,lp->pik", self.DF, U)))[:, -1], 0.0))
        quad = np.abs(np.linalg.eigvalsh(np.einsum("lij,lp->pij", self.quad, U))).max(axis=1)
        h_A = col(self.half_A @ U)
        g = (col(self.WX.T @ U) + col(self.WU.T @ U) + self.ball * col(U)
             + np.minimum(-self.centre @ U + self.half_B * h_A, self.b * self.t_e * col(self.acl0 @ U))
             + quad + self.ext_B * self.ext_E * ext_F
             + self.ext_B * (col(self.CA @ U) + self.half * h_A) + (self.e_B + self.ext_B * self.t_e) * ext_F)
        if self.box is not None:
            g = g + self.box @ np.abs(U)
        return np.maximum(g / self.m_lo, g / self.m_hi)


def _gram_rows(M: np.ndarray) -> np.ndarray:
    """M M' for a stack of matrices (p, a, b) -> (p, a, a)."""
    return np.einsum("pik,pjk->pij", M, M)


def affine_gain_set(atk: IdentificationAttack, c: Clean, delta: float, shape: ModelShape, sol: dict[str, Any],
                    maps: tuple[np.ndarray, np.ndarray], E1: list, Wmap: np.ndarray,
                    second: tuple[np.ndarray, float] | None = None) -> AffineGainSet:
    """The AffineGainSet at budget delta from the affine sandwich's solution (Xc, Yc) on the combined ellipsoid
    `shape` (model_shape(..., ball=True)), the fit's maps, E1 on the unit models and W1's matrix (riccati_maps);
    second = (g, c): W1 of the fit's second-order part lies in the box |.| <= g and the rest beyond it in the ball c
    (SecondOrder), in place of ||W1|| times step 1's rest."""
    n, nm = c.theta0.shape
    B0 = c.theta0[:, n:]
    r = atk.lqr_weights[1]
    r_X, r_U = delta * np.linalg.norm(atk.signals["X"]), delta * np.linalg.norm(atk.signals["U"])
    _, rest, _, _ = _fit_parts(atk, delta)
    Xc, Yc = _sym(sol["Xc"]), _sym(sol["Yc"])
    H, C = 0.5 * _sym(Xc - Yc), 0.5 * _sym(Xc + Yc) - c.P0
    root = _root(H)
    t_e = max(float(np.linalg.eigvalsh(Xc - c.P0)[-1]), float(np.linalg.eigvalsh(c.P0 - Yc)[-1]), 0.0)
    half_B, half = _norm(root @ B0), _norm(root)
    e_B = min(_norm(C @ B0) + half * half_B, t_e * _norm(B0))
    Ds = [shape.D[:, j * nm:(j + 1) * nm] for j in range(shape.k)]
    E_all = np.array([E.ravel() for E in E1]).T
    Ej = [_sym((E_all @ D.ravel()).reshape(n, n)) for D in Ds]
    dB = [D[:, n:] for D in Ds]
    P0A = c.P0 @ c.Acl0
    # T2's quadratic part: dB'P0 dTheta F + dB'E1(dTheta) Acl0 + B0'E1(dTheta) dTheta F at (D_i, D_j), a row per pair
    Q = np.array([[(dB[i].T @ c.P0 @ Ds[j] @ c.F + dB[i].T @ Ej[j] @ c.Acl0 + B0.T @ Ej[i] @ Ds[j] @ c.F).ravel()
                   for j in range(shape.k)] for i in range(shape.k)])  # (k, k, n)
    quad = np.moveaxis(0.5 * (Q + Q.transpose(1, 0, 2)), 2, 0)
    DF = np.array([np.array([D @ c.F[:, l] for D in Ds]).T for l in range(n)])  # (n, n, k)
    ext_B = _norm(np.hstack(dB))
    ext_E = _norm(E_all @ np.array([D.ravel() for D in Ds]).T)
    # M = r + B'PB: M0 + [2 B0'P0 dB + B0'E1 B0] + [dB'P0 dB + 2 dB'E1 B0] + dB'E1 dB + B'e B
    M0 = r + (B0.T @ c.P0 @ B0).item()
    lin = np.array([(2 * B0.T @ c.P0 @ b + B0.T @ E @ B0).item() for b, E in zip(dB, Ej)])
    Mq = np.array([[(dB[i].T @ c.P0 @ dB[j] + dB[i].T @ Ej[j] @ B0 + dB[j].T @ Ej[i] @ B0).item()
                    for j in range(shape.k)] for i in range(shape.k)])
    spread = (np.linalg.norm(lin) + np.abs(np.linalg.eigvalsh(_sym(Mq))).max() + ext_B ** 2 * ext_E
              + 2 * ext_B * e_B + ext_B ** 2 * t_e)
    centre_M = (B0.T @ C @ B0).item()
    m_lo = M0 + centre_M - half_B ** 2 - spread
    m_hi = M0 + centre_M + half_B ** 2 + spread
    if second is not None:
        rest = second[1]
    return AffineGainSet(Wmap @ maps[0] * r_X, Wmap @ maps[1] * r_U, _norm(c.W0) + _norm(Wmap) * rest,
                         (B0.T @ C @ c.Acl0).ravel(), half_B, half, root @ c.Acl0, C @ c.Acl0, e_B, t_e, c.Acl0,
                         _norm(B0), quad, DF, ext_B, ext_E, m_lo, m_hi, None if second is None else second[0])


def loop_polynomial(A: np.ndarray, B: np.ndarray, K0: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(base, slopes): det(zI - A - B (K0 + d')) = base(z) + d' slopes(z) (coefficients highest power first; one input,
    so affine in d), by Faddeev-LeVerrier: adj(zI - Acl) = sum_k z^(n-1-k) N_k, N_0 = I, N_k = Acl N_k-1 + c_k I."""
    Acl = A + B @ K0
    n = A.shape[0]
    base, slopes, N = [1.0], np.zeros((n, n + 1)), np.eye(n)
    for k in range(1, n + 1):
        slopes[:, k] = -(N @ B)[:, 0]
        AN = Acl @ N
        base.append(-float(np.trace(AN)) / k)
        N = AN + base[-1] * np.eye(n)
    return np.array(base), slopes


GRID = 4096
ANGLES = 9


def _one_input_start(name: str, atk: IdentificationAttack, delta: float
                     ) -> tuple[float, Clean, dict[str, float], tuple[np.ndarray, np.ndarray], float] | Evidence | None:
    """(eps, the clean numbers, the evidence's numbers, the fit's maps, the start time) for a zero-exclusion mechanism;
    None for more than one input (the loop is then not affine in the gain error); its UNKNOWN Evidence where the
    poisoned regressor may be singular or the clean data's gain does not stabilize the true loop (zero exclusion needs
    one stable member: the clean gain, d = 0)."""
    A, B = atk.setting.state_space
    if B.shape[1] != 1:
        return None
    t0 = time.perf_counter()
    eps, s = model_radius(atk, delta)
    if not np.isfinite(eps):
        return Evidence(name, Proof.UNKNOWN, f"the poisoned regressor may be singular (s = {s:.3g})", {"s": s},
                        Check(False, "nothing to check"), time.perf_counter() - t0)
    Y0, Z0 = atk.regression(atk.signals)
    c = clean(atk, least_squares_fit(Y0, Z0))
    clean_radius = radius(A + B @ c.K0)
    numbers: dict[str, float] = {"eps_model": eps, "s": s, "clean_radius": clean_radius}
    if not clean_radius < 1:
        return Evidence(name, Proof.UNKNOWN, f"the clean loop is not stable (spectral radius {clean_radius:.4g})",
                        numbers, Check(False, "nothing to check"), time.perf_counter() - t0)
    return eps, c, numbers, model_maps(atk), t0


def _unknown(name: str, claim: str, numbers: dict[str, float], t0: float) -> Evidence:
    return Evidence(name, Proof.UNKNOWN, claim, numbers, Check(False, "nothing to check"), time.perf_counter() - t0)


def _zero_exclusion(name: str, atk: IdentificationAttack, c: Clean, delta: float, support: Any,
                    numbers: dict[str, float], t0: float, recheck_fn: Any, detail: str) -> Evidence:
    """Zero exclusion of the true loop's polynomial over a gain set (its support function), then the mechanism's
    re-check (recheck_fn(), called only for a proof): the Evidence."""
    A, B = atk.setting.state_space
    swept = sweep(*loop_polynomial(A, B, c.K0), support, GRID, ANGLES)
    numbers.update(excluded_by=swept.excluded_by, lipschitz=swept.lipschitz)
    if not swept.proven:
        return _unknown(name, f"zero exclusion fails at delta = {delta:.6g} (guaranteed distance "
                        f"{swept.excluded_by:.3g})", numbers, t0)
    check = recheck_fn()
    return Evidence(name, Proof.PROVEN, f"no poisoning with ||dX||_F <= {delta:.6g} ||X||_F, ||dU||_F <= "
                    f"{delta:.6g} ||U||_F destabilizes the true loop under certainty-equivalence LQR ({detail}, zero "
                    f"excluded by {swept.excluded_by:.3g})", numbers, check, time.perf_counter() - t0)


def directional(target: Target, delta: float, options: dict[str, Any]) -> Evidence | None:
    """Mechanism "directional" (module docstring); None for more than one input."""
    atk = target.declaration
    start = _one_input_start("directional", atk, delta)
    if not isinstance(start, tuple):
        return start
    eps, c, numbers, maps, t0 = start
    found = sandwich(atk, c, eps, shaped=True, shape=model_shape(atk, delta, maps))
    if found is None:
        return _unknown("directional", "the gain bound's SDP found no robust cost bounds", numbers, t0)
    gains = gain_set(atk, c, delta, eps, found["X"], found["Y"], maps, first_order_map(c))
    numbers.update(t_cost=gains.t, ball=gains.ball)
    return _zero_exclusion("directional", atk, c, delta, gains.support, numbers, t0,
                           lambda: recheck_directional(atk, delta, found),
                           f"model ball {eps:.3g}, the gain's first-order image of the budget plus a ball of "
                           f"{gains.ball:.3g} and second-order terms")


def _first_order_map_kron(c: Clean) -> np.ndarray:
    """first_order_map built from Kronecker products (the re-check's route): vec(B0'P0 D F) = (B0'P0 kron F') vec(D),
    vec(D_B'P0 Acl0) = (S' kron (P0 Acl0)') vec(D') with D_B = D S, row-major vecs."""
    n, k = c.theta0.shape
    B0 = c.theta0[:, n:]
    S = np.vstack([np.zeros((n, k - n)), np.eye(k - n)])
    transpose = np.eye(n * k)[[i * k + j for j in range(k) for i in range(n)]]  # vec(D') = transpose @ vec(D)
    return np.kron(B0.T @ c.P0, c.F.T) + np.kron(S.T, (c.P0 @ c.Acl0).T) @ transpose


def recheck_directional(atk: IdentificationAttack, delta: float, sol: dict[str, Any]) -> Check:
    """The clean loop's stability and the sandwich's LMIs (and its multipliers L1, L2 >= 0) by numpy eigenvalues at the
    SDP's solution (margin above rounding), the model ball, the fit's maps and the model's ellipsoid the whitened way,
    l's matrix from Kronecker products, the loop polynomial from numpy's np.poly, and the sweep on a grid twice as fine
    with twice the directions."""
    A, B = atk.setting.state_space
    c = _refit_clean(atk)
    n = c.theta0.shape[0]
    eps = model_radius(atk, delta, whitened=True)[0] * (1 + 1e-9)
    X, Y = _sym(sol["X"]), _sym(sol["Y"])
    t = cost_radius(c, X, Y) * (1 + 1e-9)
    maps = model_maps(atk, whitened=True)
    shape = model_shape(atk, delta, maps)
    shape = ModelShape(shape.D, shape.k, shape.rho * (1 + 1e-9))
    L1, L2 = _sym(sol["L1"]), _sym(sol["L2"])
    mats = _blocks(atk, c, eps, X, Y, sol["mu1"], sol["mu2"], t, np.eye(n), 1.0, 0.0, 0.0, np, shape, L1, L2)[:4]
    eigs, ok = _smallest_eigs(mats + [L1, L2], ("upper", "lower", "above", "below", "L1", "L2"))
    lmap = _first_order_map_kron(c)
    gains = gain_set(atk, c, delta, eps, X, Y, maps, lmap)
    Acl = A + B @ c.K0
    base = np.poly(Acl)
    slopes = np.array([np.poly(Acl + B @ e[None, :]) - base for e in np.eye(n)])
    fl_base, fl_slopes = loop_polynomial(A, B, c.K0)
    agree = max(float(np.max(np.abs(lmap - first_order_map(c))) / np.max(np.abs(lmap))),
                float(np.max(np.abs(slopes - fl_slopes)) / np.max(np.abs(slopes))),
                float(np.max(np.abs(base - fl_base))))
    slopes = np.where(np.abs(slopes) >= np.abs(fl_slopes), slopes, fl_slopes)  # the larger of each pair
    swept = sweep(base, slopes, gains.support, 2 * GRID, 2 * ANGLES)
    margin = param("robust.check_margin") * float(np.max(np.abs(base)))
    clean_radius = float(np.max(np.abs(np.linalg.eigvals(Acl))))
    passed = clean_radius < 1 - margin and ok["upper"] and ok["lower"] \
        and min(eigs["above"], eigs["below"], eigs["L1"], eigs["L2"]) >= 0 \
        and float(np.linalg.eigvalsh(Y)[0]) >= 0 and float(np.linalg.eigvalsh(X - Y)[0]) >= 0 \
        and sol["mu1"] > 0 and sol["mu2"] > 0 and swept.excluded_by > margin and swept.leading > margin \
        and agree < 1e-6
    return Check(passed, f"numpy eigenvalues of the sandwich's LMIs (smallest: "
                 + ", ".join(f"{k} {v:.3g}" for k, v in eigs.items())
                 + f"); maps rebuilt agree to {agree:.1e}; the sweep at {2 * GRID} frequencies excludes zero by "
                 f"{swept.excluded_by:.3g} (margin {margin:.1e}); the clean loop's spectral radius {clean_radius:.4g}",
                 {**{f"min_eig_{k}": v for k, v in eigs.items()}, "agreement": agree, "clean_radius": clean_radius,
                  "excluded_by": swept.excluded_by, "margin": margin, "eps_model": eps, "t_cost": t})


def second_parts(atk: IdentificationAttack, c: Clean, Wmap: np.ndarray, delta: float, normal: bool = False
                 ) -> tuple[tuple[np.ndarray, float], tuple[np.ndarray, float]] | tuple[None, None]:
    """((h, c), (g, c)) at budget delta: the box of the fit's second-order part on the model's entries, that of W1
    on it, and the ball beyond the second order (SecondOrder; normal: the re-check's route); (None, None) where the
    expansion's rest is unbounded (step 1's ball then holds the whole nonlinear part)."""
    so = second_order(atk, normal)
    cubic = so.cubic(delta)
    if not np.isfinite(cubic):
        return None, None
    h = so.bound(np.vstack([np.eye(c.theta0.size), Wmap])) * delta ** 2
    return (h[:c.theta0.size], cubic), (h[c.theta0.size:], cubic)


def affine(target: Target, delta: float, options: dict[str, Any]) -> Evidence | None:
    """Mechanism "affine" (module docstring): the affine sandwich and its gain set, zero exclusion as in directional;
    None for more than one input."""
    atk = target.declaration
    start = _one_input_start("affine", atk, delta)
    if not isinstance(start, tuple):
        return start
    _, c, numbers, maps, t0 = start
    E1, Wmap = riccati_maps(c)
    in_model, in_gain = second_parts(atk, c, Wmap, delta)
    shape = model_shape(atk, delta, maps, ball=True, second=in_model)
    found = affine_sandwich(atk, c, shape, E1, Wmap)
    if found is None:
        return _unknown("affine", "the affine sandwich's SDP found no bounds", numbers, t0)
    gains = affine_gain_set(atk, c, delta, shape, found, maps, E1, Wmap, in_gain)
    numbers.update(t_e=gains.t_e, m_lo=gains.m_lo)
    if not gains.m_lo > 0:
        return _unknown("affine", "the gain equation's denominator may vanish", numbers, t0)
    return _zero_exclusion("affine", atk, c, delta, gains.support, numbers, t0,
                           lambda: recheck_affine(atk, delta, found),
                           f"Riccati solutions within {gains.t_e:.3g} of their first-order change")


def recheck_affine(atk: IdentificationAttack, delta: float, sol: dict[str, Any], second: bool = True) -> Check:
    """The affine sandwich's LMIs by numpy eigenvalues at the SDP's solution (margin above rounding; multipliers >= 0,
    Xc >= Yc), with E1 and W1 from Kronecker products, the fit's maps and the ellipsoid the whitened way, the fit's
    second-order forms from the normal equations (second: the solution's model set used them; else step 1's ball)
    and the clean model from a numpy lstsq re-fit; the gain set from them, the loop polynomial from np.poly and the
    sweep on a grid twice as fine with twice the directions."""
    A, B = atk.setting.state_space
    c = _refit_clean(atk)
    n, nm = c.theta0.shape
    q, r = atk.lqr_weights
    maps = model_maps(atk, whitened=True)
    E1, Wmap = riccati_maps(c, kron=True)
    in_model, in_gain = second_parts(atk, c, Wmap, delta, normal=True) if second else (None, None)
    if in_model is not None:
        in_model, in_gain = [(h * (1 + 1e-9), rest * (1 + 1e-9)) for h, rest in (in_model, in_gain)]
    shape = model_shape(atk, delta, maps, ball=True, second=in_model)
    channels = model_channels(shape, c.theta0.shape)
    E1c, k1c = _affine_inputs(c, r, channels, E1, Wmap)
    Xc, Yc = _sym(sol["Xc"]), _sym(sol["Yc"])
    mats = _affine_blocks(c, q, r, channels, E1c, k1c, Xc, Yc, sol["G"], sol["H"], sol["Lam"], sol["L1"], sol["L2"],
                          sol["skew1"], sol["skew2"], np)
    eigs, ok = _smallest_eigs(mats, ("upper", "lower", "gap"))
    multipliers = min(float(np.linalg.eigvalsh(L)[0]) for L in sol["L1"] + sol["L2"])
    skew = max(float(np.max(np.abs(S + S.T))) for Ss in sol["skew1"] + sol["skew2"] for S in Ss)
    gains = affine_gain_set(atk, c, delta, shape, sol, maps, E1, Wmap, in_gain)
    Acl = A + B @ c.K0
    base = np.poly(Acl)
    slopes = np.array([np.poly(Acl + B @ e[None, :]) - base for e in np.eye(n)])
    fl_base, fl_slopes = loop_polynomial(A, B, c.K0)
    agree = max(float(np.max(np.abs(slopes - fl_slopes)) / np.max(np.abs(slopes))),
                float(np.max(np.abs(base - fl_base))))
    slopes = np.where(np.abs(slopes) >= np.abs(fl_slopes), slopes, fl_slopes)
    swept = sweep(base, slopes, gains.support, 2 * GRID, 2 * ANGLES)
    margin = param("robust.check_margin") * float(np.max(np.abs(base)))
    clean_radius = float(np.max(np.abs(np.linalg.eigvals(Acl))))
    passed = clean_radius < 1 - margin and ok["upper"] and ok["lower"] and ok["gap"] and multipliers >= 0 \
        and skew == 0 and gains.m_lo > 0 and swept.excluded_by > margin and swept.leading > margin and agree < 1e-6
    return Check(passed, "numpy eigenvalues of the affine sandwich's LMIs (smallest: "
                 + ", ".join(f"{k} {v:.3g}" for k, v in eigs.items())
                 + f"; multipliers {multipliers:.3g}); the sweep at {2 * GRID} frequencies excludes zero by "
                 f"{swept.excluded_by:.3g} (margin {margin:.1e}); the clean loop's spectral radius {clean_radius:.4g}",
                 {**{f"min_eig_{k}": v for k, v in eigs.items()}, "multipliers": multipliers, "agreement": agree,
                  "clean_radius": clean_radius, "excluded_by": swept.excluded_by, "margin": margin,
                  "t_e": gains.t_e, "m_lo": gains.m_lo})


register_target(IdentificationAttack, identification_target)
register_mechanism("ident-ce-lqr", directional, "directional", cost=0.5)
register_mechanism("ident-ce-lqr", affine, "affine", cost=0.8)  # 20 times directional's CPU
register_mechanism("ident-ce-lqr", lyapunov, "lyapunov", cost=1.0)
