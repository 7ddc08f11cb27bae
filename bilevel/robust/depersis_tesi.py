"""De Persis–Tesi as a certificate target: the learner's gain under input poisoning Du is K = (U0 + Du) Q (X0 Q)^-1
= K0 + Du G, G = Q (X0 Q)^-1, exactly affine in Du: the SDP (designs lqr and stabilizing) sees only X0 and X1, so its
Q (the min-norm selection's, or Clarabel's / SCS's own) does not move with the poisoning. The true loop is
A + B K0 + B Du G: a norm-bounded perturbation of the clean loop Acl0 = A + B K0.

Budget: delta is the RMS per-entry budget, ||Du||_F <= delta sqrt(m T) (the l2 ball that contains the Willems attacks'
linf box |Du_ij| <= delta and touches it at its vertices). Mechanisms (a proof at radius r = delta sqrt(m T)):
- "stability-triangle" (n = 2, m = 1, exact): the characteristic polynomial z^2 + a1 z + a0 of Acl0 + b k is affine in
  k = Du G, and {Du G : ||Du|| <= r} is the ellipse {xi G : ||xi|| <= r}; z^2 + a1 z + a0 is Schur iff its three affine
  functions p(1), p(-1), 1 - a0 are positive, so the loop is stable for every Du iff r < min_i f_i(0) / ||G grad f_i||
  (the minimizer puts an eigenvalue on the unit circle: the bound is the exact smallest destabilizing radius).
  Re-check: f_i and their gradients recomputed by numpy determinants of the perturbed loop at k = 0 and unit vectors.
- "small-gain" (any size): the discrete bounded-real LMI with P > 0, mu = r^2:
      [[Acl0' P Acl0 - P + mu G'G, Acl0' P B], [B' P Acl0, B' P B - I]] < 0,
  whose quadratic form in (x, w = Du G x), ||w|| <= r ||G x||, gives V(x+) < V(x) for every ||Du||_2 <= r (so for
  ||Du||_F <= r). Clarabel maximizes mu once per target; the proof at r re-checks the LMI at mu = r^2 by numpy
  eigenvalues with a margin above rounding. It certifies the complex stability radius 1 / ||G (zI - Acl0)^-1 B||_inf,
  the best a common quadratic Lyapunov function gives; the real poisoning may need more.
The attack "minimal" (the upper side) builds the smallest real Du destabilizing the loop: for z = e^{jw} and v in C^m,
the least-Frobenius Du with Du H(z) v = v (H(z) = G (zI - Acl0)^-1 B) is V P^+ with P = [Re Hv, Im Hv], V = [Re v,
Im v]; minimized over a grid of (w, v) and refined locally (at z = +-1, 1 / sigma_max(H)); judged by the numpy re-fit.
"""

from __future__ import annotations

import dataclasses
import time
from dataclasses import dataclass, field
from typing import Any

import cvxpy as cp
import numpy as np
import scipy.optimize

from ..attacks.willems import destabilize_attack
from ..ddc.depersis_tesi import lqr_controller, min_norm_q, stabilizing_controller, state_data
from ..defaults import param
from ..errors import ModelError
from ..lower.quadratic import solve_clarabel
from ..problems.willems import build_attack
from ..problems.willems_instance import WillemsAttack
from .target import Signals, Target, register_mechanism, register_target
from .verdict import Check, Evidence, Proof

FAMILY = "depersis-tesi"
SELECTIONS = ("min-norm", "clarabel", "scs")
PATH = (0.02, 0.05, 0.1, 0.2, 0.3, 0.5, 0.7, 1.0, 1.5, 2.0)
"""The attack's budget path (RMS per-entry delta) before bisection."""
FREQUENCIES, DIRECTIONS = 256, 64
"""The minimal attack's grid: frequencies in (0, pi) and random directions v per frequency."""
PUSH = 1.0 + 1e-6
"""A poisoning on the unit circle's boundary scaled by this to reach past it (the attack, the triangle's refutation)."""


def learner_q(attack: WillemsAttack) -> np.ndarray:
    """The learner's Q on the clean X0, X1 (it ignores the input poisoning): the SDP solved by cvxpy with the
    selection's solver, projected onto the row space of [X0; X1] for the min-norm selection."""
    s = attack.setting
    solver = "clarabel" if s.selection == "min-norm" else s.selection
    if s.design == "stabilizing":
        q = stabilizing_controller(attack.x, attack.u, solver=solver).q
    else:
        q = lqr_controller(attack.x, attack.u, attack.qx, input_cost=False, solver=solver).q
    if s.selection == "min-norm":
        data = state_data(attack.x, attack.u)
        q = min_norm_q(np.vstack([data.x0, data.x1]), q)
    return q


