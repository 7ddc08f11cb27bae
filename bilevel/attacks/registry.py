"""The structured attack of each registered attack problem by name: attack(starts=, seed=, **params) -> BilevelResult,
params the problem's (seed: the data's and the attack's) and the attack's options (options_of(attack_options(name)):
`bilevel compare`'s method "structured", `bilevel solve`'s default for these problems, `--option NAME=VALUE`)."""

from __future__ import annotations

from typing import Any, Callable, Literal

from ..errors import ModelError
from ..problems import registry
from ..problems.vrft_instance import PAPER_EPS_Y, VRFTAttack, attack_instance
from ..result import BilevelResult
from ..solvers.engine.prepared import options_of
from . import vrft_methods
from .vrft_methods import attack_budget_path

Attack = Callable[..., BilevelResult]


def attack_options(name: str) -> tuple[Callable[..., Any], str, dict[str, Any]]:
    """The function whose keyword-only parameters are the options of problem `name`'s structured attack (besides the
    run's own: attack, path, save for VRFT), the prefix of the registry keys their None reads, and the run's own
    defaults for some of them."""
    if name.startswith("vrft-"):
        return vrft_methods.alternating, "vrft.", {}
    from .willems import destabilize_attack, hypergradient_attack

    if name == "willems-destabilize":
        return destabilize_attack, "destabilize.", {}
    return hypergradient_attack, "willems.hypergradient.", {"stop_when_unstable": False}


def _split(name: str, params: dict[str, Any]) -> dict[str, Any]:
    """Pop the attack's options out of `params` (the rest: the problem's parameters), over the run's defaults."""
    function, _, defaults = attack_options(name)
    return {**defaults, **{k: params.pop(k) for k in options_of(function) & set(params)}}


def _vrft(objective: str) -> Attack:
    """The structured attack on vrft-<objective>."""
    def run(starts: int | None = None, seed: int = 0,
            attack: Literal["alternating", "joint", "white-noise"] | None = None, path: bool = False,
            save: str | None = None, **params: Any) -> BilevelResult:
        """The alternating attack (joint for 'destabilize'), or `attack`, on the instance of these parameters; path:
        first at the paper's eps_y below eps_y, each warm-starting the next (the reproduction's budget paths); save:
        write the attack's data and signals to this .npz file (VRFTAttack.save)."""
        name = attack or ("joint" if objective == "destabilize" else "alternating")
        options = _split(f"vrft-{objective}", params)
        if save:
            VRFTAttack.save_path(save)  # before the attack
        atk = attack_instance(objective, **{**registry.spec(f"vrft-{objective}").defaults, **params, "seed": seed})
        if path and name != "alternating":
            raise ModelError(f"path=true runs the alternating attack's budget path; attack {name!r} has none")
        if path:
            eps = atk.budget_y.eps
            result = attack_budget_path(atk, [e for e in PAPER_EPS_Y if e < eps] + [eps], seed=seed, starts=starts,
                                        **options)[-1]
        else:
            result = vrft_methods.attack(atk, name, seed=seed, starts=starts, **options)
        if save:
            atk.save(result, save)
        return result
    return run


def _willems(objective: str) -> Attack:
    """The structured attack on willems-<objective>: destabilize_attack, else hypergradient_attack, by default without
    its stop at instability (the criterion's local maximum, as a generic method would seek)."""
    def run(starts: int | None = None, seed: int = 0, **params: Any) -> BilevelResult:
        from ..problems.willems import build_attack
        from ..problems.willems_instance import WillemsSetting

        options = _split(f"willems-{objective}", params)
        built = build_attack(WillemsSetting(objective=objective, **{**params, "seed": seed}))
        return attack_options(f"willems-{objective}")[0](built, starts=starts, seed=seed, **options)
    return run


STRUCTURED: dict[str, Attack] = {
    **{f"vrft-{o}": _vrft(o) for o in ("maxmin", "targeted", "destabilize")},
    **{f"willems-{o}": _willems(o) for o in ("maxmin", "eigen", "destabilize")},
}
"""Registered problem name -> its structured attack."""
