"""The structured attack of each registered attack problem, by problem name: attack(starts=, seed=, **params) ->
BilevelResult with the problem's parameters (`bilevel compare`'s method "structured", the CLI's default for them)."""

from __future__ import annotations

from typing import Any, Callable

from ..problems.vrft_instance import attack_instance
from ..result import BilevelResult
from .vrft_methods import attack_alternating, attack_joint

Attack = Callable[..., BilevelResult]


def _vrft(objective: str) -> Attack:
    """The alternating attack (its exact input step) on vrft-<objective>, joint ascent for 'destabilize'."""
    def run(starts: int = 1, seed: int = 0, **params: Any) -> BilevelResult:
        method = attack_joint if objective == "destabilize" else attack_alternating
        return method(attack_instance(objective, **params), starts=starts, seed=seed)
    return run


def _willems(objective: str) -> Attack:
    """The destabilizing attack on willems-destabilize, else the criterion's hypergradient ascent (no stop at
    instability: the criterion's local maximum, as a generic method would seek)."""
    def run(starts: int = 8, seed: int = 0, **params: Any) -> BilevelResult:
        from ..problems.willems import WillemsSetting, build_attack
        from .willems import destabilize_attack, hypergradient_attack

        built = build_attack(WillemsSetting(objective=objective, **params))
        if objective == "destabilize":
            return destabilize_attack(built, starts=starts, seed=seed)
        return hypergradient_attack(built, starts=starts, seed=seed, stop_when_unstable=False)
    return run


STRUCTURED: dict[str, Attack] = {
    **{f"vrft-{o}": _vrft(o) for o in ("maxmin", "targeted", "destabilize")},
    **{f"willems-{o}": _willems(o) for o in ("maxmin", "eigen", "destabilize")},
}
"""Registered problem name -> its structured attack."""
