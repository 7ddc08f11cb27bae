"""VRFT as a certificate target: the learner's least squares theta = argmin ||Phi(y + a_y) theta - t(u + a_u)||
with Phi and t linear in the poisoning, judged by the true plant's closed-loop polynomial (affine in theta).

Budget: delta is the relative l2 budget of both signals, ||a_u|| <= delta ||u||, ||a_y|| <= delta ||y|| (the
defenses frontier's eps_u = eps_y = eps). The attack is the project's joint attack on the destabilize objective
(the attacker's ARX model of the loop), the random baseline its white-noise poisoning.

Mechanism "perturbation": with d = theta - theta0, r0 the clean residual, v = t(a_u) - Phi(a_y) theta0 and
Phi0 = Q R, the poisoned fit is exactly x = R d = M^-1 (x_lin + D'v), M = A'A, A = Q + D, D = Phi(a_y) R^-1
(Q'r0 = 0), x_lin = Q'v + D'r0. x_lin is a linear map of (a_u, a_y) whose image of the budget balls has an exact support
function. Split D = Q B + E (B = Q'D, E orthogonal to Q): M = (I + B)'(I + B) + E'E, so (1 - beta)^2 I <= M <=
((1 + beta)^2 + eta^2) I where ||B|| <= beta = beta1 ||a_y|| < 1 and ||E|| <= ||D|| <= eta = eta1 ||a_y|| (beta1^2,
eta1^2 the largest eigenvalues of the stacked whitened regressor operators, projected on Q and not): only the part of
the regressor perturbation inside the clean regressor's range can make the poisoned fit singular; the rest (E'E >= 0)
only damps it. The remainder x - x_lin = D'v + (M^-1 - I)(x_lin + D'v) lies in a box plus a ball: each entry of D'v is
a quadratic form in (a_u, a_y) bounded by its largest singular value (the box), and ||M^-1 - I|| <= spread =
max((1 - beta)^-2 - 1, 1 - ((1 + beta)^2 + eta^2)^-1) times max||x_lin|| + the box's norm (the ball). The set {d}
is then inside the linear image plus R^-1 times that ball and box, and the true loop's characteristic polynomial,
affine in theta, is proven Schur stable over it by zero exclusion on the unit circle (bilevel.robust.zero_exclusion).
The re-check rebuilds the operators by filtering unit impulses (the learner's own filters, not the dense matrices),
recomputes beta1 and eta1 by SVDs and the Grams from the explicit maps, and re-runs the sweep on a grid twice as fine
with twice the directions from those numbers.
"""

from __future__ import annotations

import dataclasses
import time
from dataclasses import dataclass
from typing import Any

import numpy as np

from ..attacks.vrft_methods import attack
from ..defaults import param
from ..kept import kept
from ..problems.budget import Budget
from ..problems.vrft_instance import VRFTAttack
from .target import Signals, Target, register_mechanism, register_target
from .verdict import Check, Evidence, Proof
from .zero_exclusion import Sweep, sweep

PATH = (0.01, 0.02, 0.05, 0.1, 0.2, 0.5)
"""The attack's budget path before bisection (the defenses frontier's VRFT path)."""
ATTACK_STARTS = 64
"""Starts of the joint attack (the issue's 64)."""


def refit(atk: VRFTAttack, signals: Signals) -> np.ndarray:
    """The VRFT learner on (u, y) by numpy least squares (the regressor's filters, np.linalg.lstsq)."""
    reg = atk.setting.regressor
    return np.linalg.lstsq(reg(signals["y"]), reg.targets(signals["u"]), rcond=None)[0]


def at_budget(atk: VRFTAttack, delta: float) -> VRFTAttack:
    """The instance with both budgets at relative l2 budget delta, attacking the destabilize objective."""
    return dataclasses.replace(atk, budget_u=Budget(delta), budget_y=Budget(delta), objective="destabilize",
                               theta_target=None)


