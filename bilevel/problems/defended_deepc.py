"""Regularized DeePC as a defense (issue 29): the deepc-tracking attack (bilevel.problems.deepc) on a learner with a
large ridge weight lambda_g on g. A larger lambda_g keeps the plan from leaning on a few (poisoned) Hankel columns, at
the price of a plan that tracks worse on clean data. The declaration is the attack problem's own; the engine attacks
it like any DeePC problem. Performance: the true plant's tracking cost of the plan (DeePCAttack.tracking_cost).
"""

from __future__ import annotations

from typing import Any

import numpy as np

from ..model import BilevelProblem
from .deepc import DEFAULTS, SOURCE, deepc_tracking
from .deepc_instance import DeePCAttack
from .registry import register

DEFENSE_LAMBDA_G = 10.0
"""The registered defense's lambda_g: 100 times the attack family's default 0.1."""


def clean_performance(atk: DeePCAttack) -> float:
    """The true plant's tracking cost of the plan made from the clean data."""
    return attacked_performance(atk, np.zeros(atk.u.size), np.zeros(atk.y.size))


def attacked_performance(atk: DeePCAttack, du: np.ndarray, dy: np.ndarray) -> float:
    """The true plant's tracking cost of the plan the learner makes from the poisoned data (u + du, y + dy), re-solved
    by cvxpy (an attack computed for another learner is judged the same way)."""
    plan = atk.plan(atk.u + np.ravel(du), atk.y + np.ravel(dy))
    return float(atk.tracking_cost(plan))


@register("defense-deepc", source=SOURCE + "; issue 29: a large lambda_g as a defense",
          tags=("defense", "deepc", "attack"), defaults={**DEFAULTS, "lambda_g": DEFENSE_LAMBDA_G},
          description="DeePC with a large ridge weight lambda_g (a defense), attacked adaptively (tracking cost)")
def defense_deepc(**params: Any) -> BilevelProblem:
    """The deepc-tracking attack on the regularized learner (its parameters; lambda_g defaults to 10)."""
    return deepc_tracking(**{"lambda_g": DEFENSE_LAMBDA_G, **params})
