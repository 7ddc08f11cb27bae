"""The regularized De Persis–Tesi learner as a defense (issue 29): the LQR SDP of bilevel.problems.willems with a
Tikhonov weight reg on ||Q||_F^2 / 2 far above the selection's DEFAULT_REG. Under input poisoning the gain is
K = (U0 + Du) Q S^-1, so a smaller Q makes the gain less sensitive to Du, at the price of a suboptimal clean gain.
The declaration is the attack problem's own (WillemsSetting.reg); the engine attacks it like any Willems problem.
"""

from __future__ import annotations

from dataclasses import fields
from typing import Any


from ..model import BilevelProblem
from .registry import register
from .willems import SOURCE, build_attack
from .willems_instance import DEFAULT_HORIZON, WillemsSetting


@register("defense-willems-ridge", source=SOURCE + "; issue 29: Tikhonov regularization of Q as a defense",
          tags=("defense", "willems", "attack", "sdp"),
          defaults={**{f.name: f.default for f in fields(WillemsSetting) if f.name not in ("objective", "reg")},
                    "objective": "destabilize", "horizon": DEFAULT_HORIZON, "reg": 1e-2},
          description="De Persis-Tesi LQR with reg/2 ||Q||_F^2 (a defense), attacked adaptively")
def defense_willems_ridge(**params: Any) -> BilevelProblem:
    """The Willems attack problem on the regularized learner (WillemsSetting with reg)."""
    return build_attack(WillemsSetting(**params)).problem
