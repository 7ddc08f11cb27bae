"""Poisoning attacks on the De Persis–Tesi learners (paper appendix B, Willems' lemma) as bilevel problems.

The instance (setting, clean data, identified model, the quantities the attacks read) is
bilevel.problems.willems_instance's WillemsAttack; the attacks on the declared problem are in bilevel.attacks.willems.

Upper level (attacker): perturbations Du (m x T) of the inputs and, if poisoned, Dx of the states,
in linf boxes |Du| <= delta_u, |Dx| <= delta_x; it maximizes the max-min criterion (closed-loop H2
cost trace((Qx + K'RK) W), W = Acl W Acl' + I), the eigenvalue criterion log det(Acl Acl') or the
destabilizing criterion log ||Acl^p||_F / p (Gelfand: -> log rho(Acl) as p -> inf, p = GELFAND_POWER), with
Acl = A_id + B_id K and [B_id A_id] = X1 [U0; X0]^+ identified from the *clean* data (the attacker
does not know (A, B)). Lower level (learner): the De Persis–Tesi SDP on the poisoned data, with
lower variable Q (T x n), S = X0' Q (symmetric by equality constraints) and

    lqr          min tr(Qx S)            s.t. [[S - I, X1' Q], [Q' X1'^T, S]] >= 0      (paper appendix)
    lqr-r        min tr(Qx S) + tr(Xr)   s.t. the same LMI and [[Xr, R^1/2 U0' Q], [., S]] >= 0  (DPT Thm 4)
    stabilizing  min tr(S)               s.t. [[S - I, X1' Q], [Q' X1'^T, S - I]] >= 0  (DPT Thm 3)

each plus reg/2 ||Q||_F^2, and K = U0' Q S^{-1}. Why reg: the SDP sees Q only through D Q with
D = [X0; X1] ([X0; X1; U0] for lqr-r); on poisoned data the optimal set in Q is an affine family
whose gains U0' Q S^{-1} fill all of R^{m x n} (lqr, stabilizing), so "the learned K" is not a
function of the data. The Tikhonov term selects the minimum-norm optimal Q as reg -> 0; the
attacker's criteria depend on Q only through K.

Selection (`WillemsSetting.selection`). At an exact KKT point of the regularized SDP, reg Q lies in
the row space of D, but the null-space directions of Q carry curvature reg only, so a solver's KKT
residual r leaves an error ~ r / reg there (up to 7.7e-4 relative in Q at N = 50). "min-norm"
(default) projects the learner's Q onto the row space of D after solving, which leaves D Q, the
SDP's value and the constraints unchanged and makes the selection reproducible to solver accuracy;
"tikhonov" keeps the solver's Q (the selection of the sweep committed in session 1). "clarabel" and "scs"
are the unregularized learner bilevel.ddc.lqr_controller / stabilizing_controller with that SDP solver, whose Q
is the solver's own optimum (same SDP value, another gain); they are defined where the SDP does not see the
poisoning (poison="u", designs lqr and stabilizing), so Q is fixed and K is affine in Du.
"""

from __future__ import annotations

import threading
from dataclasses import fields
from typing import Any

import casadi as ca
import numpy as np
import scipy.linalg

from ..ddc.depersis_tesi import check_persistency, state_data
from ..defaults import param
from ..errors import ModelError, NotPersistentlyExciting
from ..kept import kept
from ..model import BilevelProblem
from ..vech import symmetric_sx
from .registry import register
from .surrogates import gelfand_log_radius
from .willems_instance import (DEFAULT_HORIZON, GELFAND_POWER, SOLVER_SELECTIONS, WillemsAttack, WillemsSetting,
                               declaration_of)

SOURCE = ("Russo & Proutiere, Poisoning attacks against data-driven control methods (extended), appendix "
          "'Attacks on methods based on Willems lemma'; De Persis & Tesi, IEEE TAC 2020, Thms 3-4")


