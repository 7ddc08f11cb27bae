"""The regularized De Persis–Tesi learner as a defense (issue 29): the LQR SDP of bilevel.problems.willems with a
Tikhonov weight reg on ||Q||_F^2 / 2 far above the selection's DEFAULT_REG. Under input poisoning the gain is
K = (U0 + Du) Q S^-1, so a smaller Q makes the gain less sensitive to Du, at the price of a suboptimal clean gain.
The declaration is the attack problem's own (WillemsSetting.reg); the engine attacks it like any Willems problem.
"""

from __future__ import annotations

from dataclasses import fields
from typing import Any

import casadi as ca
import numpy as np

from ..ddc.depersis_tesi import column_weights, state_data
from ..ddc.robust_depersis_tesi import poisoning_energy
from ..defaults import param
from ..errors import ModelError
from ..model import BilevelProblem
from .registry import register
from .willems import SOURCE, build_attack, identified_model
from .willems_instance import DEFAULT_HORIZON, WillemsSetting


@register("defense-willems-ridge", source=SOURCE + "; issue 29: Tikhonov regularization of Q as a defense",
          tags=("defense", "willems", "attack", "sdp"),
          defaults={**{f.name: f.default for f in fields(WillemsSetting) if f.name not in ("objective", "reg")},
                    "objective": "destabilize", "horizon": DEFAULT_HORIZON, "reg": 1e-2},
          description="De Persis-Tesi LQR with reg/2 ||Q||_F^2 (a defense), attacked adaptively")
def defense_willems_ridge(**params: Any) -> BilevelProblem:
    """The Willems attack problem on the regularized learner (WillemsSetting with reg)."""
    return build_attack(WillemsSetting(**params)).problem


ROBUST_OBJECTIVES = ("radius", "abstain")
"""The attacker's criteria on the robust learner: rho(A_id + B_id K), or the learner's value tr(Qx P) (its H2 cost
bound, unbounded as the poisoning drives the learner to abstain)."""


def declare_robust(setting: WillemsSetting, design_delta: float, objective: str = "radius") -> BilevelProblem:
    """The input-poisoning attack (|Du| <= setting.delta_u) on the robust De Persis–Tesi learner
    (bilevel.ddc.robust_depersis_tesi) with design budget design_delta: lower variables P (symmetric), Y = K P and
    alpha >= 0, its SDP min tr(Qx P) s.t. its LMI >= tau I on the poisoned data; the attacker maximizes `objective`
    (ROBUST_OBJECTIVES; [B_id A_id] identified from the clean data, the true plant for noise-free data). Where the
    learner abstains (its SDP infeasible at some poisoning) the engine reports the lower level infeasible."""
    if objective not in ROBUST_OBJECTIVES:
        raise ModelError(f"defense-willems-robust: objective={objective!r} is not one of "
                         f"{', '.join(ROBUST_OBJECTIVES)}")
    if setting.poison != "u" or setting.design != "lqr":
        raise ModelError("defense-willems-robust: the robust learner is declared for input poisoning of the lqr "
                         f"design; got poison={setting.poison!r}, design={setting.design!r}")
    if not design_delta > 0:
        raise ModelError(f"defense-willems-robust: design_delta must be > 0 (0 is the nominal learner), got "
                         f"{design_delta}")
    x, u = setting.experiment()
    data = state_data(x, u)
    a_id, b_id = identified_model(x, u)
    (n, t), m = data.x0.shape, data.u0.shape[0]
    qx = np.eye(n) if setting.qx is None else np.array(setting.qx)
    w = column_weights(data, True)  # input poisoning leaves the weights (states only) unchanged
    eps = poisoning_energy(data, w, design_delta)
    p = BilevelProblem("defense-willems-robust")
    du = p.upper_variable("Du", (m, t), lb=-setting.delta_u, ub=setting.delta_u, start=0.0)
    pm = p.lower_variable("P", (n, n), symmetric=True)
    y = p.lower_variable("Y", (m, n))
    alpha = p.lower_variable("alpha", lb=0.0)
    x1w = ca.DM(data.x1 * w)
    dw = ca.vertcat(ca.DM(data.x0 * w), ca.mtimes(ca.DM(data.u0) + du, ca.DM(np.diag(w))))
    n11 = -ca.mtimes(x1w, x1w.T)
    n12 = ca.mtimes(x1w, dw.T)
    n22 = ca.diag(ca.vertcat(ca.DM.zeros(n), eps ** 2 * ca.DM.ones(m))) - ca.mtimes(dw, dw.T)
    py = ca.vertcat(pm, y)
    lmi = ca.blockcat([[pm - ca.DM.eye(n) - alpha * n11, -alpha * n12, ca.DM.zeros(n, n)],
                       [-alpha * n12.T, -alpha * n22, py], [ca.DM.zeros(n, n), py.T, pm]])
    p.lower_psd_constraint(lmi - param("robust_willems.lmi_margin") * ca.DM.eye(3 * n + m), name="robust_lyapunov")
    p.minimize_lower(ca.trace(ca.mtimes(ca.DM(qx), pm)))
    if objective == "abstain":
        p.maximize_upper(ca.trace(ca.mtimes(ca.DM(qx), pm)))
    else:
        p.maximize_spectral_radius(ca.DM(a_id) + ca.mtimes(ca.DM(b_id), ca.mtimes(y, ca.inv(pm))))
    return p


@register("defense-willems-robust", source=SOURCE + "; issue 46: the matrix S-lemma design (van Waarde, Camlibel & "
          "Mesbahi 2022; Bisoffi, De Persis & Tesi 2022) robust to linf input poisoning up to design_delta",
          tags=("defense", "willems", "attack", "sdp"),
          defaults={"horizon": DEFAULT_HORIZON, "seed": 0, "delta_u": 0.05, "design_delta": 0.1,
                    "objective": "radius"},
          description="robust De Persis-Tesi LQR (matrix S-lemma, design budget design_delta), attacked adaptively")
def defense_willems_robust(horizon: int = DEFAULT_HORIZON, seed: int = 0, delta_u: float = 0.05,
                           design_delta: float = 0.1, objective: str = "radius") -> BilevelProblem:
    """The attack on the robust learner (declare_robust) for the batch reactor's drawn data."""
    return declare_robust(WillemsSetting(objective="destabilize", horizon=horizon, seed=seed, delta_u=delta_u),
                          design_delta, objective)