@dataclass
class DPTLoop:
    """The certified object: the attack instance and its true loop Acl0 + B Du G (module docstring); `cache` keeps
    what the mechanisms compute once per target (the small-gain LMI's solution, the minimal poisoning)."""

    attack: WillemsAttack
    acl: np.ndarray
    b: np.ndarray
    g: np.ndarray
    cache: dict[str, Any] = field(default_factory=dict)


def dpt_target(attack: WillemsAttack, **options: Any) -> Target:
    """The Target of a Willems attack instance with input poisoning of the lqr or stabilizing design and the min-norm,
    clarabel or scs selection (module docstring); options go to the mechanisms."""
    s = attack.setting
    if s.poison != "u" or s.design not in ("lqr", "stabilizing") or s.selection not in SELECTIONS:
        raise ModelError(f"De Persis-Tesi certificates need input poisoning (poison='u') of design lqr or stabilizing "
                         f"and selection {', '.join(SELECTIONS)}; got poison={s.poison!r}, design={s.design!r}, "
                         f"selection={s.selection!r}")
    data = state_data(attack.x, attack.u)
    q = learner_q(attack)
    a, b = s.plant_matrices()
    m, t = attack.u.shape

    def refit(signals: Signals) -> np.ndarray:  # K = U0' Q (X0 Q)^-1 by numpy, the learner's Q fixed
        return np.linalg.solve((data.x0 @ q).T, (signals["u"] @ q).T).T

    def radius(gain: np.ndarray) -> float:
        return float(np.max(np.abs(np.linalg.eigvals(a + b @ gain))))

    def box(delta: float, seed: int) -> Signals:  # the project's exact linf attack: its box lies in the ball
        setting = dataclasses.replace(s, objective="destabilize", delta_u=delta)
        return {"u": destabilize_attack(build_attack(setting), seed=seed).stats["x"].reshape((m, t), order="F")}

    g = np.linalg.solve((data.x0 @ q).T, q.T).T
    loop = DPTLoop(attack, a + b @ (data.u0 @ g), b, g)
    target = Target(f"depersis-tesi-{s.design}-{s.selection}-T{t}", FAMILY, loop, {"u": attack.u},
                    {"u": float(np.sqrt(m * t))}, refit, radius, {}, PATH, options=options)
    target.attacks.update({"minimal": lambda delta, seed: {"u": minimal_poisoning(target, delta)},
                           "destabilize": box})
    return target


def _transfer(acl: np.ndarray, b: np.ndarray, g: np.ndarray, w: np.ndarray) -> np.ndarray:
    """H(e^{jw}) = G (zI - Acl)^-1 B for each frequency: (len(w), T, m)."""
    n = acl.shape[0]
    z = np.exp(1j * w)[:, None, None]
    return g @ np.linalg.solve(z * np.eye(n) - acl, np.broadcast_to(b, (w.size, *b.shape)))


