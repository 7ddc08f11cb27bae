"""Poisoning attacks on DeePC as registered bilevel problems (deepc-tracking, deepc-first-action).

Upper variables: one change per recorded signal (du, dy), each within ||dS||_q <= eps ||S||_q (l_inf: bounds on the
variable; l2: an upper constraint). Lower level: the user's DeePC learner, a cvxpy Problem
(bilevel.problems.deepc_instance.DeePCAttack.learner) whose Hankel Parameters are bound to the Hankel matrices of the
poisoned signals with lower_cvxpy. The attacker maximizes the true plant's tracking cost of the plan, or the squared
deviation of its first action from the clean plan's.
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Any, NamedTuple

import casadi as ca

from ..model import BilevelProblem
from .deepc_instance import DeePCAttack, Norm, Objective, attack_instance, hankel
from .registry import register

if TYPE_CHECKING:  # pragma: no cover
    from ..frontends.cvxpy_lower import CvxpyLower

SOURCE = ("beyond the paper: DeePC (Coulson, Lygeros & Doerfler, Data-Enabled Predictive Control: In the Shallows of "
          "the DeePC, 2019) on the flexible transmission")
DEFAULTS = {"T": 200, "eps": 0.05, "norm": "l2", "seed": 0, "noise_std": 0.01, "past_std": 0.0, "t_ini": 4,
            "horizon": 10, "lambda_g": 0.1, "lambda_y": 1000.0, "u_max": None}


class Declared(NamedTuple):
    """A declared attack: the problem, its lower level (ll[v] is cvxpy Variable v as a CasADi expression) and the
    learner's cvxpy Parameters and Variables by name (DeePCAttack.learner)."""

    problem: BilevelProblem
    lower: CvxpyLower
    learner: dict[str, Any]


def declare(atk: DeePCAttack) -> BilevelProblem:
    """The bilevel program of an attack instance, declared with the public API (lower_cvxpy)."""
    return declaration(atk).problem


def declaration(atk: DeePCAttack) -> Declared:
    """The bilevel program of an attack instance with its lower level and the learner's cvxpy leaves."""
    p = BilevelProblem(f"deepc-{atk.objective}")
    learner, v = atk.learner()
    depth = atk.t_ini + atk.horizon
    bound = {}
    for name, param in (("u", v["Hu"]), ("y", v["Hy"])):
        radius = atk.radius(name)
        if atk.budget.norm == "linf":
            d = p.upper_variable(f"d{name}", getattr(atk, name).size, lb=-radius, ub=radius)
        else:
            d = p.upper_variable(f"d{name}", getattr(atk, name).size)
            p.upper_constraint(ca.sumsqr(d) <= radius ** 2, name=f"budget_{name}")
        bound[param] = hankel(ca.DM(getattr(atk, name)) + d, depth)
    ll = p.lower_cvxpy(learner, parameters=bound)
    p.maximize_upper(atk.value(ll[v["u"]]))
    return Declared(p, ll, v)


def _build(objective: Objective, T: int, eps: float, norm: Norm, seed: int, noise_std: float, past_std: float,
           t_ini: int, horizon: int, lambda_g: float, lambda_y: float, u_max: float | None) -> BilevelProblem:
    return declare(attack_instance(T=T, eps=eps, norm=norm, objective=objective, seed=seed, noise_std=noise_std,
                                   past_std=past_std, t_ini=t_ini, horizon=horizon, lambda_g=lambda_g,
                                   lambda_y=lambda_y, u_max=u_max))


@register("deepc-tracking", source=SOURCE, tags=("attack", "deepc"), defaults=DEFAULTS,
          description="poisoning of DeePC's data (maximize the true plant's tracking cost of the plan)")
def deepc_tracking(T: int = 200, eps: float = 0.05, norm: Norm = "l2", seed: int = 0, noise_std: float = 0.01,
                   past_std: float = 0.0, t_ini: int = 4, horizon: int = 10, lambda_g: float = 0.1,
                   lambda_y: float = 1000.0, u_max: float | None = None) -> BilevelProblem:
    """DeePC from T poisoned samples of the flexible transmission; the attacker maximizes the true tracking cost."""
    return _build("tracking", T, eps, norm, seed, noise_std, past_std, t_ini, horizon, lambda_g, lambda_y, u_max)


@register("deepc-first-action", source=SOURCE, tags=("attack", "deepc"), defaults=DEFAULTS,
          description="poisoning of DeePC's data (maximize the first planned input's deviation from the clean one)")
def deepc_first_action(T: int = 200, eps: float = 0.05, norm: Norm = "l2", seed: int = 0, noise_std: float = 0.01,
                       past_std: float = 0.0, t_ini: int = 4, horizon: int = 10, lambda_g: float = 0.1,
                       lambda_y: float = 1000.0, u_max: float | None = None) -> BilevelProblem:
    """DeePC from T poisoned samples of the flexible transmission; the attacker maximizes (u_0 - u_0^clean)^2."""
    return _build("first-action", T, eps, norm, seed, noise_std, past_std, t_ini, horizon, lambda_g, lambda_y,
                  u_max)
