"""DeePC (tracking cost) as a certificate target, and its mechanism "kkt-sensitivity".

Learner: the DeePC QP of bilevel.problems.deepc_instance (no input bound), poisoned within ||du|| <= delta ||u|| and
||dy|| <= delta ||y|| (l2). The attacker's goal: the true plant's tracking cost J(u) = ||Mm u - c||^2 of the plan
(Mm = [sqrt(q) S; sqrt(r_weight) I], c = [sqrt(q) (r - free); 0]) at least `factor` times the clean plan's cost J0
(defaults["robust.deepc_cost_factor"], the defenses sweep's degradation goal). The target's "radius" of a plan is
J / (factor J0): >= 1 means the attacker reached the goal, as a spectral radius >= 1 does for the other families.

Exact form of the learner: the depth-L Hankel rows W = [Up; Yp; Uf; Yf] of the poisoned data, K = W W' (2L x 2L).
Where the slack is zero (its multiplier within lambda_y), the plan is u = -(lambda_g / r_weight) v_uf with
M v = h, M = K + lambda_g Pi (Pi = blkdiag(0, I / r_weight, I / q)), h = [u_ini; y_ini; 0; r 1]: the poisoning Delta
(the Hankel rows of (du, dy)) enters only through M = (W0 + Delta)(W0 + Delta)' + lambda_g Pi.

Mechanism "kkt-sensitivity" (a proof at delta):
- the linear part: dv1 = -M0^-1 (W0 Delta' v0 + Delta g0) (g0 = W0' v0) is a linear map of the poisoning; its image
  in the cost, r0 + G a, is bounded over the product of the two balls by Lagrangian duality (S-lemma):
  sup ||r0 + G a||^2 <= r0' (I - Q)^-1 r0 + l_u rho_u^2 + l_y rho_y^2 for any l_u, l_y > 0 with
  Q = G_u G_u' / l_u + G_y G_y' / l_y < I;
- the rest is exactly v - v0 - dv1 = R2 + R3 with the quadratic R2 = -M0^-1 [W0 Delta' dv1 + Delta dg1]
  (dg1 = W0' dv1 + Delta' v0) and R3 = -M^-1 [W Delta' R2 + Delta (W0' R2 + Delta' dv1)]. R2's image in the cost
  is a quadratic form of the poisoning per cost entry, a' B_i a, each bounded over the balls by its blocks' spectral
  norms; R3 is bounded with M >= lambda_g Pi (so (lambda_g / r_weight) ||Mm E_uf M^-1/2|| <= ||Mm||
  sqrt(lambda_g / r_weight)), ||M^-1/2 W|| <= 1, ||M0^-1/2 W0|| <= 1 and M >= (1 - beta)^2 M0 where beta >=
  ||M0^-1/2 Delta|| (so ||M^-1/2 Delta|| <= beta / (1 - beta)): R3 = -M^-1 y3 with ||M^-1/2 y3|| <= y3 :=
  beta ||M0^1/2 R2|| + beta / (1 - beta) (||M0^1/2 R2|| + ||Delta' dv1||), and R3's image in the cost is at most
  ||Mm|| sqrt(lambda_g / r_weight) y3 (the first way); the norm of a linear map F of the poisoning over the two balls
  is bounded by the S-lemma, sup ||F a||^2 <= l_u rho_u^2 + l_y rho_y^2 whenever F'F <= diag(l_u I, l_y I) (at most
  the sum of its two blocks' spectral norms times the radii, 14 % below it for beta on attack_instance(T=100,
  seed=3757552657));
- the cubic rest, a second way, through the plan's own sensitivity P0 = (lambda_g / r_weight) Mm E_uf M0^-1 (the
  cost residual's response to M's right-hand side at the clean data) instead of M's weakest directions. With
  e = v - v0 and g = W' v the poisoned learner's g, M0 e = -(M - M0) v exactly, and (M - M0) v = W0 Delta' v + Delta g,
  so the cost residual is exactly r(a) = r0 + G a + P0 W0 Delta' e + P0 Delta (g - g0). Splitting e = dv1 + (e - dv1)
  and g - g0 = dg1 + (g - g0 - dg1) gives back the quadratic part above, and the rest is
  P0 W0 Delta' (e - dv1) + P0 Delta (g - g0 - dg1) with e - dv1 = -M^-1 [W Delta' dv1 + Delta dg1] and
  g - g0 - dg1 = W' (e - dv1) + Delta' dv1. With rest >= ||M^-1/2 [W Delta' dv1 + Delta dg1]||, the smaller of
  ||Delta' dv1|| + beta / (1 - beta) ||dg1|| and ||M0^1/2 R2|| / (1 - beta) + beta / (1 - beta) ||Delta' dv1|| (the
  bracket is -M0 R2 + Delta Delta' dv1), and y3 >= ||M^-1/2 y3|| as in the first way:
  ||Delta' (e - dv1)|| <= min(beta / (1 - beta) rest, beta ||M0^1/2 R2|| + beta / (1 - beta) y3) (e - dv1 = R2 + R3),
  ||W' (e - dv1)|| <= min(rest, (1 + beta) ||M0^1/2 R2|| + y3) (||W' M^-1/2|| <= 1, W0 W0' <= M0), so the rest is at
  most ||P0 W0|| ||Delta' (e - dv1)|| + sup ||P0 Delta|| (||W' (e - dv1)|| + ||Delta' dv1||). The plan barely reads
  W0's range (||P0 W0|| = 0.156 against the first way's factor 6.4 on attack_instance(T=100, seed=0)) and
  sup ||P0 Delta|| is 19 times smaller than 6.4 beta there; the bound takes the smaller of the two ways;
- a second lower bound on M, through the poisoning's linear part L = W0 Delta' + Delta W0' instead of beta: for t in
  (0, 1], (W - t W0)(W - t W0)' >= 0 gives W W' >= (2t - t^2) W0 W0' + t L, and lambda_g Pi >= (2t - t^2) lambda_g Pi,
  so M >= (2t - t^2) M0 + t L >= t (2 - t - gamma) M0 where gamma >= ||M0^-1/2 L M0^-1/2|| (its Frobenius norm's
  block bound over the balls); t = 1 - gamma / 2 gives M >= (1 - gamma / 2)^2 M0 for gamma < 2. Every (1 - beta)
  above, where it bounds ||M^-1/2 M0^1/2|| <= 1 / (1 - beta), becomes kappa = max(1 - beta, 1 - gamma / 2) > 0
  (so ||M^-1/2 Delta|| <= beta / kappa). The weak directions cost far less this way: the poisoning must cancel the
  data's own (small) component along them, W0' z, not merely be large there (attack_instance(T=100, seed=3757552657):
  beta 619 and gamma / 2 413 per unit delta; at delta 0.0014 the smallest eigenvalue of M0^-1/2 M M0^-1/2 found by
  an alternating descent over the balls is 0.478, (1 - beta)^2 = 0.018, (1 - gamma / 2)^2 = 0.177);
- sqrt(J) <= sqrt(linear bound) + the two remainders' bounds; the slack stays zero if 2 lambda_g ||v_yp||_inf <
  lambda_y over the set (v - v0 - dv1 = -M^-1 [W Delta' dv1 + Delta dg1] bounded the same way).
The re-check builds the linear maps a second way (implicit differentiation of the learner's KKT system in g, numpy),
the clean plan by cvxpy + Clarabel (DeePCAttack.plan), recomputes every norm by SVD and the dual bound at the
mechanism's multipliers from those maps; it passes if the recomputed bound is at most the claimed one (above
rounding) and the multipliers are feasible with a margin.
"""

