"""The structured attack of each registered attack problem by name: attack(starts=, seed=, **params) -> BilevelResult,
params the problem's (seed: the data's and the attack's), other keywords the attack's options (`bilevel compare`'s
method "structured", `bilevel solve`'s default for these problems, `--option NAME=VALUE`)."""

from __future__ import annotations

from typing import Any, Callable, Literal

from ..errors import ModelError
from ..problems import registry
from ..problems.vrft_instance import PAPER_EPS_Y, attack_instance
from ..result import BilevelResult
from . import vrft_methods
from .vrft_methods import METHODS, attack_budget_path, save_attack, save_path

Attack = Callable[..., BilevelResult]


def _vrft(objective: str) -> Attack:
    """The structured attack on vrft-<objective>."""
    def run(starts: int = 1, seed: int = 0, attack: Literal["alternating", "joint", "white-noise"] | None = None,
            path: bool = False, save: str | None = None, **params: Any) -> BilevelResult:
        """The alternating attack (joint for 'destabilize'), or `attack`, on the instance of these parameters; path:
        first at the paper's eps_y below eps_y, each warm-starting the next (the reproduction's budget paths); save:
        write the attack's data and signals to this .npz file (save_attack)."""
        name = attack or ("joint" if objective == "destabilize" else "alternating")
        if save:
            save_path(save)  # before the attack
        if name not in METHODS:
            raise ModelError(f"attack={name!r} is not one of {', '.join(METHODS)}")
        atk = attack_instance(objective, **{**registry.spec(f"vrft-{objective}").defaults, **params, "seed": seed})
        if path and name != "alternating":
            raise ModelError(f"path=true runs the alternating attack's budget path; attack {name!r} has none")
        if path:
            eps = atk.budget_y.eps
            result = attack_budget_path(atk, [e for e in PAPER_EPS_Y if e < eps] + [eps], seed=seed,
                                        starts=starts)[-1]
        else:
            result = vrft_methods.attack(atk, name, seed=seed, **({} if name == "white-noise" else {"starts": starts}))
        if save:
            save_attack(result, atk, save)
        return result
    return run


def _willems(objective: str) -> Attack:
    """The destabilizing attack on willems-destabilize, else the criterion's hypergradient ascent (no stop at
    instability: the criterion's local maximum, as a generic method would seek)."""
    def run(starts: int = 8, seed: int = 0, **params: Any) -> BilevelResult:
        from ..problems.willems import WillemsSetting, build_attack
        from .willems import destabilize_attack, hypergradient_attack

        built = build_attack(WillemsSetting(objective=objective, **{**params, "seed": seed}))
        if objective == "destabilize":
            return destabilize_attack(built, starts=starts, seed=seed)
        return hypergradient_attack(built, starts=starts, seed=seed, stop_when_unstable=False)
    return run


STRUCTURED: dict[str, Attack] = {
    **{f"vrft-{o}": _vrft(o) for o in ("maxmin", "targeted", "destabilize")},
    **{f"willems-{o}": _willems(o) for o in ("maxmin", "eigen", "destabilize")},
}
"""Registered problem name -> its structured attack."""