def vrft_target(atk: VRFTAttack, starts: int = ATTACK_STARTS, **options: Any) -> Target:
    """The Target of a VRFT attack instance (module docstring); options go to the mechanisms."""
    def method(name: str, **kw: Any):
        def run(delta: float, seed: int) -> Signals:
            result = attack(at_budget(atk, delta), name, seed=seed, **kw)
            return {"u": np.asarray(result.x["a_u"], float), "y": np.asarray(result.x["a_y"], float)}
        return run

    return Target(f"vrft-N{atk.N}", "vrft", atk, {"u": atk.u, "y": atk.y},
                  {"u": float(np.linalg.norm(atk.u)), "y": float(np.linalg.norm(atk.y))},
                  lambda s: refit(atk, s), atk.setting.loop.spectral_radius,
                  {"joint": method("joint", starts=starts), "white-noise": method("white-noise")}, PATH,
                  options=options)


@dataclass(frozen=True)
class Perturbation:
    """What the VRFT perturbation bound needs of one data set, per unit budget (module `bound` docstring): theta0,
    the clean regressor's R (Phi0 = Q R), the Grams of the linear maps a_u -> d, a_y -> d (K_u, K_y) and the norms of
    R L_u, R L_y, eta1 (||Phi(a_y) R^-1|| <= eta1 ||a_y||), beta1 (||Q'Phi(a_y) R^-1|| <= beta1 ||a_y||), the
    second-order coefficients (q_u[i], q_y[i]) and ||u||, ||y||."""

    theta0: np.ndarray
    R: np.ndarray
    K_u: np.ndarray
    K_y: np.ndarray
    lin_u: float
    lin_y: float
    eta1: float
    beta1: float
    q_u: np.ndarray
    q_y: np.ndarray
    norm_u: float
    norm_y: float


def _operators(atk: VRFTAttack) -> tuple[np.ndarray, np.ndarray]:
    """The dense regressor operators T_i (k, rows, N) with Phi(y)[:, i] = T_i y, and the targets' (rows, N)."""
    reg, N = atk.setting.regressor, atk.N
    targets = np.eye(N)[: reg.rows(N)] if reg.prefilter is None else reg.prefilter.dense(N)[: reg.rows(N)]
    return reg.dense(N), targets


def perturbation(atk: VRFTAttack) -> Perturbation:
    """The data set's Perturbation, from the dense operators (O(N^3) once; every budget reuses it)."""
    T, Tu = _operators(atk)
    phi0, theta0 = atk.phi0, atk.theta0
    r0 = atk.t0 - phi0 @ theta0
    _, R = np.linalg.qr(phi0)
    Rinv = np.linalg.inv(R)
    G0inv = Rinv @ Rinv.T
    F = np.einsum("i,irn->rn", theta0, T)  # a_y -> Phi(a_y) theta0
    L_u = G0inv @ (phi0.T @ Tu)
    L_y = G0inv @ (np.einsum("r,irn->in", r0, T) - phi0.T @ F)
    M = np.tensordot(Rinv, T, axes=(0, 0))  # Phi(a_y) R^-1 x = sum_i x_i M_i a_y
    eta1, beta1 = _gains(M, phi0 @ Rinv, lambda op: float(np.sqrt(np.linalg.eigvalsh(op.T @ op)[-1])))
    q_u = np.array([np.linalg.norm(Tu.T @ m, 2) for m in M])
    q_y = np.array([np.max(np.abs(np.linalg.eigvalsh(0.5 * (m.T @ F + F.T @ m)))) for m in M])
    return Perturbation(theta0, R, L_u @ L_u.T, L_y @ L_y.T, float(np.linalg.norm(R @ L_u, 2)),
                        float(np.linalg.norm(R @ L_y, 2)), eta1, beta1, q_u, q_y, float(np.linalg.norm(atk.u)),
                        float(np.linalg.norm(atk.y)))


def _gains(M: np.ndarray, Q: np.ndarray, norm) -> tuple[float, float]:
    """(eta1, beta1): the norms (by `norm`) of a_y -> Phi(a_y) R^-1 and a_y -> Q'Phi(a_y) R^-1 (stacked M_i, Q'M_i)."""
    N = M.shape[-1]
    return norm(M.reshape(-1, N)), norm(np.einsum("rj,irn->ijn", Q, M).reshape(-1, N))


