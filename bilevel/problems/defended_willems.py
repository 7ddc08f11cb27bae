"""The regularized De Persis–Tesi learner as a defense (issue 29): the LQR SDP of bilevel.problems.willems with a
Tikhonov weight reg on ||Q||_F^2 / 2 far above the selection's DEFAULT_REG. Under input poisoning the gain is
K = (U0 + Du) Q S^-1, so a smaller Q makes the gain less sensitive to Du, at the price of a suboptimal clean gain.
The declaration is the attack problem's own (WillemsSetting.reg); the engine attacks it like any Willems problem.
"""

from __future__ import annotations

from dataclasses import fields
from typing import Any

import numpy as np

from ..model import BilevelProblem
from .registry import register
from .willems import DEFAULT_HORIZON, SOURCE, WillemsAttack, WillemsSetting, build_attack, criterion_values


def clean_gain(attack: WillemsAttack) -> np.ndarray:
    """The learner's gain on the clean data (the engine's SDP lower level solved at zero poisoning)."""
    from ..attacks.willems import engine, loop  # attacks sit above problems: imported where used

    zero = np.zeros(int(attack.upper.numel()))
    return loop(attack, zero, engine(attack).evaluate(zero).lower.y)[0]


def h2_cost(attack: WillemsAttack, gain: np.ndarray) -> float:
    """The true closed loop's H2 cost trace((Qx + K' R K) W), W = Acl W Acl' + I, with the learner's Qx and R (R = 0
    for the designs without an input cost: the cost the SDP minimizes); inf where A + B K is unstable."""
    return float(criterion_values(attack.true_closed_loop(gain), gain, "maxmin", attack.qx, attack.cost_weight))


def clean_performance(attack: WillemsAttack) -> float:
    """h2_cost of the gain learned from the clean data."""
    return h2_cost(attack, clean_gain(attack))


@register("defense-willems-ridge", source=SOURCE + "; issue 29: Tikhonov regularization of Q as a defense",
          tags=("defense", "willems", "attack", "sdp"),
          defaults={**{f.name: f.default for f in fields(WillemsSetting) if f.name not in ("objective", "reg")},
                    "objective": "destabilize", "horizon": DEFAULT_HORIZON, "reg": 1e-2},
          description="De Persis-Tesi LQR with reg/2 ||Q||_F^2 (a defense), attacked adaptively")
def defense_willems_ridge(**params: Any) -> BilevelProblem:
    """The Willems attack problem on the regularized learner (WillemsSetting with reg)."""
    return build_attack(WillemsSetting(**params)).problem
