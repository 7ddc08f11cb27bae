"""The sampling check of a certificate's soundness: random poisonings on the budget sphere (every attacked signal
at the full radius of its ball, uniformly distributed in direction) and every attack method's answer at the same
budget, each judged by the target's numpy re-fit of the learner and numpy eigenvalues of the true loop, code the
certificates do not use. A sound certificate at delta leaves every one of them stable."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from ..defaults import param
from ..threads import single_threaded_call
from .target import Signals, Target


@dataclass(frozen=True)
class Soundness:
    """What the sampling found at budget delta: samples drawn, how many destabilized the true loop (spectral radius
    >= 1) and how many made the learner abstain, the largest radius among them, and each attack method's radius."""

    delta: float
    samples: int
    unstable: int
    abstained: int
    worst_radius: float
    attack_radius: dict[str, float] = field(default_factory=dict)

    @property
    def sound(self) -> bool:
        """No sample and no attack destabilized the true loop."""
        return self.unstable == 0 and all(r < 1.0 for r in self.attack_radius.values())


def sphere_poisoning(target: Target, delta: float, rng: np.random.Generator) -> Signals:
    """One poisoning with every attacked signal on the sphere of its ball at budget delta (Gaussian direction)."""
    out = {}
    for name, radius in target.radii(delta).items():
        v = rng.standard_normal(target.signals[name].shape)
        out[name] = radius * v / np.linalg.norm(v)
    return out


@single_threaded_call
def sample_soundness(target: Target, delta: float, samples: int | None = None, seed: int = 0,
                     attacks: bool = True) -> Soundness:
    """Soundness at delta (module docstring): `samples` sphere poisonings (defaults["robust.soundness_samples"]) and,
    with attacks, every attack method of the target run at delta."""
    rng = np.random.default_rng(seed)
    count = int(param("robust.soundness_samples", samples))
    unstable = abstained = 0
    worst = 0.0
    for _ in range(count):
        answer = target.refit(target.poisoned(sphere_poisoning(target, delta, rng)))
        if target.abstains(answer):
            abstained += 1
            continue
        rho = float(target.radius(answer))
        worst = max(worst, rho)
        unstable += rho >= 1.0
    found = {name: target.true_radius(attack(delta, seed)) for name, attack in target.attacks.items()} if attacks \
        else {}
    return Soundness(float(delta), count, int(unstable), abstained, worst, found)