def _impulse_operators(atk: VRFTAttack) -> tuple[np.ndarray, np.ndarray]:
    """_operators again, column by column from the learner's filters on unit impulses (the re-check's route)."""
    reg, N = atk.setting.regressor, atk.N
    eye = np.eye(N)
    T = np.transpose(reg.stack(eye), (2, 1, 0))  # stack: (N inputs, rows, k) -> (k, rows, N)
    Tu = np.stack([reg.targets(e) for e in eye], axis=1)
    return T, Tu


KEPT = 8
_KEPT: dict[int, tuple[VRFTAttack, Perturbation]] = {}


def _cached(atk: VRFTAttack) -> Perturbation:
    """perturbation(atk), kept for the last KEPT instances (certified_margin certifies one data set many times)."""
    return kept(_KEPT, id(atk), lambda: (atk, perturbation(atk)), KEPT, usable=lambda hit: hit[0] is atk)[0][1]


def remainder(P: Perturbation, delta: float) -> tuple[float, float, np.ndarray]:
    """(beta, ball, box) at budget delta: the bound on ||B||, the radius of the remainder's ball and the entries' bounds
    of its box (module docstring; ball inf where beta >= 1)."""
    r_u, r_y = delta * P.norm_u, delta * P.norm_y
    beta, eta = r_y * P.beta1, r_y * P.eta1
    box = r_y * r_u * P.q_u + r_y ** 2 * P.q_y
    if beta >= 1.0:
        return beta, float("inf"), box
    spread = max((1 - beta) ** -2 - 1, 1 - 1 / ((1 + beta) ** 2 + eta ** 2))
    return beta, spread * (r_u * P.lin_u + r_y * P.lin_y + float(np.linalg.norm(box))), box


def support(P: Perturbation, delta: float, ball: float, box: np.ndarray):
    """The support function of the certified set of d at budget delta (columns of W -> values): the linear image plus
    R^-1 times the remainder's ball and box."""
    r_u, r_y = delta * P.norm_u, delta * P.norm_y
    rinv_t = np.linalg.inv(P.R).T

    def h(W: np.ndarray) -> np.ndarray:
        quad = lambda K: np.sqrt(np.maximum(np.einsum("im,ij,jm->m", W, K, W), 0.0))  # noqa: E731
        X = rinv_t @ W
        return r_u * quad(P.K_u) + r_y * quad(P.K_y) + ball * np.linalg.norm(X, axis=0) + box @ np.abs(X)
    return h


GRID = 16384
ANGLES = 9


def _sweep(atk: VRFTAttack, P: Perturbation, delta: float, refine: int = 1) -> tuple[float, float, Sweep | None]:
    beta, ball, box = remainder(P, delta)
    if not np.isfinite(ball):
        return beta, ball, None
    loop = atk.setting.loop
    base = loop.coefficients(P.theta0)
    return beta, ball, sweep(base, loop.slopes, support(P, delta, ball, box), GRID * refine, ANGLES * refine)


def perturbation_bound(target: Target, delta: float, options: dict[str, Any]) -> Evidence | None:
    """Mechanism "perturbation" (module docstring)."""
    atk = target.declaration
    t0 = time.perf_counter()
    P = _cached(atk)
    beta, ball, found = _sweep(atk, P, delta)
    if found is None:
        return Evidence("perturbation", Proof.UNKNOWN, f"beta = {beta:.3g} >= 1: the poisoned regressor's conditioning "
                        "is not bounded at this budget", {"beta": beta}, Check(False, "nothing to check"),
                        time.perf_counter() - t0)
    numbers = {"beta": beta, "ball": ball, "excluded_by": found.excluded_by, "lipschitz": found.lipschitz,
               "leading": found.leading}
    if not found.proven:
        return Evidence("perturbation", Proof.UNKNOWN, f"zero exclusion fails at delta = {delta:.6g} (guaranteed "
                        f"distance {found.excluded_by:.3g})", numbers, Check(False, "nothing to check"),
                        time.perf_counter() - t0)
    check = recheck(atk, P, delta)
    return Evidence("perturbation", Proof.PROVEN, f"no poisoning with ||a_u|| <= {delta:.6g} ||u||, ||a_y|| <= "
                    f"{delta:.6g} ||y|| destabilizes the true loop (perturbation bound + zero exclusion, distance "
                    f"{found.excluded_by:.3g} > 0)", numbers, check, time.perf_counter() - t0)