from __future__ import annotations

import dataclasses
import time
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import scipy.linalg
import scipy.optimize

from ..defaults import param
from ..errors import ModelError
from ..problems.budget import Budget
from ..problems.deepc import declare
from ..problems.deepc_instance import DeePCAttack
from ..solvers.registry import solve
from .target import Signals, Target, register_mechanism, register_target
from .verdict import Check, Evidence, Proof

FAMILY = "deepc-tracking"
PATH = (0.0005, 0.001, 0.002, 0.005, 0.01, 0.02, 0.05)
"""The attack's budget path (relative l2 delta) before bisection."""
AGREE = 1e-6
"""The two routes' bounds must agree to this relative difference (they differ by rounding only)."""


def hankel_rows(atk: DeePCAttack, u: np.ndarray, y: np.ndarray) -> np.ndarray:
    """W = [Up; Yp; Uf; Yf], the depth t_ini + horizon Hankel rows of recorded (u, y) (2L x columns)."""
    depth, k = atk.t_ini + atk.horizon, atk.t_ini
    cols = u.size - depth + 1
    hu = np.lib.stride_tricks.sliding_window_view(np.asarray(u, float), cols)[:depth]
    hy = np.lib.stride_tricks.sliding_window_view(np.asarray(y, float), cols)[:depth]
    return np.vstack([hu[:k], hy[:k], hu[k:], hy[k:]])