def identified_model(x: np.ndarray, u: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(A, B) from [B A] = X1 [U0; X0]^+ (De Persis–Tesi Thm 1; exact on noise-free, persistently exciting data)."""
    data = state_data(x, u)
    check_persistency(data)
    m = data.u0.shape[0]
    ba = data.x1 @ np.linalg.pinv(np.vstack([data.u0, data.x0]))
    return ba[:, m:], ba[:, :m]


def _weight(value: Any, size: int, what: str) -> np.ndarray:
    w = np.eye(size) if value is None else np.asarray(value, dtype=float)
    if w.shape != (size, size) or not np.allclose(w, w.T) or np.linalg.eigvalsh(w).min() <= 0:
        raise ModelError(f"willems: {what} must be a symmetric positive definite {size} x {size} matrix")
    return w


def _gramian_expr(acl: ca.SX) -> ca.SX:
    """W with W = Acl W Acl' + I, by the Kronecker linear system (valid where Acl is Schur stable)."""
    n = int(acl.size1())
    vec_w = ca.solve(ca.SX.eye(n * n) - ca.kron(acl, acl), ca.vec(ca.SX.eye(n)))
    return ca.reshape(vec_w, n, n)


def build_attack(setting: WillemsSetting | None = None, **params: Any) -> WillemsAttack:
    """The clean data of `setting` (or of keyword parameters), given or drawn from its plant, checked for the
    learner's rank condition, and the attack problem declared on them."""
    if setting is not None and params:
        raise ModelError("build_attack: pass either a WillemsSetting or keyword parameters, not both")
    try:
        s = setting if setting is not None else WillemsSetting(**params)
    except TypeError:
        known = ", ".join(f.name for f in fields(WillemsSetting))
        raise ModelError(f"build_attack: the parameters {', '.join(sorted(params))} include an unknown one; a "
                         f"WillemsSetting takes {known}") from None
    x, u = s.experiment()
    try:
        check_persistency(state_data(x, u))
    except NotPersistentlyExciting as err:
        n_m = x.shape[0] + u.shape[0]
        raise NotPersistentlyExciting(
            f"willems: the learner needs [U0; X0] of full row rank, so T >= n + m = {n_m} samples at least: {err}. "
            "Fix: a longer horizon (drawn data: horizon=; given data: a longer experiment) or a richer input, one "
            "that excites every state (from x0 = 0 an uncontrollable (A, B) never gives full rank)") from None
    a_id, b_id = identified_model(x, u)
    qx, r = _weight(s.qx, x.shape[0], "qx"), _weight(s.r, u.shape[0], "r")
    p, du, dx, gain, acl, upper, seen = declare(s, x, u, a_id, b_id, qx, r)
    return WillemsAttack(s, x, u, a_id, b_id, qx, r, p, du, dx, gain, acl, upper, seen)


_BUILT = threading.local()
"""Per thread, .attacks: declaration -> the attack kept_attack built for it (the last willems.shared_kept)."""


def kept_attack(setting: WillemsSetting) -> WillemsAttack:
    """build_attack(setting), reusing this thread's attack of the same declaration (data, learner, criterion) where it
    was built before, at the setting's budgets (WillemsAttack.at_budget: nothing rebuilt, the declared box shared):
    for sweeps that attack one data set at several budgets, one attack at a time."""
    built, made = kept(_BUILT.__dict__.setdefault("attacks", {}), declaration_of(setting),
                       lambda: build_attack(setting), param("willems.shared_kept"))
    return built if made else built.at_budget(setting.delta_u, setting.delta_x)


def declare(s: WillemsSetting, x: np.ndarray, u: np.ndarray, a_id: np.ndarray, b_id: np.ndarray, qx: np.ndarray,
            r: np.ndarray, parameters: bool = False) -> tuple[BilevelProblem, ca.SX, ca.SX | None, ca.SX, ca.SX,
                                                            ca.SX, ca.SX]:
    """The attack problem of setting s on data (X, U) with identified model (A_id, B_id), and its Du, Dx, gain,
    identified loop, flat upper vector and seen rows; with parameters, the data and the model are the problem's
    parameters X, U, A_id and B_id (valued here, re-set by set_value: one declaration serves every data set of its
    shape), else constants."""
    n, m, t = x.shape[0], u.shape[0], s.horizon
    p = BilevelProblem(f"willems-{s.objective}")

    def data(name: str, value: np.ndarray) -> ca.SX:
        return p.parameter(name, value.shape, value=value) if parameters else ca.SX(ca.DM(value))
    du = p.upper_variable("Du", (m, t), lb=-s.delta_u, ub=s.delta_u, start=0.0)
    xs = data("X", x)
    dx = None
    if "x" in s.poison:
        offset = 0 if s.poison_x0 else 1
        dx = p.upper_variable("Dx", (n, t + 1 - offset), lb=-s.delta_x, ub=s.delta_x, start=0.0)
        xs = ca.horzcat(xs[:, :offset], xs[:, offset:] + dx) if offset else xs + dx
    us = data("U", u) + du
    x0p, x1p = xs[:, :t], xs[:, 1:]
    q = p.lower_variable("Q", (t, n))
    s_raw = ca.mtimes(x0p, q)
    p.lower_constraint(ca.vertcat(*[s_raw[i, j] - s_raw[j, i] for j in range(n) for i in range(j)]) == 0,
                       name="S_symmetric")
    s_mat = 0.5 * (s_raw + s_raw.T)
    m_mat = ca.mtimes(x1p, q)
    eye = ca.SX.eye(n)
    lower = ca.trace(ca.mtimes(ca.DM(qx), s_mat)) if s.design != "stabilizing" else ca.trace(s_mat)
    corner = s_mat - eye if s.design == "stabilizing" else s_mat
    p.lower_psd_constraint(ca.blockcat([[s_mat - eye, m_mat], [m_mat.T, corner]]), name="gramian")
    v_mat = ca.mtimes(us, q)
    if s.design == "lqr-r":
        xr = symmetric_sx(p.lower_variable("Xr", m * (m + 1) // 2), m)
        weighted = ca.mtimes(ca.DM(np.real(scipy.linalg.sqrtm(r))), v_mat)
        p.lower_psd_constraint(ca.blockcat([[xr, weighted], [weighted.T, s_mat]]), name="input_cost")
        lower += ca.trace(xr)
    p.minimize_lower(lower + 0.5 * s.reg * ca.sumsqr(q))
    gain = ca.mtimes(v_mat, ca.inv(s_mat))
    acl = data("A_id", a_id) + ca.mtimes(data("B_id", b_id), gain)
    if s.objective == "eigen":
        p.maximize_upper(2 * ca.log(ca.fabs(ca.det(acl))))
    elif s.objective == "destabilize":
        p.maximize_upper(gelfand_log_radius(acl, GELFAND_POWER))
    else:
        cost = ca.DM(qx) + (ca.mtimes([gain.T, ca.DM(r), gain]) if s.design == "lqr-r" else 0)
        p.maximize_upper(ca.trace(ca.mtimes(cost, _gramian_expr(acl))))
    upper = ca.vertcat(ca.vec(du), ca.vec(dx)) if dx is not None else ca.vec(du)
    seen = ca.vertcat(x0p, x1p, us) if s.design == "lqr-r" else ca.vertcat(x0p, x1p)
    return p, du, dx, gain, acl, upper, seen


def _register(objective: str, description: str) -> None:
    @register(f"willems-{objective}", source=SOURCE, tags=("willems", "attack", "sdp"), description=description,
              defaults={**{f.name: f.default for f in fields(WillemsSetting) if f.name != "objective"},
                        "horizon": DEFAULT_HORIZON})
    def build(**params: Any) -> BilevelProblem:
        if params.get("selection") in SOLVER_SELECTIONS:
            raise ModelError(f"willems-{objective}: the declared problem's learner is the regularized SDP; "
                             f"selection={params['selection']!r} (the solver's own Q) exists in the structured "
                             "attacks only (bilevel.attacks.willems; `bilevel solve willems-destabilize` without "
                             "--method)")
        return build_attack(WillemsSetting(objective=objective, **params)).problem


_register("maxmin", "max-min attack on De Persis-Tesi: maximize the closed-loop H2 cost through the Gramian")
_register("eigen", "eigenvalue attack on De Persis-Tesi: maximize log det((A+BK)(A+BK)')")
_register("destabilize", "destabilizing attack on De Persis-Tesi: maximize log ||(A+BK)^16||_F / 16 (-> log rho)")
