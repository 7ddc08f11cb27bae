"""Data-poisoning attacks on data-driven control learners (VRFT, De Persis–Tesi), built on the bilevel core.

The public VRFT attack API (docs/own_plant.md): describe the learner with `VRFTSetting`, the instance with
`VRFTAttack` (budgets as `Budget` or plain numbers; both defined with the declared problems in bilevel.problems),
and run `attack_alternating`, `attack_joint`, `attack_white_noise` or `attack_budget_path`; each returns the
engine's `bilevel.BilevelResult` of the registered problem vrft-<objective> (x: a_u, a_y; y: theta; its
certificate and local probe; the VRFT quantities in stats, read with `attack_summary`, `attack_value`, `unstable`,
saved with `save_attack`).
"""

from ..ddc.loop import LoopPolynomial, arx_orders_for, fit_arx
from ..problems.budget import Budget
from ..problems.vrft_instance import (PAPER_THETA0, VRFTAttack, VRFTSetting, attack_instance,
                                      flexible_transmission_setting)
from .outcome import unstable
from .vrft_methods import (ATTACKS, attack_alternating, attack_budget_path, attack_joint, attack_summary,
                           attack_value, attack_white_noise, save_attack)

__all__ = [
    "ATTACKS", "Budget", "LoopPolynomial", "PAPER_THETA0", "VRFTAttack", "VRFTSetting",
    "arx_orders_for", "attack_alternating", "attack_budget_path", "attack_instance", "attack_joint",
    "attack_summary", "attack_value", "attack_white_noise", "fit_arx", "flexible_transmission_setting",
    "save_attack", "unstable",
]
