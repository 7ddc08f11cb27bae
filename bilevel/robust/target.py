"""What a certificate needs from a declaration, and the registries of target builders and mechanisms.

A `Target` holds the clean signals the attacker may change, the budget (signal S may move by at most delta *
scale[S] in the l2 / Frobenius norm: a product of balls, one budget delta for all), a numpy re-fit of the learner
and the true closed loop's spectral radius under its answer (both independent of the certifying code), the project's
attacks at a budget, and the declaration itself for the mechanisms. `as_target` builds one from a registered attack
instance (a builder per declaration type: `register_target`) or from a user's BilevelProblem (the generic target,
global bounds on its upper objective only). A mechanism is `fn(target, delta, options) -> Evidence | None` (None:
it does not apply), registered per learner family with its cost rank (`register_mechanism`).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any, Callable

import numpy as np

from ..errors import ModelError, UnknownName
from ..model import BilevelProblem
from .verdict import Evidence

Signals = dict[str, np.ndarray]
Attack = Callable[[float, int], Signals]
"""An attack at budget delta with a seed -> its poisoning (one array per attacked signal)."""


@dataclass(frozen=True)
class Target:
    """A learner under attack, as the certificates see it (module docstring). `radius(answer)` is inf where the
    learner returns no controller (an abstention is not a destabilization: `abstains(answer)` tells them apart);
    `attacks` maps a method name to an Attack, the first the one whose budget search gives delta_ub; `path` is that
    search's increasing budget path."""

    name: str
    family: str
    declaration: Any
    signals: Signals = field(default_factory=dict)
    scale: dict[str, float] = field(default_factory=dict)
    refit: Callable[[Signals], Any] | None = None
    radius: Callable[[Any], float] | None = None
    attacks: dict[str, Attack] = field(default_factory=dict)
    path: tuple[float, ...] = ()
    abstains: Callable[[Any], bool] = lambda answer: answer is None
    options: dict[str, Any] = field(default_factory=dict)

    def radii(self, delta: float) -> dict[str, float]:
        """The l2 (Frobenius) radius of each attacked signal's ball at budget delta."""
        return {name: float(delta) * s for name, s in self.scale.items()}

    def poisoned(self, poisoning: Signals) -> Signals:
        """The clean signals plus a poisoning (a signal it leaves out stays clean)."""
        return {name: s + poisoning[name] if name in poisoning else s for name, s in self.signals.items()}

    def true_radius(self, poisoning: Signals) -> float:
        """The true loop's spectral radius under the learner re-fitted by numpy on the poisoned signals."""
        if self.refit is None or self.radius is None:
            raise ModelError(f"target {self.name!r} ({self.family}) has no numpy re-fit of its learner")
        return float(self.radius(self.refit(self.poisoned(poisoning))))


TargetBuilder = Callable[..., Target]
BUILDERS: dict[type, TargetBuilder] = {}
"""Declaration type -> the function that makes a Target of it (keyword options passed on)."""


def register_target(kind: type, build: TargetBuilder) -> None:
    """Make as_target accept declarations of type `kind` (build(declaration, **options) -> Target)."""
    BUILDERS[kind] = build


def as_target(declaration: Any, **options: Any) -> Target:
    """The Target of a registered attack instance (a VRFTAttack, an IdentificationAttack, ...: BUILDERS), of a user's
    BilevelProblem whose upper level maximizes over its budget set (family "generic": global bounds only), or a
    Target itself."""
    if isinstance(declaration, Target):
        return declaration
    for kind, build in BUILDERS.items():
        if isinstance(declaration, kind):
            return build(declaration, **options)
    if isinstance(declaration, BilevelProblem):
        if options:
            raise ModelError(f"a BilevelProblem target takes no options, got {', '.join(sorted(options))}")
        return Target(declaration.name or "problem", "generic", declaration)
    known = ", ".join(sorted(k.__name__ for k in BUILDERS))
    raise ModelError(f"cannot certify a {type(declaration).__name__}: pass a registered attack instance ({known}), a "
                     "BilevelProblem whose upper level maximizes over a budget set, or a bilevel.robust.Target")


Mechanism = Callable[[Target, float | None, dict[str, Any]], Evidence | None]


@dataclass(frozen=True)
class Registered:
    """A mechanism as registered: its name, family, function and cost rank (cheapest first)."""

    name: str
    family: str
    fn: Mechanism
    cost: float


MECHANISMS: dict[str, list[Registered]] = {}


def register_mechanism(family: str, fn: Mechanism, name: str, cost: float = 0.0) -> None:
    """Add mechanism `fn` for learner family `family` under `name` (unique per family); the chain tries a family's
    mechanisms in increasing cost."""
    own = MECHANISMS.setdefault(family, [])
    if any(m.name == name for m in own):
        raise ModelError(f"mechanism {name!r} is already registered for family {family!r}")
    own.append(Registered(name, family, fn, float(cost)))
    own.sort(key=lambda m: m.cost)


def mechanisms_of(family: str, names: list[str] | tuple[str, ...] | None = None) -> list[Registered]:
    """The family's mechanisms, cheapest first, or those named (in the order given)."""
    own = MECHANISMS.get(family, [])
    if names is None:
        return list(own)
    by_name = {m.name: m for m in own}
    unknown = [n for n in names if n not in by_name]
    if unknown:
        raise UnknownName(f"no mechanism {', '.join(map(repr, unknown))} for family {family!r}; it has "
                          f"{', '.join(by_name) or 'none'}")
    return [by_name[n] for n in names]
