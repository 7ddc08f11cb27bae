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
only damps it. Two outer sets of x, the certified set their intersection (the smaller support along each direction):
- the expansion: x - x_lin = D'v + (M^-1 - I)(x_lin + D'v) lies in a box plus a ball: each entry of D'v is a quadratic
  form in (a_u, a_y) bounded by its largest singular value (the box), and ||M^-1 - I|| <= spread =
  max((1 - beta)^-2 - 1, 1 - ((1 + beta)^2 + eta^2)^-1) times max||x_lin|| + the box's norm (the ball);
- the damped split: x = M^-1 (I + B)'Q'v + M^-1 E'r0 + M^-1 E'(I - QQ')v exactly, with ||M^-1 (I + B)'|| <= 1/(1 - beta)
  (M >= (I + B)'(I + B)) and ||M^-1 E'|| <= 1/(2 (1 - beta)) (M^-1 E'E M^-1 <= M^-1 - (1 - beta)^2 M^-2): an E that
  moves the fit hard also damps it. Each of the first two terms is its linear part (Q'v, E'r0: exact supports) plus a
  ball (||M^-1 (I + B)' - I|| <= min(spread + beta (1 - beta)^-2, (beta + eta / 2) / (1 - beta)); spread for E'r0) or a
  ball about zero (||Q'v|| / (1 - beta), ||r0|| / (2 (1 - beta))), whichever gives the smaller support; the third is a
  ball of radius min(||(I - QQ')v|| / 2, (||box|| + beta ||Q'v||) / (1 - beta)) / (1 - beta) (||v|| and each linear
  part's largest norm over the budget balls from the operators' norms).
Then, ROUNDS times, a per-direction refinement from the set found so far: the normal equation is exactly
x - x_lin = D'(r(a) - r0) - Q'Phi(a_y) d (r(a) the poisoned fit's residual), so along R's left singular vectors U_j
(R = U S V'), |U_j'(x - x_lin)| <= ||a_y|| (||H(V_j)|| / s_j ||r(a) - r0|| + sum_k c_k ||H(V_k)'Q U_j||), where
H(c) = sum_i c_i T_i is the regressor's filter, c_k >= |V_k'd| the set's extent along V_k and
||r(a) - r0||^2 <= min(||r0||, ||D'r0|| / (1 - beta))^2 + ||v||^2 (r(a) - r0 = (I - P_a) v - P_a r0, two orthogonal
parts, P_a r0 = (Q + D) M^-1 E'r0). That box in U's basis is small along R's strong directions, where the fit barely moves and
where the zero-exclusion test often looks; the certified set is the linear image plus it, intersected with the set
before.
Then the joint bound along the critical directions (option "joint", default on): that inequality holds along any
direction w of d, not only R's singular ones. With g = R^-T w and c = R^-1 g = G0^-1 w (G0 = R'R): w'(d - d_lin) =
g'(x - x_lin) = (H(c) a_y)'(r(a) - r0) - sum_k (V_k'd) g'Q'H(V_k) a_y exactly (D g = Phi(a_y) R^-1 g = H(c) a_y, and
Phi(a_y) d = H(d) a_y = sum_k (V_k'd) H(V_k) a_y), so |w'(d - d_lin)| <= ||a_y|| (||H(c)|| ||r(a) - r0|| +
sum_k c_k ||H(V_k)'Q g||) (Cauchy-Schwarz per term): one operator norm of the combined filter H(c), where summing the
refinement's bounds over the U_j that g mixes gives sum_j |U_j'g| ||H(V_j)|| / s_j >= ||H(c)|| (triangle inequality,
c = sum_j V_j U_j'g / s_j). It is taken along the directions w_i = S_z'u that decide the sweep: the best u at the
CRITICAL smallest local minima of the sweep's bound on a COARSE grid, over the set without it (zero_exclusion.closest;
any direction is valid, these are the ones that matter). For any W and any basis b of d, W = sum alpha_l b_l gives
W'(d - d_lin) <= sum |alpha_l| max|b_l'(d - d_lin)|; the bases used are R'U (whose bound along R'U_j is the refinement's
box) with the U_j that w_i leans on most replaced by w_i (invertible: that coefficient is nonzero), the certified set's
support the linear image's plus the smallest of these sums, intersected with the set before. ||H(c)|| depends only on
the direction (its frequency and angle index on the coarse grid), so each is computed once per data set (the square
root of the largest eigenvalue of H(c) H(c)').
The set {d} = R^-1 {x}, and the true loop's characteristic polynomial, affine in theta, is proven Schur stable over it
by zero exclusion on the unit circle (bilevel.robust.zero_exclusion). The re-check rebuilds the operators by filtering
unit impulses (the learner's own filters, not the dense matrices), recomputes beta1, eta1 and the operators' norms by
SVDs and the Grams from the explicit maps, and re-runs the sweep on a grid twice as fine with twice the directions from
those numbers (the larger of each pair), the joint bound's norms along the same directions by SVDs of the impulse-built
H(c) (the larger of each pair).
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
from .zero_exclusion import Sweep, closest, sweep

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
    """What the VRFT perturbation bound needs of one data set, per unit budget (module docstring): theta0, the clean
    regressor's R (Phi0 = Q R), the Grams of the linear maps a_u -> d, a_y -> d (K_u, K_y) and the norms of R L_u,
    R L_y, eta1 (||Phi(a_y) R^-1|| <= eta1 ||a_y||), beta1 (||Q'Phi(a_y) R^-1|| <= beta1 ||a_y||), the second-order
    coefficients (q_u[i], q_y[i]), ||u||, ||y||, and for the damped split: the Grams of a_y -> d through Q'v and
    through D'r0 (K_v, K_r), the norms of a_y -> Q'Phi(a_y) theta0 and a_y -> D'r0 (lin_v, lin_r), of
    (I - QQ') t(.) and (I - QQ') Phi(.) theta0 (out_u, out_y) and ||r0||; for the refinement: R's SVD (U, sv, Vt),
    ||H(V_k)|| (HV), ||H(V_k)'Q U_j|| (HQ[j, k]) and the norms of t(.) and Phi(.) theta0 (norm_t, norm_f); for the
    joint bound along the critical directions: the dense regressor operators T (k, rows, N) and H(V_k)'Q (HVQ[k],
    N x k)."""

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
    K_v: np.ndarray
    K_r: np.ndarray
    lin_v: float
    lin_r: float
    out_u: float
    out_y: float
    norm_r0: float
    U: np.ndarray
    sv: np.ndarray
    Vt: np.ndarray
    HV: np.ndarray
    HQ: np.ndarray
    HVQ: np.ndarray
    norm_t: float
    norm_f: float
    T: np.ndarray


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
    L_v, L_r = -G0inv @ (phi0.T @ F), L_y + G0inv @ (phi0.T @ F)
    Q = phi0 @ Rinv
    out = lambda A: float(np.linalg.norm(A - Q @ (Q.T @ A), 2))  # noqa: E731
    return Perturbation(theta0, R, L_u @ L_u.T, L_y @ L_y.T, float(np.linalg.norm(R @ L_u, 2)),
                        float(np.linalg.norm(R @ L_y, 2)), eta1, beta1, q_u, q_y, float(np.linalg.norm(atk.u)),
                        float(np.linalg.norm(atk.y)), L_v @ L_v.T, L_r @ L_r.T, float(np.linalg.norm(R @ L_v, 2)),
                        float(np.linalg.norm(R @ L_r, 2)), out(Tu), out(F), float(np.linalg.norm(r0)),
                        *_directions(T, Q, R, lambda A: float(np.linalg.norm(A, 2))), float(np.linalg.norm(Tu, 2)),
                        float(np.linalg.norm(F, 2)), T)


def _directions(T: np.ndarray, Q: np.ndarray, R: np.ndarray, norm) -> tuple[np.ndarray, ...]:
    """(U, sv, Vt, HV, HQ, HVQ) of the refinement (Perturbation docstring), the operator norms by `norm`."""
    U, sv, Vt = np.linalg.svd(R)
    HVQ = np.stack([np.tensordot(v, T, axes=(0, 0)).T @ Q for v in Vt])
    return U, sv, Vt, np.array([norm(np.tensordot(v, T, axes=(0, 0))) for v in Vt]), \
        np.linalg.norm(HVQ @ U, axis=1).T, HVQ


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
_KEPT: dict[int, tuple[VRFTAttack, Perturbation, dict]] = {}


def _entry(atk: VRFTAttack) -> tuple[VRFTAttack, Perturbation, dict]:
    """(atk, perturbation(atk), the joint bound's norms ||H(c)|| by critical direction's key), kept for the last KEPT
    instances (certified_margin certifies one data set many times; the norms do not depend on the budget and the
    bisection meets the same directions again)."""
    return kept(_KEPT, id(atk), lambda: (atk, perturbation(atk), {}), KEPT, usable=lambda hit: hit[0] is atk)[0]


def _cached(atk: VRFTAttack) -> Perturbation:
    """perturbation(atk), kept (_entry)."""
    return _entry(atk)[1]


@dataclass(frozen=True)
class Remainder:
    """The radii (in x = R d) at one budget (module docstring): beta, the expansion's ball and box; the damped split's
    balls about Q'v's and E'r0's linear parts (rem_v, rem_r) or about zero (sat_v, sat_r), and that of M^-1 E'v;
    floor, the lower bound on the smallest singular value of A = Q + D used (1 - beta, or a larger one given)."""

    beta: float
    ball: float
    box: np.ndarray
    rem_v: float
    sat_v: float
    rem_r: float
    sat_r: float
    rest: float
    floor: float


def remainder(P: Perturbation, delta: float, floor: float = 0.0) -> Remainder:
    """The Remainder at budget delta, given `floor`, a proven lower bound on the smallest singular value of
    A = Q + Phi(a_y) R^-1 over the budget ball (0: none known; 1 - beta is one): every bound below that needs
    1 - beta needs only s = max(1 - beta, floor) > 0, since ||M^-1 A'|| = 1 / sigma_min(A) <= 1 / s bounds
    M^-1 (I + B)' = M^-1 A'Q and M^-1 E' = M^-1 A'(I - QQ'), and M >= s^2 I (every radius inf where s <= 0)."""
    r_u, r_y = delta * P.norm_u, delta * P.norm_y
    beta, eta = r_y * P.beta1, r_y * P.eta1
    box = r_y * r_u * P.q_u + r_y ** 2 * P.q_y
    s = max(1.0 - beta, float(floor))
    if not s > 0.0:
        inf = float("inf")
        return Remainder(beta, inf, box, inf, inf, inf, inf, inf, s)
    damp = min(1 / (2 * (1 - beta)), 1 / s) if beta < 1.0 else 1 / s  # ||M^-1 E'||
    spread = max(s ** -2 - 1, 1 - 1 / ((1 + beta) ** 2 + eta ** 2))
    qv, out = r_u * P.lin_u + r_y * P.lin_v, r_u * P.out_u + r_y * P.out_y
    norm_box = float(np.linalg.norm(box))
    return Remainder(beta, spread * (r_u * P.lin_u + r_y * P.lin_y + norm_box), box,
                     min(spread + beta / s ** 2, beta / s + eta * damp) * qv, qv / s,
                     spread * r_y * P.lin_r, P.norm_r0 * damp,
                     min(out * damp, (norm_box + beta * qv) / s ** 2), s)


def support(P: Perturbation, delta: float, rem: Remainder, joint: Joint | None = None, orthogonal: bool = True):
    """The support function of the certified set of d at budget delta (columns of W -> values): the smaller of the
    expansion's (linear image plus R^-1 times ball and box) and the damped split's, refined along R's singular
    directions and, given `joint`, along its critical directions (module docstring); `orthogonal` bounds
    ||r(a) - r0|| by the hypot of its two orthogonal parts' bounds, else by their sum (larger; critical uses both)."""
    r_u, r_y = delta * P.norm_u, delta * P.norm_y
    rinv_t = np.linalg.inv(P.R).T

    def h(W: np.ndarray) -> np.ndarray:
        quad = lambda K: np.sqrt(np.maximum(np.einsum("im,ij,jm->m", W, K, W), 0.0))  # noqa: E731
        X = rinv_t @ W
        size = np.linalg.norm(X, axis=0)
        lin_u, lin_y = r_u * quad(P.K_u), r_y * quad(P.K_y)
        expansion = lin_u + lin_y + rem.ball * size + rem.box @ np.abs(X)
        apart = np.minimum(lin_u + r_y * quad(P.K_v) + rem.rem_v * size, rem.sat_v * size) + \
            np.minimum(r_y * quad(P.K_r) + rem.rem_r * size, rem.sat_r * size)
        damped = np.minimum(lin_u + lin_y + (rem.rem_v + rem.rem_r) * size, apart) + rem.rest * size
        return np.minimum(expansion, damped)
    if not rem.floor > 0.0:
        return h
    parts = (min(P.norm_r0, r_y * P.lin_r / rem.floor), r_u * P.norm_t + r_y * P.norm_f)
    resid = float(np.hypot(*parts)) if orthogonal else sum(parts)
    for _ in range(ROUNDS):
        h = _refined(P, r_u, r_y, resid, h)
    for _ in range(JOINT_ROUNDS if joint is not None else 0):
        h = _joint_refined(P, r_u, r_y, resid, h, joint)
    return h


ROUNDS = 3
JOINT_ROUNDS = 1


@dataclass(frozen=True)
class Joint:
    """Directions w_i of d (W, k x m) with upper bounds on the norms the joint bound along them needs: nH[i] >=
    ||H(G0^-1 w_i)|| (G0 = R'R) and nQ[i, k] >= ||H(V_k)'Q R^-T w_i|| (module docstring)."""

    W: np.ndarray
    nH: np.ndarray
    nQ: np.ndarray


def joint_norms(P: Perturbation, W: np.ndarray, norm, keys: list | None = None,
                known: dict | None = None) -> Joint:
    """The Joint of directions W (k x m), the operator norms ||H(c)|| by `norm` from P's dense operators; with `keys`
    (one hashable per direction that fixes it, e.g. zero_exclusion.closest's) those norms are looked up in and added
    to `known`."""
    Rinv = np.linalg.inv(P.R)
    G = Rinv.T @ W
    known = {} if known is None else known
    keys = keys if keys is not None else [None] * W.shape[1]
    nH = []
    for key, c in zip(keys, (Rinv @ G).T):
        if key is None or key not in known:
            value = norm(np.tensordot(c, P.T, axes=(0, 0)))
            if key is None:
                nH.append(value)
                continue
            known[key] = value
        nH.append(known[key])
    return Joint(W, np.array(nH, float).reshape(-1), np.linalg.norm(P.HVQ @ G, axis=1).T)


def _joint_refined(P: Perturbation, r_u: float, r_y: float, resid: float, before, joint: Joint):
    """One joint refinement (module docstring) of the set whose support function is `before`: the remainder's bound
    along each critical direction w_i, exchanged into the basis R'U for the U_j it leans on most."""
    extent = np.maximum(before(P.Vt.T), before(-P.Vt.T))
    box = r_y * (P.HV / P.sv * resid + P.HQ @ extent)
    wide = r_y * (joint.nH * resid + joint.nQ @ extent)
    to_u = P.U.T @ np.linalg.inv(P.R).T  # W = R'U alpha: alpha = U'R^-T W
    inverses, widths = [], []
    for i, a in enumerate((to_u @ joint.W).T):
        j = int(np.argmax(np.abs(a)))
        if not abs(a[j]) > 0:
            continue  # w_i = 0 bounds nothing
        basis = np.eye(a.size)
        basis[:, j] = a
        inverses.append(np.linalg.solve(basis, to_u))
        widths.append(np.where(np.arange(a.size) == j, wide[i], box))
    if not inverses:
        return before
    inverses, widths = np.array(inverses), np.array(widths)

    def h(W: np.ndarray) -> np.ndarray:
        quad = lambda K: np.sqrt(np.maximum(np.einsum("im,ij,jm->m", W, K, W), 0.0))  # noqa: E731
        rest = np.min(np.einsum("bj,bjm->bm", widths, np.abs(inverses @ W)), axis=0)
        return np.minimum(before(W), r_u * quad(P.K_u) + r_y * quad(P.K_y) + rest)
    return h


def _refined(P: Perturbation, r_u: float, r_y: float, resid: float, before):
    """One refinement (module docstring) of the set whose support function is `before`."""
    extent = np.maximum(before(P.Vt.T), before(-P.Vt.T))
    box = r_y * (P.HV / P.sv * resid + P.HQ @ extent)
    to_u = P.U.T @ np.linalg.inv(P.R).T

    def h(W: np.ndarray) -> np.ndarray:
        quad = lambda K: np.sqrt(np.maximum(np.einsum("im,ij,jm->m", W, K, W), 0.0))  # noqa: E731
        return np.minimum(before(W), r_u * quad(P.K_u) + r_y * quad(P.K_y) + box @ np.abs(to_u @ W))
    return h


GRID = 16384
ANGLES = 9


CRITICAL = 8
"""Frequencies (smallest local minima of the sweep's bound on a coarse grid) whose deciding direction u is bounded
jointly (with SPREAD neighbouring directions on each side)."""
SPREAD = 0
COARSE = 1024


def critical(atk: VRFTAttack, P: Perturbation, delta: float) -> tuple[np.ndarray, list[tuple[int, int]]]:
    """The critical directions (k x m) at budget delta and their keys: where the sweep over the set without the joint
    bound comes closest to failing (zero_exclusion.closest), the union of the picks over that set with ||r(a) - r0||
    bounded by the hypot and by the sum of its parts (a smaller set can flip the best angle at a frequency to one the
    joint bound serves worse); none where no floor is known (beta >= 1)."""
    rem = remainder(P, delta)
    if not rem.floor > 0.0:
        return np.zeros((P.theta0.size, 0)), []
    loop = atk.setting.loop
    columns, keys = [], []
    for orthogonal in (True, False):  # both sets' picks: the smaller set alone may pick a worse angle
        W, found = closest(loop.coefficients(P.theta0), loop.slopes, support(P, delta, rem, orthogonal=orthogonal),
                           COARSE, ANGLES, CRITICAL, SPREAD)
        new = [i for i, key in enumerate(found) if key not in keys]
        columns.append(W[:, new])
        keys += [found[i] for i in new]
    return np.hstack(columns), keys


def _eig_norm(A: np.ndarray) -> float:
    """||A|| as the square root of the largest eigenvalue of A A' (the primary route; the re-check uses SVDs)."""
    return float(np.sqrt(np.linalg.eigvalsh(A @ A.T)[-1]))


def _sweep(atk: VRFTAttack, P: Perturbation, delta: float, refine: int = 1,
           joint: Joint | None = None) -> tuple[float, float, Sweep | None]:
    rem = remainder(P, delta)
    if not rem.floor > 0.0:
        return rem.beta, rem.ball, None
    loop = atk.setting.loop
    base = loop.coefficients(P.theta0)
    return rem.beta, rem.ball, sweep(base, loop.slopes, support(P, delta, rem, joint), GRID * refine,
                                     ANGLES * refine)


def perturbation_bound(target: Target, delta: float, options: dict[str, Any]) -> Evidence | None:
    """Mechanism "perturbation" (module docstring)."""
    atk = target.declaration
    t0 = time.perf_counter()
    _, P, known = _entry(atk)
    joint = None
    if options.get("joint", True):
        W, keys = critical(atk, P, delta)
        joint = joint_norms(P, W, _eig_norm, keys, known)
    beta, ball, found = _sweep(atk, P, delta, joint=joint)
    if found is None:
        return Evidence("perturbation", Proof.UNKNOWN, f"beta = {beta:.3g} >= 1: the poisoned regressor's conditioning "
                        "is not bounded at this budget", {"beta": beta}, Check(False, "nothing to check"),
                        time.perf_counter() - t0)
    numbers = {"beta": beta, "ball": ball, "excluded_by": found.excluded_by, "lipschitz": found.lipschitz,
               "leading": found.leading}
    if not found.proven:
        why = f"the clean loop is not stable (largest root modulus {found.nominal:.4g})" if not found.nominal < 1 \
            else f"zero exclusion fails at delta = {delta:.6g} (guaranteed distance {found.excluded_by:.3g})"
        return Evidence("perturbation", Proof.UNKNOWN, why, numbers, Check(False, "nothing to check"),
                        time.perf_counter() - t0)
    check = recheck(atk, P, delta, joint)
    return Evidence("perturbation", Proof.PROVEN, f"no poisoning with ||a_u|| <= {delta:.6g} ||u||, ||a_y|| <= "
                    f"{delta:.6g} ||y|| destabilizes the true loop (perturbation bound + zero exclusion, distance "
                    f"{found.excluded_by:.3g} > 0)", numbers, check, time.perf_counter() - t0)


def recheck(atk: VRFTAttack, P: Perturbation, delta: float, joint: Joint | None = None) -> Check:
    """The independent re-check (module docstring): operators from impulses, eta1 by SVD, Grams from the explicit
    maps, the joint bound's norms by SVD from those operators, the sweep on a twice finer grid with the larger of
    each pair of numbers."""
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
    L_v = np.linalg.solve(phi0.T @ phi0, -phi0.T @ F)
    L_r = np.linalg.solve(phi0.T @ phi0, np.einsum("r,irn->in", r0, T))
    top = lambda A: float(np.linalg.svd(A, compute_uv=False)[0])  # noqa: E731
    out = lambda A: top(A - phi0 @ np.linalg.lstsq(phi0, A, rcond=None)[0])  # noqa: E731
    again = Perturbation(theta0, R, L_u @ L_u.T, L_y @ L_y.T, top(R @ L_u), top(R @ L_y), eta1, beta1, q_u, q_y,
                         P.norm_u, P.norm_y, L_v @ L_v.T, L_r @ L_r.T, top(R @ L_v), top(R @ L_r), out(Tu), out(F),
                         float(np.linalg.norm(r0)), *_directions(T, phi0 @ Rinv, R, top), top(Tu), top(F), T)
    larger = {f.name: max(getattr(P, f.name), getattr(again, f.name)) for f in dataclasses.fields(Perturbation)
              if isinstance(getattr(P, f.name), float)}
    worst = dataclasses.replace(again, q_u=np.maximum(P.q_u, again.q_u), q_y=np.maximum(P.q_y, again.q_y),
                                HV=np.maximum(P.HV, again.HV), HQ=np.maximum(P.HQ, again.HQ), **larger)
    relative = lambda a, b: float(np.max(np.abs(a - b)) / np.max(np.abs(b)))  # noqa: E731
    agree = max(abs(again.eta1 - P.eta1) / P.eta1, abs(again.beta1 - P.beta1) / P.beta1,
                *(relative(getattr(again, K), getattr(P, K)) for K in ("K_u", "K_y", "K_v", "K_r")))
    if joint is not None:
        top_joint = joint_norms(again, joint.W, top)
        joint = Joint(joint.W, np.maximum(joint.nH, top_joint.nH), np.maximum(joint.nQ, top_joint.nQ))
    _, _, found = _sweep(atk, worst, delta, refine=2, joint=joint)
    scale = float(np.max(np.abs(atk.setting.loop.coefficients(theta0))))
    margin = param("robust.check_margin") * scale
    passed = found is not None and found.proven and found.excluded_by > margin and found.leading > margin \
        and agree < 1e-6
    return Check(passed, f"impulse-built operators agree to {agree:.1e}; the sweep at {2 * GRID} frequencies excludes "
                 f"zero by {-np.inf if found is None else found.excluded_by:.3g} (margin {margin:.1e})",
                 {"agreement": agree, "excluded_by": -np.inf if found is None else found.excluded_by,
                  "margin": margin})


register_target(VRFTAttack, vrft_target)
register_mechanism("vrft", perturbation_bound, "perturbation", cost=1.0)
