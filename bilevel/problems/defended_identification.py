"""Robust identification of [A B] as defended lower levels (issue 29): Huber and least-absolute-deviation (LAD)
regression on the poisoned state-space data, attacked by the generic engine.

The data, budgets and regression are those of bilevel.problems.identification ("ss" learner): upper variables dX, dU
in the balls ||dS||_F <= eps ||S||_F, residuals E = X+ - Theta [X; U] of the poisoned signals (affine in Theta).
Learners (T samples, n outputs):
  "lad"    min_{Theta, t} sum(t) / T          s.t. -t <= E <= t                     (an LP);
  "huber"  min_{Theta, s, v} (1/2 ||s||^2 + M sum(v)) / T  s.t. -v <= E - s <= v  (a QP: sum of Huber losses of E
           with threshold M = k * noise_std; its minimum over (s, v) is the Huber function of each residual).
The attacker maximizes ||Theta - Theta_clean||_F^2, Theta_clean the same learner's estimate on the clean data.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

import casadi as ca
import cvxpy as cp
import numpy as np

from ..errors import ModelError
from ..lower.quadratic import solve_clarabel
from ..real_data import real_number
from ..model import BilevelProblem
from .identification import SOURCE
from .identification_instance import IdentificationAttack, attack_instance, ss_regression
from .registry import register

Loss = Literal["ls", "huber", "lad"]
LOSSES = ("ls", "huber", "lad")
HUBER_K = 1.345
"""The Huber threshold in noise standard deviations (95% efficiency under Gaussian noise)."""
HUBER_K_MIN = 1e-3
"""The smallest threshold k (noise stds) taken: below it the Huber learner is LAD scaled by the threshold."""


def robust_fit(Y: np.ndarray, Z: np.ndarray, loss: Loss, threshold: float = 0.0) -> np.ndarray:
    """Theta = argmin sum loss(Y - Theta Z) by cvxpy + Clarabel ("ls": squares, "huber": Huber with `threshold`,
    "lad": absolute values); an independent solve of each learner, not the engine's."""
    if loss not in LOSSES:
        raise ModelError(f"loss {loss!r} is not one of {', '.join(LOSSES)}")
    theta = cp.Variable((Y.shape[0], Z.shape[0]))
    E = Y - theta @ Z
    cost = {"ls": lambda: cp.sum_squares(E), "lad": lambda: cp.sum(cp.abs(E)),
            "huber": lambda: cp.sum(cp.huber(E, threshold))}[loss]()
    solve_clarabel(cp.Problem(cp.Minimize(cost / Y.shape[1])), f"the {loss} identification")
    return np.asarray(theta.value)


@dataclass
class DefendedIdentification:
    """A defended identification instance: the undefended "ss" instance `atk` (data, budgets) and the loss."""

    atk: IdentificationAttack
    loss: Loss
    k: float = HUBER_K

    def __post_init__(self) -> None:
        if self.atk.learner != "ss" or self.atk.stealth is not None:
            raise ModelError("defended identification takes the state-space learner without stealth constraints")
        if self.loss not in LOSSES:
            raise ModelError(f"loss {self.loss!r} is not one of {', '.join(LOSSES)}")
        if real_number(self.k, "the Huber threshold k (noise stds)") < HUBER_K_MIN:
            raise ModelError(f"the Huber threshold k={self.k!r} noise stds is below {HUBER_K_MIN:g}: there the Huber "
                             "loss is the LAD loss scaled by the threshold, its quadratic part never acting, and the "
                             "learner's problem is solved to no accuracy; use loss 'lad'")
        self.threshold = self.k * self.atk.setting.noise_std
        if self.loss == "huber" and not self.threshold > 0:
            raise ModelError(f"the Huber threshold is k * noise_std = {self.threshold:g}: the setting's noise_std "
                             f"{self.atk.setting.noise_std!r} must be > 0 for the Huber learner (or use loss 'lad')")
        self.theta_clean = self.learn(self.atk.signals)

    def learn(self, signals: dict[str, np.ndarray]) -> np.ndarray:
        """The defended learner's [A B] on the given signals (robust_fit)."""
        return robust_fit(*self.atk.regression(signals), self.loss, self.threshold)

    def poisoned(self, dX: np.ndarray, dU: np.ndarray) -> np.ndarray:
        """[A B] learned from the poisoned data (an attack computed for another learner, transferred)."""
        return self.learn({"X": self.atk.signals["X"] + dX, "U": self.atk.signals["U"] + dU})

    def clean_performance(self) -> float:
        """Identification error ||[A B]_clean - [A B]_true||_F of the learner on the clean data."""
        A, B = self.atk.setting.state_space
        return float(np.linalg.norm(self.theta_clean - np.hstack([A, B])))


