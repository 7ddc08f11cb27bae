"""VRFT poisoning attacks as registered bilevel problems (paper Sec. 3-4, appendix A).

Upper variables a_u, a_y (N each) with budgets ||a|| <= eps ||signal||; lower variable theta (nk)
solving the VRFT least squares on the poisoned data. The regressor Phi(y + a_y) is written as
filter recursions (O(N) expression nodes per column, no N x N blocks), so IPOPT on the KKT
reformulation (with a limited-memory Hessian) scales. The fast structured algorithms for the same
instances are in bilevel.attacks.vrft_methods; `attack_instance` builds their VRFTAttack.
"""

from __future__ import annotations

import casadi as ca
import numpy as np

from ..attacks.vrft import VRFTAttack, attack_instance
from ..attacks.vrft_methods import conditioning_start
from ..ddc.operators import LTIOperator
from ..errors import ModelError
from ..model import BilevelProblem
from .registry import register
from .surrogates import gelfand_log_radius

SOURCE = "Russo & Proutiere, Poisoning Attacks against Data-Driven Control Methods (extended), "
DEFAULTS = {"scenario": "B", "eps_u": 0.1, "eps_y": 0.057, "seed": 0, "N": 64, "convention": "paper"}


def sx_filter(op: LTIOperator, x: ca.SX) -> ca.SX:
    """The operator's Toeplitz map applied to an SX signal by its difference equation (O(N order) nodes)."""
    n = int(x.numel())
    d = op.advance
    b = op._b / op.den[0]
    a = op.den / op.den[0]
    src = ca.vertcat(x, ca.SX.zeros(d)) if d else x
    out: list[ca.SX] = []
    for t in range(n + d):
        acc = sum(b[j] * src[t - j] for j in range(b.size) if t - j >= 0 and b[j] != 0)
        acc = acc - sum(a[j] * out[t - j] for j in range(1, a.size) if t - j >= 0 and a[j] != 0)
        out.append(ca.SX(acc))
    return ca.vertcat(*out[d:])


def attack_problem(atk: VRFTAttack) -> BilevelProblem:
    """The bilevel program of an attack instance (l2 budgets), declared with the generic API."""
    if atk.budget_u.norm != "l2" or atk.budget_y.norm != "l2" or atk.budget_u.rho or atk.budget_y.rho:
        raise ModelError("the declared VRFT problem supports plain l2 budgets; use the structured attacks in "
                         "bilevel.attacks.vrft_methods for linf/l1/sparse budgets")
    reg = atk.setting.regressor
    N, k = atk.N, reg.n_params
    p = BilevelProblem(f"vrft-{atk.objective}")
    a_u = p.upper_variable("a_u", N)
    a_y = p.upper_variable("a_y", N)
    theta = p.lower_variable("theta", k, start=atk.theta0)
    err = sx_filter(reg.error, a_y)
    if reg.prefilter is not None:
        err = sx_filter(reg.prefilter, err)
    rows = reg.rows(N)
    phi_a = ca.horzcat(*[sx_filter(beta, err)[:rows] for beta in reg.basis])
    t_a = a_u if reg.prefilter is None else sx_filter(reg.prefilter, a_u)
    residual = ca.DM(atk.t0) + t_a[:rows] - ca.mtimes(ca.DM(atk.phi0) + phi_a, theta)
    p.minimize_lower(ca.sumsqr(residual) / rows)
    p.upper_constraint(ca.sumsqr(a_u) <= atk.delta_u ** 2, name="budget_u")
    p.upper_constraint(ca.sumsqr(a_y) <= atk.delta_y ** 2, name="budget_y")
    p.suggest_start(a_y=conditioning_start(atk))  # a_y = 0 is stationary: start where the regressor is ill-conditioned
    if atk.objective == "maxmin":
        clean = ca.DM(atk.t0) - ca.mtimes(ca.DM(atk.phi0), theta)
        p.maximize_upper(ca.sumsqr(clean) / rows)
    elif atk.objective == "targeted":
        p.minimize_upper(ca.sumsqr(ca.DM(atk.theta_target) - theta) / k)
    else:
        p.maximize_upper(gelfand_radius(atk.model_loop.base, atk.model_loop.slopes, theta))
    return p


def gelfand_radius(base: np.ndarray, slopes: np.ndarray, theta: ca.SX, power: int = 16) -> ca.SX:
    """Smooth spectral-radius surrogate log(||C(theta)^p||_F) / p (Gelfand: -> log rho as p -> inf),
    C the companion matrix of the closed-loop polynomial base + theta' slopes; p a power of two."""
    coeffs = ca.DM(base) + ca.mtimes(ca.DM(slopes).T, theta)
    n = int(coeffs.numel()) - 1
    monic = coeffs[1:] / coeffs[0]
    C = ca.vertcat(-monic.T, ca.horzcat(ca.SX.eye(n - 1), ca.SX.zeros(n - 1, 1)))
    return gelfand_log_radius(C, power)


@register("vrft-maxmin", source=SOURCE + "Sec. 4.4, eq. (op_maxmin)", tags=("attack", "vrft"), defaults=DEFAULTS,
          description="max-min poisoning of VRFT on the flexible transmission (maximize the learner's loss)")
def vrft_maxmin(**params) -> BilevelProblem:
    """Max-min attack on VRFT: maximize the learner's clean-data loss at the poisoned theta."""
    return attack_problem(attack_instance("maxmin", **params))


@register("vrft-targeted", source=SOURCE + "appendix A, eq. (op_vrft_targeted), theta_a = 3 theta_0",
          tags=("attack", "vrft"), defaults=DEFAULTS,
          description="targeted poisoning of VRFT: drive theta towards theta_a = 3 theta_0")
def vrft_targeted(**params) -> BilevelProblem:
    """Targeted attack on VRFT: minimize ||theta_a - theta'||^2 / nk."""
    return attack_problem(attack_instance("targeted", **params))


@register("vrft-destabilize", source=SOURCE + "beyond the paper: the attacker fits an ARX model to the clean data "
          "and maximizes a smooth spectral radius of the modelled closed loop", tags=("attack", "vrft"),
          defaults=DEFAULTS, description="destabilizing poisoning of VRFT (maximize the modelled closed-loop "
          "spectral radius)")
def vrft_destabilize(**params) -> BilevelProblem:
    """Destabilizing attack: maximize log ||C(theta')^16||_F / 16 for the ARX-modelled closed loop."""
    return attack_problem(attack_instance("destabilize", **params))
