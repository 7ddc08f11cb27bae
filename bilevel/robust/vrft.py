"""VRFT as a certificate target: the learner's least squares theta = argmin ||Phi(y + a_y) theta - t(u + a_u)||
with Phi and t linear in the poisoning, judged by the true plant's closed-loop polynomial (affine in theta).

Budget: delta is the relative l2 budget of both signals, ||a_u|| <= delta ||u||, ||a_y|| <= delta ||y|| (the
defenses frontier's eps_u = eps_y = eps). The attack is the project's joint attack on the destabilize objective
(the attacker's ARX model of the loop), the random baseline its white-noise poisoning.
"""

from __future__ import annotations

import dataclasses
from typing import Any

import numpy as np

from ..attacks.vrft_methods import attack
from ..problems.budget import Budget
from ..problems.vrft_instance import VRFTAttack
from .target import Signals, Target, register_target

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


register_target(VRFTAttack, vrft_target)