def declare(d: DefendedIdentification) -> BilevelProblem:
    """The bilevel program of a defended identification instance (budget balls, the robust learner as lower level)."""
    atk = d.atk
    p = BilevelProblem(f"defense-ident-{d.loss}")
    poisoned = {}
    for name, clean in atk.signals.items():
        delta = p.upper_variable(f"d{name}", clean.shape)
        p.upper_constraint(ca.sumsqr(delta) <= atk.radius(name) ** 2, name=f"budget_{name}")
        poisoned[name] = ca.DM(clean) + delta
    Y, Z = ss_regression(poisoned["X"], poisoned["U"])
    theta = p.lower_variable("theta", d.theta_clean.shape, start=d.theta_clean)
    E = Y - ca.mtimes(theta, Z)
    T = int(E.shape[1])
    if d.loss == "ls":
        p.minimize_lower(ca.sumsqr(E) / T)
    elif d.loss == "lad":
        t = p.lower_variable("t", E.shape)
        p.lower_constraint(ca.vec(E - t) <= 0, name="abs_high")
        p.lower_constraint(ca.vec(-E - t) <= 0, name="abs_low")
        p.minimize_lower(ca.sum1(ca.vec(t)) / T)
    else:
        s, v = p.lower_variable("s", E.shape), p.lower_variable("v", E.shape)
        p.lower_constraint(ca.vec(E - s - v) <= 0, name="huber_high")
        p.lower_constraint(ca.vec(s - E - v) <= 0, name="huber_low")
        p.minimize_lower((0.5 * ca.sumsqr(s) + d.threshold * ca.sum1(ca.vec(v))) / T)
    p.maximize_upper(ca.sumsqr(theta - ca.DM(d.theta_clean)))
    return p


def defended_instance(loss: Loss, T: int = 100, eps: float = 0.05, seed: int = 0,
                      k: float = HUBER_K) -> DefendedIdentification:
    """The flexible transmission's "ss" instance (bilevel.problems.identification_instance) with learner `loss`."""
    return DefendedIdentification(attack_instance("ss", T, eps, "frobenius", None, seed), loss, k)


@register("defense-ident-huber", source=SOURCE + "; issue 29: Huber regression as a defense",
          tags=("defense", "identification", "attack"), defaults={"T": 100, "eps": 0.05, "seed": 0, "k": HUBER_K},
          description="Huber identification of [A B] (threshold k noise stds), attacked adaptively")
def defense_ident_huber(T: int = 100, eps: float = 0.05, seed: int = 0, k: float = HUBER_K) -> BilevelProblem:
    """Huber regression of [A B] from poisoned states and inputs."""
    return declare(defended_instance("huber", T, eps, seed, k))


@register("defense-ident-lad", source=SOURCE + "; issue 29: least-absolute-deviation regression as a defense",
          tags=("defense", "identification", "attack"), defaults={"T": 100, "eps": 0.05, "seed": 0},
          description="least-absolute-deviation (LP) identification of [A B], attacked adaptively")
def defense_ident_lad(T: int = 100, eps: float = 0.05, seed: int = 0) -> BilevelProblem:
    """LAD regression of [A B] from poisoned states and inputs."""
    return declare(defended_instance("lad", T, eps, seed))
