"""Data-poisoning attacks on data-driven control learners (VRFT, De Persis–Tesi) on the bilevel engine.

VRFT (docs/own_plant.md): a `VRFTSetting` and a `VRFTAttack` (bilevel.problems), then `attack_alternating`,
`attack_joint`, `attack_white_noise` or `attack_budget_path`: the BilevelResult of vrft-<objective> (x: a_u, a_y;
y: theta) with the VRFT quantities in stats (`attack_value`, `unstable`; `VRFTAttack.save` writes them).
"""

from ..ddc.loop import LoopPolynomial, arx_orders_for, fit_arx
from ..problems.budget import Budget
from ..problems.vrft_instance import (PAPER_THETA0, VRFTAttack, VRFTSetting, attack_instance,
                                      flexible_transmission_setting)
from .outcome import unstable
from .vrft_methods import (METHODS, attack, attack_alternating, attack_budget_path, attack_joint, attack_value,
                           attack_white_noise)

__all__ = [
    "METHODS", "Budget", "LoopPolynomial", "PAPER_THETA0", "VRFTAttack", "VRFTSetting",
    "arx_orders_for", "attack", "attack_alternating", "attack_budget_path", "attack_instance", "attack_joint",
    "attack_value", "attack_white_noise", "fit_arx", "flexible_transmission_setting", "unstable",
]