def _real_cost(h: np.ndarray, v: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """||V P^+||_F and V P^+ for H (..., T, m), v (..., m) complex: the least real Du with Du H v = v."""
    hv = np.einsum("...tm,...m->...t", h, v)
    p = np.stack([hv.real, hv.imag], axis=-1)
    vv = np.stack([v.real, v.imag], axis=-1)
    du = vv @ np.linalg.pinv(p)
    return np.linalg.norm(du, axis=(-2, -1)), du


def _minimal(loop: DPTLoop) -> np.ndarray:
    """The least-Frobenius real Du found to put a closed-loop eigenvalue on the unit circle (module docstring)."""
    if "minimal" in loop.cache:
        return loop.cache["minimal"]
    acl, b, g = loop.acl, loop.b, loop.g
    m = b.shape[1]
    best = []
    for w0 in (0.0, np.pi):  # real z: a rank-one Du = v u' / sigma_1
        u_, sv, vt = np.linalg.svd(_transfer(acl, b, g, np.array([w0]))[0].real)
        best.append((1.0 / sv[0], np.outer(vt[0], u_[:, 0]) / sv[0]))
    w = np.linspace(0.0, np.pi, FREQUENCIES + 2)[1:-1]
    rng = np.random.default_rng(0)
    v = rng.standard_normal((DIRECTIONS, m)) + 1j * rng.standard_normal((DIRECTIONS, m))
    cost, _ = _real_cost(_transfer(acl, b, g, w)[:, None], v[None])
    i, j = np.unravel_index(np.argmin(cost), cost.shape)

    def objective(theta: np.ndarray) -> float:
        return float(_real_cost(_transfer(acl, b, g, theta[:1])[0], theta[1:1 + m] + 1j * theta[1 + m:])[0])
    x0 = np.concatenate([[w[i]], v[j].real, v[j].imag])
    found = scipy.optimize.minimize(objective, x0, method="Nelder-Mead", options={"xatol": 1e-10, "fatol": 1e-14,
                                                                                  "maxiter": 4000})
    theta = found.x if found.fun < cost[i, j] else x0
    norm, du = _real_cost(_transfer(acl, b, g, theta[:1])[0], theta[1:1 + m] + 1j * theta[1 + m:])
    best.append((float(norm), du))
    loop.cache["minimal"] = min(best, key=lambda item: item[0])[1]
    return loop.cache["minimal"]


def minimal_poisoning(target: Target, delta: float) -> np.ndarray:
    """The minimal destabilizing Du (module docstring) scaled by PUSH past the unit circle, or, where that exceeds the
    budget's radius, scaled to the radius (then it need not destabilize)."""
    du = _minimal(target.declaration)
    radius = target.radii(delta)["u"]
    norm = np.linalg.norm(du)
    return du * min(PUSH, radius / norm)


def _margin(*sizes: float) -> float:
    return param("robust.check_margin") * (1.0 + sum(sizes))


def triangle(target: Target, delta: float | None, options: dict[str, Any]) -> Evidence | None:
    """Mechanism "stability-triangle" (n = 2, m = 1; module docstring): exact."""
    loop = target.declaration
    acl, b, g = loop.acl, loop.b, loop.g
    if acl.shape != (2, 2) or b.shape[1] != 1:
        return None
    t0 = time.perf_counter()
    r = target.radii(delta)["u"]
    # f_i(k) = c_i + k d_i: p(1) = det(I - Acl - b k), p(-1) = det(-I - Acl - b k), 1 - a0 = 1 - det(Acl + b k)
    mats = (np.eye(2) - acl, -np.eye(2) - acl, acl)
    c = np.array([np.linalg.det(mats[0]), np.linalg.det(mats[1]), 1 - np.linalg.det(acl)])
    gd = g @ np.stack([-(adj_at(mt) @ b)[:, 0] for mt in mats]).T
    radii = np.where(c > 0, c, 0.0) / np.linalg.norm(gd, axis=0)
    i = int(np.argmin(radii))
    safe = float(radii[i])
    if r < safe:
        return Evidence("stability-triangle", Proof.PROVEN,
                        f"every ||Du||_F <= {r:.6g} (delta = {delta:.6g}) leaves the true loop stable: the gain "
                        f"ellipse lies in the stability triangle (exact radius {safe:.6g})",
                        {"radius": r, "exact_radius": safe}, _recheck_triangle(target, r), time.perf_counter() - t0)
    if r < safe * PUSH:
        return Evidence("stability-triangle", Proof.UNKNOWN, f"radius {r:.6g} is at the exact radius {safe:.6g}",
                        {"radius": r, "exact_radius": safe}, Check(False, "not attempted: on the boundary"),
                        time.perf_counter() - t0)
    du = -safe * PUSH * gd[:, i][None, :] / np.linalg.norm(gd[:, i])
    rho = target.true_radius({"u": du})
    return Evidence("stability-triangle", Proof.REFUTED,
                    f"a poisoning of norm {safe * PUSH:.6g} <= {r:.6g} puts a closed-loop eigenvalue on or past "
                    f"the unit circle (exact radius {safe:.6g})", {"radius": r, "exact_radius": safe},
                    Check(rho >= 1.0, "numpy: the true loop's spectral radius under the re-fitted gain",
                          {"spectral_radius": rho}), time.perf_counter() - t0)


def adj_at(m: np.ndarray) -> np.ndarray:
    """The adjugate of a 2 x 2 matrix."""
    return np.array([[m[1, 1], -m[0, 1]], [-m[1, 0], m[0, 0]]])


def _recheck_triangle(target: Target, r: float) -> Check:
    """numpy: the three Schur functions of the 2 x 2 loop A + B K(Du) at Du = 0 and along unit Du's (affine in Du, so
    exact), their smallest value over the ball of radius r, against a margin above rounding."""
    u0 = target.signals["u"]
    a, b = target.declaration.attack.setting.plant_matrices()

    def schur_values(du: np.ndarray) -> np.ndarray:
        acl = a + b @ target.refit({"u": u0 + du})
        return np.array([np.linalg.det(np.eye(2) - acl), np.linalg.det(-np.eye(2) - acl), 1 - np.linalg.det(acl)])
    f0 = schur_values(np.zeros_like(u0))
    grads = np.stack([schur_values(e.reshape(u0.shape)) - f0 for e in np.eye(u0.size)], axis=1)
    low = f0 - r * np.linalg.norm(grads, axis=1)
    margin = _margin(float(np.abs(f0).max()), r * float(np.abs(grads).max()))
    return Check(bool(np.min(low) > margin), "numpy: the Schur triangle's three affine functions over the ball",
                 {"smallest_value": float(np.min(low)), "margin": margin})


def _small_gain_lmi(loop: DPTLoop) -> tuple[np.ndarray, float]:
    """(P, mu*): Clarabel's maximum of mu in the bounded-real LMI (module docstring), strict by lmi_margin."""
    if "small-gain" in loop.cache:
        return loop.cache["small-gain"]
    acl, b, g = loop.acl, loop.b, loop.g
    n, m = b.shape
    p = cp.Variable((n, n), symmetric=True)
    mu = cp.Variable(nonneg=True)
    lmi = cp.bmat([[acl.T @ p @ acl - p + mu * (g.T @ g), acl.T @ p @ b], [b.T @ p @ acl, b.T @ p @ b - np.eye(m)]])
    tau = param("robust_willems.lmi_margin")
    problem = cp.Problem(cp.Maximize(mu), [(lmi + lmi.T) / 2 << -tau * np.eye(n + m), p >> tau * np.eye(n)])
    solve_clarabel(problem, "the small-gain LMI of a De Persis-Tesi loop")
    loop.cache["small-gain"] = ((p.value + p.value.T) / 2, float(mu.value))
    return loop.cache["small-gain"]


def recheck_small_gain(acl: np.ndarray, b: np.ndarray, g: np.ndarray, p: np.ndarray, r: float) -> Check:
    """numpy: the bounded-real matrix at mu = r^2 negative definite and P positive definite, both beyond a margin
    above rounding."""
    m = b.shape[1]
    lmi = np.block([[acl.T @ p @ acl - p + r ** 2 * g.T @ g, acl.T @ p @ b], [b.T @ p @ acl, b.T @ p @ b - np.eye(m)]])
    top = float(np.linalg.eigvalsh((lmi + lmi.T) / 2)[-1])
    low = float(np.linalg.eigvalsh(p)[0])
    pn = np.linalg.norm(p, 2)
    margin = _margin(pn * (1 + np.linalg.norm(acl, 2)) ** 2 * (1 + np.linalg.norm(b, 2)) ** 2,
                     r ** 2 * np.linalg.norm(g, 2) ** 2)
    return Check(top < -margin and low > margin, "numpy: eigenvalues of the bounded-real LMI at mu = r^2 and of P",
                 {"largest_lmi_eigenvalue": top, "smallest_p_eigenvalue": low, "margin": margin})


def small_gain(target: Target, delta: float | None, options: dict[str, Any]) -> Evidence | None:
    """Mechanism "small-gain" (module docstring)."""
    t0 = time.perf_counter()
    loop = target.declaration
    p, mu = _small_gain_lmi(loop)
    r = target.radii(delta)["u"]
    if r ** 2 >= mu:
        return Evidence("small-gain", Proof.UNKNOWN, f"radius {r:.6g} exceeds the small-gain radius {np.sqrt(mu):.6g}",
                        {"radius": r, "small_gain_radius": float(np.sqrt(mu))},
                        Check(False, "not attempted: beyond the LMI's radius"), time.perf_counter() - t0)
    check = recheck_small_gain(loop.acl, loop.b, loop.g, p, r)
    return Evidence("small-gain", Proof.PROVEN,
                    f"every ||Du||_F <= {r:.6g} (delta = {delta:.6g}) leaves the true loop stable (a common quadratic "
                    f"Lyapunov function, small-gain radius {np.sqrt(mu):.6g})",
                    {"radius": r, "small_gain_radius": float(np.sqrt(mu))}, check, time.perf_counter() - t0)


register_target(WillemsAttack, dpt_target)
register_mechanism(FAMILY, triangle, "stability-triangle", cost=0.0)
register_mechanism(FAMILY, small_gain, "small-gain", cost=1.0)