def kkt_solution(atk: DeePCAttack, w: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(g, mu): the learner's equality-constrained QP in g with zero slack (Up g = u_ini, Yp g = y_ini) solved from
    its KKT system by numpy; mu are the multipliers of the past rows (the slack stays zero iff |mu_y| <= lambda_y)."""
    k, n = atk.t_ini, atk.horizon
    past, uf, yf = w[:2 * k], w[2 * k:2 * k + n], w[2 * k + n:]
    cols = w.shape[1]
    hess = atk.lambda_g * np.eye(cols) + atk.q * yf.T @ yf + atk.r_weight * uf.T @ uf
    kkt = np.block([[2 * hess, past.T], [past, np.zeros((2 * k, 2 * k))]])
    rhs = np.concatenate([2 * atk.q * atk.reference * yf.sum(axis=0), atk.past_u[-k:], atk.past_y[-k:]])
    z = scipy.linalg.solve(kkt, rhs, assume_a="sym")
    return z[:cols], z[cols:]


def numpy_plan(atk: DeePCAttack, u: np.ndarray, y: np.ndarray) -> np.ndarray:
    """The learner's plan on recorded (u, y): the KKT solve in g (kkt_solution) where its slack multipliers are within
    lambda_y, else cvxpy + Clarabel on the full QP (DeePCAttack.plan). Independent of the mechanism's Gram form."""
    w = hankel_rows(atk, u, y)
    g, mu = kkt_solution(atk, w)
    if np.max(np.abs(mu[atk.t_ini:])) >= atk.lambda_y:
        return atk.plan(u, y)
    k, n = atk.t_ini, atk.horizon
    return w[2 * k:2 * k + n] @ g


@dataclass
class DeePCCost:
    """The certified object: the attack instance, the clean plan's true tracking cost J0 (cvxpy) and the level
    factor J0 the certificates prove the cost stays below; `cache` keeps the mechanism's and the re-check's maps."""

    attack: DeePCAttack
    clean_cost: float
    level: float
    cache: dict[str, Any] = field(default_factory=dict)


def deepc_target(atk: DeePCAttack, starts: int = 1, factor: float | None = None, **options: Any) -> Target:
    """The Target of a deepc-tracking instance with an l2 budget and no input bound (module docstring); the attack
    is the engine's on the registered problem with `starts` starts."""
    if atk.objective != "tracking" or atk.budget.norm != "l2" or atk.u_max is not None:
        raise ModelError(f"DeePC certificates cover the tracking cost with an l2 budget and no input bound; got "
                         f"objective={atk.objective!r}, norm={atk.budget.norm!r}, u_max={atk.u_max!r}")
    if not (atk.q > 0 and atk.r_weight > 0 and atk.lambda_g > 0):
        raise ModelError(f"DeePC certificates need q, r_weight and lambda_g > 0, got {atk.q}, {atk.r_weight}, "
                         f"{atk.lambda_g}")
    clean = float(atk.tracking_cost(atk.plan(atk.u, atk.y)))
    level = float(param("robust.deepc_cost_factor", factor)) * clean
    cost = DeePCCost(atk, clean, level)

    def engine(delta: float, seed: int) -> Signals:
        instance = dataclasses.replace(atk, budget=Budget(delta, "l2"))
        result = solve(declare(instance), starts=starts, seed=seed)
        return {"u": np.ravel(result.x["du"]), "y": np.ravel(result.x["dy"])}

    return Target(f"deepc-tracking-T{atk.u.size}-h{atk.horizon}", FAMILY, cost, {"u": atk.u, "y": atk.y},
                  {"u": float(np.linalg.norm(atk.u)), "y": float(np.linalg.norm(atk.y))},
                  lambda s: numpy_plan(atk, s["u"], s["y"]), lambda plan: float(atk.tracking_cost(plan)) / level,
                  {"engine": engine}, PATH, options=options)


def _cost_metric(atk: DeePCAttack) -> tuple[np.ndarray, np.ndarray]:
    """(Mm, c): J(u) = ||Mm u - c||^2."""
    n = atk.horizon
    mm = np.vstack([np.sqrt(atk.q) * atk.step, np.sqrt(atk.r_weight) * np.eye(n)])
    return mm, np.concatenate([np.sqrt(atk.q) * (atk.reference - atk.free), np.zeros(n)])


def _unit_rows(atk: DeePCAttack) -> np.ndarray:
    """Delta(e_s) for every unit poisoning e_s (first the samples of du, then of dy): (2T, 2L, columns)."""
    t = atk.u.size
    eye = np.eye(2 * t)
    return np.stack([hankel_rows(atk, e[:t], e[t:]) for e in eye])


def _block_norm(rows: np.ndarray, t: int, radii: tuple[float, float]) -> float:
    """An upper bound of sup ||sum_s a_s rows[s]|| (Frobenius) over ||a_u|| <= radii[0], ||a_y|| <= radii[1] (rows: one
    image per unit poisoning, first the t of du): the smaller of the two blocks' spectral norms times their radii,
    summed, and the S-lemma's value l_u radii[0]^2 + l_y radii[1]^2 with F'F <= diag(l_u I, l_y I) (F the flattened
    rows' transpose), l_y = tau l_u at the best tau found by a bounded scalar search, l_u = lambda_max(D^-1/2 F'F
    D^-1/2) (1 + 1e-9) (D = diag(I, tau I)): every tau gives a valid bound."""
    flat = rows.reshape(rows.shape[0], -1)
    nu, ny = np.linalg.norm(flat[:t], 2), np.linalg.norm(flat[t:], 2)
    blocks = radii[0] * nu + radii[1] * ny
    if nu == 0.0 or ny == 0.0:
        return float(blocks)
    gram = flat @ flat.T

    def value(log_tau: float) -> float:
        scale = np.concatenate([np.ones(t), np.full(rows.shape[0] - t, np.exp(-log_tau / 2))])
        return float(np.linalg.eigvalsh(gram * np.outer(scale, scale))[-1] * (1 + 1e-9)
                     * (radii[0] ** 2 + np.exp(log_tau) * radii[1] ** 2))

    centre = np.log(ny * radii[0] / (nu * radii[1]))  # the block sum's tau
    found = scipy.optimize.minimize_scalar(value, bounds=(centre - 5.0, centre + 5.0), method="bounded",
                                           options={"xatol": 1e-6})
    return float(min(blocks, np.sqrt(value(float(found.x)))))


@dataclass(frozen=True)
class Maps:
    """What the bound needs, per unit budget (radii ||u||, ||y||): the clean cost residual r0, the linear map G of the
    poisoning into the cost residual, v0, and the norm bounds of the module docstring."""

    r0: np.ndarray
    g: np.ndarray
    v0: np.ndarray
    beta: float
    gamma: float
    delta_frob: float
    dv1: float
    dv1_m0: float
    dg1: float
    out: float
    s_norm: float
    quad: np.ndarray
    quad_m0: np.ndarray
    p0w0: float
    beta_p: float


def _quadratic_blocks(p: np.ndarray, w0: np.ndarray, units: np.ndarray, dv1: np.ndarray, dg1: np.ndarray,
                      t: int) -> np.ndarray:
    """Per cost entry i, the spectral norms of the blocks (uu, uy, yy) of B_i, a' B_i a = (P [W0 Delta' dv1 + Delta
    dg1])_i (P: v -> cost residual, Delta, dv1, dg1 at the poisoning a): (2N, 3)."""
    x = np.tensordot(p @ w0, units, axes=([1], [2]))  # (i, s, r): Delta(e_s) (P W0)_i'
    y = np.tensordot(p, units, axes=([1], [1]))  # (i, s, c): P_i Delta(e_s)
    b = x @ dv1.T + y @ dg1.T
    b = (b + b.transpose(0, 2, 1)) / 2
    return np.array([[np.linalg.norm(bi[:t, :t], 2), np.linalg.norm(bi[:t, t:], 2), np.linalg.norm(bi[t:, t:], 2)]
                     for bi in b])


def _maps(cost: DeePCCost, dv1: np.ndarray, dg1: np.ndarray, v0: np.ndarray, w0: np.ndarray, m0_inv_uf: np.ndarray,
          u0: np.ndarray, units: np.ndarray) -> Maps:
    """The bounds' numbers from the linear maps dv1 (2T, 2L), dg1 (2T, C), the clean v0, W0, the u_f rows of M0^-1
    and the clean plan u0."""
    atk = cost.attack
    t, k, n, lam = atk.u.size, atk.t_ini, atk.horizon, atk.lambda_g
    radii = (float(np.linalg.norm(atk.u)), float(np.linalg.norm(atk.y)))
    mm, c = _cost_metric(atk)
    pi = np.concatenate([np.zeros(2 * k), np.full(n, 1 / atk.r_weight), np.full(n, 1 / atk.q)])
    m0 = w0 @ w0.T + lam * np.diag(pi)
    ev, vec = np.linalg.eigh(m0)
    s = vec @ np.diag(ev ** -0.5) @ vec.T  # M0^-1/2
    g = mm @ (-(lam / atk.r_weight) * dv1[:, 2 * k:2 * k + n].T)
    p = (lam / atk.r_weight) * mm @ m0_inv_uf  # P0: the plan's (cost residual's) sensitivity to M's right-hand side
    lin = s @ units @ (w0.T @ s)  # M0^-1/2 Delta(e_s) W0' M0^-1/2, per unit poisoning
    return Maps(mm @ u0 - c, g, v0, _block_norm(np.tensordot(units, s, axes=([1], [1])), t, radii),
                _block_norm(lin + lin.transpose(0, 2, 1), t, radii), _block_norm(units, t, radii),
                _block_norm(dv1, t, radii),
                _block_norm(dv1 @ np.linalg.cholesky(m0), t, radii), _block_norm(dg1, t, radii),
                float(np.linalg.norm(mm, 2) * np.sqrt(lam / atk.r_weight)), float(ev[0] ** -0.5),
                _quadratic_blocks(p, w0, units, dv1, dg1, t), _quadratic_blocks(s, w0, units, dv1, dg1, t),
                float(np.linalg.norm(p @ w0, 2)), _block_norm(np.tensordot(units, p, axes=([1], [1])), t, radii))


def gram_maps(cost: DeePCCost) -> Maps:
    """The mechanism's maps, from the Gram form (module docstring)."""
    if "gram" in cost.cache:
        return cost.cache["gram"]
    atk = cost.attack
    k, n, lam = atk.t_ini, atk.horizon, atk.lambda_g
    w0 = hankel_rows(atk, atk.u, atk.y)
    pi = np.diag(np.concatenate([np.zeros(2 * k), np.full(n, 1 / atk.r_weight), np.full(n, 1 / atk.q)]))
    h = np.concatenate([atk.past_u[-k:], atk.past_y[-k:], np.zeros(n), np.full(n, atk.reference)])
    m0 = w0 @ w0.T + lam * pi
    v0 = np.linalg.solve(m0, h)
    g0 = w0.T @ v0
    units = _unit_rows(atk)
    dvt_v0 = np.einsum("src,r->sc", units, v0)  # Delta(e_s)' v0
    dv1 = -np.linalg.solve(m0, (np.einsum("src,c->sr", units, g0) + dvt_v0 @ w0.T).T).T
    cost.cache["gram"] = _maps(cost, dv1, dv1 @ w0 + dvt_v0, v0, w0, np.linalg.inv(m0)[2 * k:2 * k + n],
                               -(lam / atk.r_weight) * v0[2 * k:2 * k + n], units)
    return cost.cache["gram"]


def kkt_maps(cost: DeePCCost) -> Maps:
    """The same maps the second way (the re-check): the derivative of the learner's KKT system in g (numpy) at the
    clean data for every unit poisoning; v recovered from it (v_f = -[r_weight u; q (y - r)] / lambda_g, v_p = -mu /
    (2 lambda_g)); the clean plan by cvxpy + Clarabel."""
    if "kkt" in cost.cache:
        return cost.cache["kkt"]
    atk = cost.attack
    k, n, lam, q, rw = atk.t_ini, atk.horizon, atk.lambda_g, atk.q, atk.r_weight
    w0 = hankel_rows(atk, atk.u, atk.y)
    cols = w0.shape[1]
    g0, mu0 = kkt_solution(atk, w0)
    units = _unit_rows(atk)
    past, uf, yf = w0[:2 * k], w0[2 * k:2 * k + n], w0[2 * k + n:]
    hess = lam * np.eye(cols) + q * yf.T @ yf + rw * uf.T @ uf
    kkt = np.block([[2 * hess, past.T], [past, np.zeros((2 * k, 2 * k))]])
    dp, du, dy = units[:, :2 * k], units[:, 2 * k:2 * k + n], units[:, 2 * k + n:]
    # d(2 H g0 + past' mu0 - 2 q r Yf' 1) and d(past g0) along each unit poisoning
    dh_g0 = (q * (np.einsum("snc,n->sc", dy, yf @ g0) + np.einsum("nc,snd,d->sc", yf, dy, g0))
             + rw * (np.einsum("snc,n->sc", du, uf @ g0) + np.einsum("nc,snd,d->sc", uf, du, g0)))
    top = 2 * dh_g0 + np.einsum("spc,p->sc", dp, mu0) - 2 * q * atk.reference * dy.sum(axis=1)
    rhs = -np.hstack([top, np.einsum("spc,c->sp", dp, g0)])
    dz = scipy.linalg.solve(kkt, rhs.T, assume_a="sym").T
    dg, dmu = dz[:, :cols], dz[:, cols:]
    du_plan = dg @ uf.T + du @ g0
    dy_plan = dg @ yf.T + dy @ g0
    dv1 = np.hstack([-dmu / (2 * lam), -rw * du_plan / lam, -q * dy_plan / lam])
    u_plan, y_plan = uf @ g0, yf @ g0
    v0 = np.concatenate([-mu0 / (2 * lam), -rw * u_plan / lam, -q * (y_plan - atk.reference) / lam])
    pi = np.concatenate([np.zeros(2 * k), np.full(n, 1 / rw), np.full(n, 1 / q)])
    chol = scipy.linalg.cho_factor(w0 @ w0.T + lam * np.diag(pi))
    m0_inv_uf = scipy.linalg.cho_solve(chol, np.eye(2 * k + 2 * n)[:, 2 * k:2 * k + n]).T
    cost.cache["kkt"] = _maps(cost, dv1, dg, v0, w0, m0_inv_uf, atk.plan(atk.u, atk.y), units)
    return cost.cache["kkt"]


def _dual_value(maps: Maps, t: int, radii: tuple[float, float], mult: tuple[float, float]) -> float:
    """r0' (I - Q)^-1 r0 + l_u rho_u^2 + l_y rho_y^2 at multipliers (l_u, l_y) (inf where Q < I fails)."""
    gu, gy = maps.g[:, :t], maps.g[:, t:]
    q = gu @ gu.T / mult[0] + gy @ gy.T / mult[1]
    if np.linalg.eigvalsh(q)[-1] >= 1.0:
        return float("inf")
    return float(maps.r0 @ np.linalg.solve(np.eye(q.shape[0]) - q, maps.r0) + mult[0] * radii[0] ** 2
                 + mult[1] * radii[1] ** 2)


def _best_multipliers(maps: Maps, t: int, radii: tuple[float, float]) -> tuple[float, float]:
    """The dual's multipliers (l_u, l_y), minimized over their logarithms by Nelder-Mead."""
    gu, gy = maps.g[:, :t], maps.g[:, t:]
    start = np.log([4 * max(np.linalg.norm(gu, 2) ** 2, 1e-300), 4 * max(np.linalg.norm(gy, 2) ** 2, 1e-300)])
    found = scipy.optimize.minimize(lambda x: _dual_value(maps, t, radii, tuple(np.exp(x))), start,
                                    method="Nelder-Mead", options={"xatol": 1e-6, "fatol": 1e-12})
    return tuple(float(v) for v in np.exp(found.x if np.isfinite(found.fun) else start))


def cost_bound(maps: Maps, atk: DeePCAttack, delta: float, mult: tuple[float, float]) -> dict[str, float]:
    """The proven bound at delta from the maps (module docstring): the linear part's dual value at `mult`, the
    remainder, the bound on J, and the slack multipliers' bound; inf where kappa = max(1 - beta, 1 - gamma / 2) <= 0
    (M >= kappa^2 M0)."""
    t = atk.u.size
    radii = (delta * float(np.linalg.norm(atk.u)), delta * float(np.linalg.norm(atk.y)))
    beta = maps.beta * delta
    kappa = max(1.0 - beta, 1.0 - maps.gamma * delta / 2)  # M >= kappa^2 M0
    linear = _dual_value(maps, t, radii, mult)
    if kappa <= 0.0 or not np.isfinite(linear):
        return {"beta": beta, "kappa": kappa, "linear": linear, "remainder": float("inf"), "bound": float("inf"),
                "slack_multiplier": float("inf")}
    a2 = delta ** 2 * min(maps.delta_frob * maps.dv1, maps.beta * maps.dv1_m0)  # ||Delta' dv1||
    squares = np.array([radii[0] ** 2, 2 * radii[0] * radii[1], radii[1] ** 2])
    b2 = min(a2 + beta * maps.dg1 * delta, float(np.linalg.norm(maps.quad_m0 @ squares)))  # ||M0^1/2 R2||
    second = float(np.linalg.norm(maps.quad @ squares))
    grow = beta / kappa  # >= ||M^-1/2 Delta||
    # >= ||M^-1/2 [W Delta' dv1 + Delta dg1]|| = ||M^1/2 (v - v0 - dv1)||
    rest = min(a2 + grow * maps.dg1 * delta, b2 / kappa + grow * a2)
    y3 = beta * b2 + grow * (b2 + a2)  # >= ||M^-1/2 y3||
    through_m = maps.out * y3
    d_rest = min(grow * rest, beta * b2 + grow * y3)  # >= ||Delta' (v - v0 - dv1)||
    w_rest = min(rest, (1 + beta) * b2 + y3)  # >= ||W' (v - v0 - dv1)||
    through_plan = maps.p0w0 * d_rest + maps.beta_p * delta * (w_rest + a2)
    third = min(through_m, through_plan)
    remainder = second + third
    dv = maps.dv1 * delta + maps.s_norm / kappa * (a2 + grow * maps.dg1 * delta)
    k = atk.t_ini
    slack = 2 * atk.lambda_g * (float(np.max(np.abs(maps.v0[k:2 * k]))) + dv)
    return {"beta": beta, "kappa": kappa, "linear": linear, "second_order": second, "third_through_m": through_m,
            "third_through_plan": through_plan, "remainder": remainder,
            "bound": (np.sqrt(linear) + remainder) ** 2, "slack_multiplier": slack}


def sensitivity(target: Target, delta: float | None, options: dict[str, Any]) -> Evidence | None:
    """Mechanism "kkt-sensitivity" (module docstring): proven when the bound on the tracking cost is below the level,
    else a proven bound (bounded)."""
    cost = target.declaration
    if not isinstance(cost, DeePCCost):
        return None
    t0 = time.perf_counter()
    atk = cost.attack
    maps = gram_maps(cost)
    radii = (delta * target.scale["u"], delta * target.scale["y"])
    mult = _best_multipliers(maps, atk.u.size, radii)
    found = cost_bound(maps, atk, delta, mult)
    numbers = {**found, "level": cost.level, "clean_cost": cost.clean_cost, "multiplier_u": mult[0],
               "multiplier_y": mult[1]}
    if not (np.isfinite(found["bound"]) and found["slack_multiplier"] < atk.lambda_y):
        return Evidence("kkt-sensitivity", Proof.UNKNOWN, f"no bound at delta = {delta:.6g} (beta delta = "
                        f"{found['beta']:.3g}, slack multiplier bound {found['slack_multiplier']:.3g})", numbers,
                        Check(False, "not attempted: no bound"), time.perf_counter() - t0)
    proven = found["bound"] < cost.level
    check = recheck(cost, delta, found, mult, proven)
    if proven:
        return Evidence("kkt-sensitivity", Proof.PROVEN,
                        f"every poisoning with ||du|| <= {radii[0]:.6g}, ||dy|| <= {radii[1]:.6g} (delta = "
                        f"{delta:.6g}) leaves the true tracking cost at most {found['bound']:.6g} < "
                        f"{cost.level:.6g} (the level, {cost.level / cost.clean_cost:g} x the clean "
                        f"{cost.clean_cost:.6g})",
                        numbers, check, time.perf_counter() - t0)
    return Evidence("kkt-sensitivity", Proof.BOUNDED,
                    f"the true tracking cost is at most {found['bound']:.6g} for every poisoning within delta = "
                    f"{delta:.6g} (above the level {cost.level:.6g})", numbers, check, time.perf_counter() - t0)


def recheck(cost: DeePCCost, delta: float, found: dict[str, float], mult: tuple[float, float], proven: bool) -> Check:
    """The second route (module docstring): the bound recomputed from kkt_maps at the same multipliers must agree
    with the claimed one (relative AGREE), keep the slack at zero and, for a proof, stay below the level by a margin
    above rounding."""
    atk = cost.attack
    again = cost_bound(kkt_maps(cost), atk, delta, mult)
    margin = param("robust.check_margin") * (1.0 + cost.level)
    passed = bool(abs(again["bound"] - found["bound"]) <= AGREE * found["bound"]
                  and again["slack_multiplier"] < atk.lambda_y and (not proven or again["bound"] < cost.level - margin))
    return Check(passed, "numpy: the linear maps from the KKT system in g, the clean plan by cvxpy, the norms by SVD "
                 "and the dual bound at the same multipliers", {"recomputed_bound": again["bound"],
                                                              "recomputed_linear": again["linear"],
                                                              "recomputed_remainder": again["remainder"]})


register_target(DeePCAttack, deepc_target)
register_mechanism(FAMILY, sensitivity, "kkt-sensitivity", cost=0.0)
