"""Defended VRFT learners as lower levels of the poisoning problem (issue 29), attacked by the generic engine.

Defenses (the learner's problem on the poisoned data u' = u + a_u, y' = y + a_y):
  "none"   theta = argmin (1/n) ||t(u') - Phi(y') theta||^2 (the paper's learner, for the same data);
  "ridge"  theta = argmin (1/n) ||t(u') - Phi(y') theta||^2 + lam * s ||theta||^2, s = tr(Phi0' Phi0) / (n nk) the
           mean regressor power of the clean data (lam is relative: lam = 0.01 adds 1% of it to each eigenvalue);
  "iv"     instrumental variables (Campi, Lecchini & Savaresi 2002, Automatica 38): a second experiment with the same
           input gives y2 and the instrument Z = Phi(y2'); theta solves Z' (Phi(y') theta - t(u')) = 0, a square
           linear system, declared as the least squares min ||Z' (t - Phi theta)||^2 / n^2 (its unique minimizer
           where Z' Phi is invertible). The attacker poisons both experiments: a_u (the one input record), a_y and
           a_y2, each output in its own l2 ball eps_y ||y_k||;
  "iv-trusted"  the same learner with a second experiment the attacker cannot reach (a_y2 = 0).
Data: the paper's flexible-transmission instance (bilevel.problems.vrft_instance) with independent white measurement
noise of std noise * std(y) on each recorded output (IV needs noise to differ from least squares on clean data).
The attacker's criterion is the undefended instance's: the clean-data VRFT loss (maxmin), the targeted distance, or
(destabilize) the exact spectral radius of the closed loop of the attacker's ARX model (VRFTAttack.model_loop), declared
with maximize_spectral_radius, so defended and undefended learners are attacked for the same goal.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

import casadi as ca
import numpy as np

from ..ddc.bases import controller_tf
from ..ddc.analysis import closed_loop
from ..ddc.operators import LTIOperator
from ..ddc.vrft import instrumental_variables
from ..errors import InvalidData, ModelError
from ..model import BilevelProblem
from ..solvers.engine.options import check_flags
from .budget import Budget
from .registry import register
from .vrft import filtered
from .vrft_instance import Objective, VRFTAttack, VRFTSetting, attack_instance

Defense = Literal["none", "ridge", "iv", "iv-trusted"]
DEFENSES = ("none", "ridge", "iv", "iv-trusted")
INSTRUMENTAL = ("iv", "iv-trusted")
MODEL_REFERENCE_HORIZON = 4000
"""Samples of the impulse response summed in the model-reference cost (the reference model's poles are e^-0.5)."""


@dataclass
class DefendedVRFT:
    """A defended VRFT instance: the undefended instance `atk` (data of experiment 1, budgets, criterion), the defense
    and its parameter lam (ridge), and the second experiment's output y2 (iv, iv-trusted; None otherwise)."""

    atk: VRFTAttack
    defense: Defense
    lam: float = 0.0
    y2: np.ndarray | None = None

    def __post_init__(self) -> None:
        if self.defense not in DEFENSES:
            raise ModelError(f"VRFT defense {self.defense!r} is not one of {', '.join(DEFENSES)}")
        if not (np.isfinite(self.lam) and self.lam >= 0):
            raise ModelError(f"ridge weight lam must be finite and >= 0, got {self.lam}")
        if self.defense in INSTRUMENTAL and (self.y2 is None or np.shape(self.y2) != self.atk.y.shape):
            raise InvalidData("the IV learner needs the second experiment's output y2, of the first's length")
        reg = self.atk.setting.regressor
        self.scale = float(np.trace(self.atk.gram0)) / (self.atk.n * reg.n_params)
        self.delta_y2 = self.atk.budget_y.radius(self.y2) if self.defense == "iv" else 0.0
        self.theta_clean = self.learn(self.atk.u, self.atk.y, self.y2)

    def learn(self, u: np.ndarray, y: np.ndarray, y2: np.ndarray | None = None) -> np.ndarray:
        """The defended learner's theta on data (u, y) (and y2 for iv), in closed form (no engine code)."""
        reg = self.atk.setting.regressor
        phi, t = reg(y), reg.targets(u)
        if self.defense in INSTRUMENTAL:
            return instrumental_variables(phi, reg(y2), t)[0]
        ridge = self.lam * self.scale * self.atk.n if self.defense == "ridge" else 0.0
        return np.linalg.solve(phi.T @ phi + ridge * np.eye(phi.shape[1]), phi.T @ t)

    def poisoned(self, a_u: np.ndarray, a_y: np.ndarray, a_y2: np.ndarray | None = None) -> np.ndarray:
        """The defended learner's theta under poisoning (a_u, a_y, a_y2), e.g. an attack computed for another
        learner and transferred (a_y2 is ignored for iv-trusted)."""
        a_y2 = None if self.defense == "iv-trusted" else a_y2
        y2 = None if self.y2 is None else self.y2 + (0.0 if a_y2 is None else a_y2)
        return self.learn(self.atk.u + a_u, self.atk.y + a_y, y2)

    def clean_performance(self) -> float:
        """The model-reference cost of the controller learned on clean data (model_reference_cost)."""
        return model_reference_cost(self.atk.setting, self.theta_clean)


def model_reference_cost(setting: VRFTSetting, theta: np.ndarray, horizon: int = MODEL_REFERENCE_HORIZON) -> float:
    """J_MR(theta) = ||G K(theta) / (1 + G K(theta)) - M_r||_2^2 (Campi et al. 2002), the squared l2 norm of the
    impulse-response difference over `horizon` samples; inf where the true closed loop is unstable."""
    if setting.loop.spectral_radius(theta) >= 1.0:
        return float("inf")
    controller = controller_tf(setting.basis, np.asarray(theta, dtype=float), getattr(setting.plant, "dt", True))
    loop = LTIOperator(closed_loop(setting.plant, controller)).impulse(horizon)
    return float(np.sum((loop - LTIOperator(setting.reference).impulse(horizon)) ** 2))


def _regressor(p: BilevelProblem, setting: VRFTSetting, a_y: ca.SX, suffix: str) -> ca.SX:
    """Phi(a_y) (rows x nk) as filter definitions named with `suffix` (the recursions of bilevel.problems.vrft)."""
    reg = setting.regressor
    err = filtered(p, f"e_y{suffix}", reg.error, a_y)
    if reg.prefilter is not None:
        err = filtered(p, f"le_y{suffix}", reg.prefilter, err)
    return ca.horzcat(*[filtered(p, f"phi_{j}{suffix}", beta, err) for j, beta in enumerate(reg.basis)])


def declare(d: DefendedVRFT) -> BilevelProblem:
    """The bilevel program of a defended instance: l2 budget balls on a_u, a_y (and a_y2), the defended learner as the
    lower level, the undefended instance's criterion as the upper objective."""
    atk = d.atk
    for budget in (atk.budget_u, atk.budget_y):
        if budget.norm != "l2" or budget.rho:
            raise ModelError(f"defended VRFT problems take l2 budgets without sparsity, got {budget}")
    reg, N = atk.setting.regressor, atk.N
    rows, k = reg.rows(N), reg.n_params
    p = BilevelProblem(f"defense-vrft-{d.defense}")
    a_u, a_y = p.upper_variable("a_u", N), p.upper_variable("a_y", N)
    theta = p.lower_variable("theta", k, start=d.theta_clean)
    phi = ca.DM(atk.phi0) + _regressor(p, atk.setting, a_y, "")[:rows, :]
    t_a = (a_u if reg.prefilter is None else filtered(p, "lu", reg.prefilter, a_u))[:rows]
    residual = ca.DM(atk.t0) + t_a - ca.mtimes(phi, theta)
    budgets = [("u", a_u), ("y", a_y)]
    if d.defense in INSTRUMENTAL:
        instrument = ca.DM(reg(d.y2))
        if d.defense == "iv":
            a_y2 = p.upper_variable("a_y2", N)
            budgets.append(("y2", a_y2))
            instrument = instrument + _regressor(p, atk.setting, a_y2, "_2")[:rows, :]
        p.minimize_lower(ca.sumsqr(ca.mtimes(instrument.T, residual)) / rows ** 2)
    else:
        ridge = d.lam * d.scale if d.defense == "ridge" else 0.0
        p.minimize_lower(ca.sumsqr(residual) / rows + ridge * ca.sumsqr(theta))
    radii = budget_values(d)  # parameters: budget_values of another budget re-sets them (no new declaration)
    for name, a in budgets:
        p.upper_constraint(ca.sumsqr(a) <= p.parameter(f"delta_{name}", value=radii[f"delta_{name}"]) ** 2,
                           name=f"budget_{name}")
    if atk.objective == "maxmin":
        p.maximize_upper((float(atk.t0 @ atk.t0) - 2 * ca.dot(ca.DM(atk.cross0), theta)
                          + ca.bilin(ca.DM(atk.gram0), theta, theta)) / rows)
    elif atk.objective == "targeted":
        p.minimize_upper(ca.sumsqr(ca.DM(atk.theta_target) - theta) / k)
    else:
        p.maximize_spectral_radius(companion(atk.model_loop.base, atk.model_loop.slopes, theta))
    return p


def budget_values(d: DefendedVRFT) -> dict[str, float]:
    """The budget radii of instance d by parameter name of its declared problem: set_value them on the problem declared
    for another budget of the same data, defense and lam to attack d without declaring again."""
    return {"delta_u": d.atk.delta_u, "delta_y": d.atk.delta_y} | ({"delta_y2": d.delta_y2} if d.defense == "iv" else {})


def companion(base: np.ndarray, slopes: np.ndarray, theta: ca.SX) -> ca.SX:
    """The companion matrix of the closed-loop polynomial base + theta' slopes: its eigenvalues are the poles."""
    coeffs = ca.DM(base) + ca.mtimes(ca.DM(slopes).T, theta)
    n = int(coeffs.numel()) - 1
    return ca.vertcat(-(coeffs[1:] / coeffs[0]).T, ca.horzcat(ca.SX.eye(n - 1), ca.SX.zeros(n - 1, 1)))


def defended_instance(defense: Defense, objective: Objective = "destabilize", lam: float = 0.0, scenario: str = "B",
                      eps_u: float = 0.1, eps_y: float = 0.057, seed: int = 0, N: int = 512,
                      noise: float = 0.02) -> DefendedVRFT:
    """The paper's instance (attack_instance) with measurement noise of relative std `noise` on each experiment's
    output (drawn with default_rng([seed, 1])), defended by `defense`."""
    if not (np.isfinite(noise) and noise >= 0):
        raise ModelError(f"noise must be a relative std >= 0, got {noise}")
    base = attack_instance(objective, scenario, eps_u, eps_y, seed, N)
    rng = np.random.default_rng([seed, 1])
    std = noise * float(np.std(base.y))
    y1, y2 = (base.y + std * rng.standard_normal(base.N) for _ in range(2))
    atk = VRFTAttack(base.setting, base.u, y1, base.budget_u, Budget(eps_y), objective, base.theta_target)
    return DefendedVRFT(atk, defense, lam, y2 if defense in INSTRUMENTAL else None)


SOURCE = ("issue 29 (defended learners); Campi, Lecchini & Savaresi, Virtual reference feedback tuning, Automatica 38 "
          "(2002) for IV; data: Russo & Proutiere (extended), Sec. 4")
DEFAULTS = {"objective": "destabilize", "scenario": "B", "eps_u": 0.1, "eps_y": 0.057, "seed": 0, "N": 512,
            "noise": 0.02}


@register("defense-vrft-ridge", source=SOURCE, tags=("defense", "vrft", "attack"),
          defaults={**DEFAULTS, "lam": 0.001},
          description="VRFT with a Tikhonov term lam * (mean regressor power) * ||theta||^2, attacked adaptively")
def defense_vrft_ridge(objective: Objective = "destabilize", lam: float = 0.001, scenario: str = "B",
                       eps_u: float = 0.1, eps_y: float = 0.057, seed: int = 0, N: int = 512,
                       noise: float = 0.02) -> BilevelProblem:
    """Ridge VRFT under poisoning of (u, y)."""
    return declare(defended_instance("ridge", objective, lam, scenario, eps_u, eps_y, seed, N, noise))


@register("defense-vrft-iv", source=SOURCE, tags=("defense", "vrft", "attack"),
          defaults={**DEFAULTS, "trusted_instrument": False},
          description="instrumental-variable VRFT (second experiment as instrument; poisoned too unless trusted)")
def defense_vrft_iv(objective: Objective = "destabilize", scenario: str = "B", eps_u: float = 0.1, eps_y: float = 0.057,
                    seed: int = 0, N: int = 512, noise: float = 0.02,
                    trusted_instrument: bool = False) -> BilevelProblem:
    """IV VRFT under poisoning of (u, y, y2), or of (u, y) with trusted_instrument."""
    check_flags({"trusted_instrument": trusted_instrument}, ("trusted_instrument",))
    defense = "iv-trusted" if trusted_instrument else "iv"
    return declare(defended_instance(defense, objective, 0.0, scenario, eps_u, eps_y, seed, N, noise))