def recheck(atk: VRFTAttack, P: Perturbation, delta: float) -> Check:
    """The independent re-check (module docstring): operators from impulses, eta1 by SVD, Grams from the explicit
    maps, the sweep on a twice finer grid with the larger of each pair of numbers."""
    T, Tu = _impulse_operators(atk)
    phi0 = np.einsum("irn,n->ri", T, atk.y)
    theta0 = np.linalg.lstsq(phi0, Tu @ atk.u, rcond=None)[0]
    r0 = Tu @ atk.u - phi0 @ theta0
    R = np.linalg.qr(phi0)[1]
    R = R * np.sign(np.diag(R))[:, None] * np.sign(np.diag(P.R))[:, None]
    Rinv = np.linalg.inv(R)
    M = np.tensordot(Rinv, T, axes=(0, 0))
    eta1, beta1 = _gains(M, phi0 @ Rinv, lambda op: float(np.linalg.svd(op, compute_uv=False)[0]))
    F = np.einsum("i,irn->rn", theta0, T)
    G0inv = Rinv @ Rinv.T
    L_u = np.linalg.solve(phi0.T @ phi0, phi0.T @ Tu)
    L_y = G0inv @ (np.einsum("r,irn->in", r0, T) - phi0.T @ F)
    q_u = np.array([np.linalg.svd(Tu.T @ m, compute_uv=False)[0] for m in M])
    q_y = np.array([np.linalg.svd(0.5 * (m.T @ F + F.T @ m), compute_uv=False)[0] for m in M])
    again = Perturbation(theta0, R, L_u @ L_u.T, L_y @ L_y.T, float(np.linalg.svd(R @ L_u, compute_uv=False)[0]),
                         float(np.linalg.svd(R @ L_y, compute_uv=False)[0]), eta1, beta1, q_u, q_y, P.norm_u,
                         P.norm_y)
    worst = Perturbation(theta0, R, again.K_u, again.K_y,
                         max(P.lin_u, again.lin_u), max(P.lin_y, again.lin_y), max(P.eta1, again.eta1),
                         max(P.beta1, again.beta1), np.maximum(P.q_u, again.q_u), np.maximum(P.q_y, again.q_y),
                         P.norm_u, P.norm_y)
    agree = max(abs(again.eta1 - P.eta1) / P.eta1, abs(again.beta1 - P.beta1) / P.beta1,
                float(np.max(np.abs(again.K_y - P.K_y)) / np.max(np.abs(P.K_y))),
                float(np.max(np.abs(again.K_u - P.K_u)) / np.max(np.abs(P.K_u))))
    _, _, found = _sweep(atk, worst, delta, refine=2)
    scale = float(np.max(np.abs(atk.setting.loop.coefficients(theta0))))
    margin = param("robust.check_margin") * scale
    passed = found is not None and found.excluded_by > margin and found.leading > margin and agree < 1e-6
    return Check(passed, f"impulse-built operators agree to {agree:.1e}; the sweep at {2 * GRID} frequencies excludes "
                 f"zero by {-np.inf if found is None else found.excluded_by:.3g} (margin {margin:.1e})",
                 {"agreement": agree, "excluded_by": -np.inf if found is None else found.excluded_by,
                  "margin": margin})


register_target(VRFTAttack, vrft_target)
register_mechanism("vrft", perturbation_bound, "perturbation", cost=1.0)
