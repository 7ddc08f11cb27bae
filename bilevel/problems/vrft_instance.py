"""A VRFT poisoning instance: the learner's design (VRFTSetting), the clean data, budgets and the attacker's objective.

Lower level (learner): theta(u', y') = argmin ||t(u') - Phi(y') theta||^2 with Phi linear in y'
(bilevel.ddc.vrft). Upper level (attacker): maximize J(theta(u + a_u, y + a_y)) over budgets on
a_u, a_y. J is one of
  "maxmin"      (1/n) ||t(u) - Phi(y) theta||^2, the learner's loss on clean data (paper, eq. op_maxmin);
  "targeted"    -(1/nk) ||theta_a - theta||^2 (paper appendix A; maximizing minus the distance);
  "destabilize" a smooth max of the closed-loop pole moduli of an ARX model the attacker fits
                from the clean data (it does not know the plant).
bilevel.problems.vrft declares the instance as a BilevelProblem; `VRFTAttack.learner` is its learner as the engine's
affine least squares (bilevel.lower.affine_least_squares), which bilevel.attacks.vrft_methods attacks.
"""

from __future__ import annotations

import os
from dataclasses import dataclass
from functools import cache, cached_property
from typing import Any, Literal

import numpy as np

from ..ddc.bases import Basis, flexible_transmission_basis
from ..ddc.data import paper_input, simulate
from ..ddc.loop import LoopPolynomial, arx_orders_for, fit_arx
from ..ddc.operators import LTIOperator
from ..ddc.plants import flexible_transmission, flexible_transmission_prefilter, flexible_transmission_reference
from ..ddc.systems import SystemLike, num_den
from ..ddc.vrft import VRFTRegressor, least_squares, vrft_regressor
from ..errors import InvalidData, ModelError, RankDeficientRegressor
from ..files import atomic_path
from ..kept import kept
from ..lower.affine_least_squares import AffineLeastSquares, AffineMaps
from ..result import BilevelResult
from ..solvers.engine.affine_ls import UpperObjective
from ..solvers.engine.projections import Blocks, Projection
from ..solvers.engine.options import check_common_options
from .budget import Budget

Objective = Literal["maxmin", "targeted", "destabilize"]
DataConvention = Literal["prefiltered", "raw"]


@dataclass(frozen=True)
class VRFTSetting:
    """The learner's design: plant (for evaluation only), M_r, basis, L, data convention, boundary.

    data="prefiltered": the recorded (u, y) are already filtered by L and the learner regresses on them
    (the paper's assumption); data="raw": the learner filters by L itself. boundary: see ddc.vrft.
    """

    plant: SystemLike
    reference: SystemLike
    basis: Basis
    prefilter: SystemLike
    data: DataConvention = "prefiltered"
    boundary: Literal["zero-final", "drop"] = "zero-final"

    def __post_init__(self) -> None:
        if self.data not in ("prefiltered", "raw"):
            raise ModelError(f"data convention {self.data!r} is not 'prefiltered' or 'raw'")

    @cached_property
    def regressor(self) -> VRFTRegressor:
        return vrft_regressor(self.reference, self.basis, None if self.data == "prefiltered" else self.prefilter,
                              self.boundary)

    @cached_property
    def loop(self) -> LoopPolynomial:
        """Closed loop of the true plant (used to judge stability, never by the attacker)."""
        return LoopPolynomial.of(self.plant, self.basis)

    @cached_property
    def _filters(self) -> tuple[tuple[np.ndarray, np.ndarray], LTIOperator]:
        """The plant's (num, den) and L's filter, read once: a setting records many data sets."""
        return num_den(self.plant), LTIOperator(self.prefilter)

    def recorded(self, u_raw: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """The data set the learner receives for plant input u_raw (filtered by L if prefiltered)."""
        plant, pre = self._filters
        y_raw = simulate(plant, u_raw)
        if self.data == "raw":
            return np.asarray(u_raw, dtype=float), y_raw
        return pre.apply(u_raw), pre.apply(y_raw)


def flexible_transmission_setting(data: DataConvention = "prefiltered",
                                  boundary: Literal["zero-final", "drop"] = "zero-final") -> VRFTSetting:
    """The paper's VRFT example: Landau's flexible transmission, M_r with a = e^-0.5, L = (1-M_r)M_r."""
    return VRFTSetting(flexible_transmission(), flexible_transmission_reference(),
                       flexible_transmission_basis(), flexible_transmission_prefilter(), data, boundary)


CONVENTIONS = {
    "paper": ("prefiltered", "zero-final"),
    "prefiltered-drop": ("prefiltered", "drop"),
    "raw": ("raw", "zero-final"),
    "raw-drop": ("raw", "drop"),
}
"""Data convention and virtual-reference boundary handling; "paper" is the paper's (Sec. 4.1, Lemma 1)."""

PAPER_THETA0 = np.array([0.33, -0.61, 0.72, -0.66, 0.48, -0.13])
"""theta_0 of Campi et al. (2002) as quoted by the paper; its targeted attack aims at 3 * theta_0."""
PAPER_EPS_Y = (0.01, 0.023, 0.037, 0.05, 0.057)
"""The paper's output budgets (Table 1's columns)."""


KEPT_DATA = 16
"""attack_instance keeps this many recorded data sets per process, VRFTAttack as many clean fits (a sweep's attacks
on one data set, one per budget, share them)."""
_DATA: dict[tuple[Any, ...], tuple[np.ndarray, np.ndarray]] = {}
_CLEAN: dict[tuple[Any, ...], tuple[VRFTSetting, tuple[np.ndarray, ...]]] = {}


def _read_only(*arrays: np.ndarray) -> tuple[np.ndarray, ...]:
    """The arrays, made read-only: a kept value is shared by the instances that read it."""
    for a in arrays:
        a.flags.writeable = False
    return arrays


def scenario_data(setting: VRFTSetting, scenario: Literal["A", "B"], n: int = 512,
                  rng: np.random.Generator | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Recorded (u, y) of the paper's scenario A (step on [5, 15]) or B (white noise, needs rng)."""
    return setting.recorded(paper_input(scenario, n, rng))


@dataclass
class VRFTAttack:
    """One attack instance: clean data, the learner, budgets and the attacker's objective.

    A budget given as a number eps means Budget(eps): ||a||_2 <= eps * ||signal||_2.
    """

    setting: VRFTSetting
    u: np.ndarray
    y: np.ndarray
    budget_u: Budget | float
    budget_y: Budget | float
    objective: Objective = "maxmin"
    theta_target: np.ndarray | None = None
    arx_orders: tuple[int, int, int] = (4, 2, 3)
    surrogate_beta: float = 50.0

    def __post_init__(self) -> None:
        try:
            self.u = np.asarray(self.u, dtype=float)
            self.y = np.asarray(self.y, dtype=float)
        except (TypeError, ValueError):
            raise InvalidData("attack data u and y must be arrays of real numbers") from None
        if self.u.shape != self.y.shape or self.u.ndim != 1:
            raise InvalidData(f"u and y must be 1-D of equal length, got {self.u.shape} and {self.y.shape}")
        if not (np.all(np.isfinite(self.u)) and np.all(np.isfinite(self.y))):
            raise InvalidData("attack data contain NaN or inf")
        self.budget_u, self.budget_y = Budget.of(self.budget_u), Budget.of(self.budget_y)
        if self.objective not in ("maxmin", "targeted", "destabilize"):
            raise ModelError(f"objective {self.objective!r} is not maxmin, targeted or destabilize")
        reg = self.setting.regressor
        if reg.rows(self.u.size) <= reg.n_params:
            raise InvalidData(f"{self.u.size} samples give {max(reg.rows(self.u.size), 0)} regression rows for "
                              f"{reg.n_params} controller parameters; the learner needs more rows than parameters: "
                              "record a longer experiment")
        self.phi0, self.t0, self.theta0, self.gram0, self.cross0 = kept(
            _CLEAN, (id(self.setting), self.u.tobytes(), self.y.tobytes()), lambda: (self.setting, self._clean_fit()),
            KEPT_DATA, usable=lambda hit: hit[0] is self.setting)[0][1]  # the setting kept alive: its id not reused
        self.n = self.t0.size
        if self.objective == "targeted":
            if self.theta_target is None:
                raise ModelError("the targeted attack needs theta_target (the paper uses 3 * theta_0)")
            try:
                self.theta_target = np.asarray(self.theta_target, dtype=float)
            except (TypeError, ValueError):
                raise InvalidData("theta_target must be an array of real numbers") from None
            if self.theta_target.shape != (reg.n_params,) or not np.all(np.isfinite(self.theta_target)):
                raise InvalidData(f"theta_target must be {reg.n_params} finite numbers (one per basis function), "
                                  f"got shape {self.theta_target.shape}; e.g. 3 * PAPER_THETA0")
        self.delta_u = self.budget_u.radius(self.u)
        self.delta_y = self.budget_y.radius(self.y)
        if self.objective == "destabilize":
            try:
                num, den = fit_arx(self.u, self.y, *self.arx_orders)
            except RankDeficientRegressor as err:
                raise RankDeficientRegressor(
                    f"the destabilize objective's ARX model with arx_orders={tuple(self.arx_orders)} (na, nb, delay) "
                    f"is rank-deficient on these data ({err}); pass VRFTAttack(..., arx_orders=...), e.g. "
                    f"arx_orders={arx_orders_for(self.u, self.y)} (chosen from the data by "
                    "bilevel.ddc.loop.arx_orders_for: least AIC among full-rank orders)") from err
            self.model_loop = LoopPolynomial.of((num, den), self.setting.basis)

    def _clean_fit(self) -> tuple[np.ndarray, ...]:
        """The clean regressor Phi0, targets t0, learner's theta0 and Phi0's Gram matrix and Phi0't0 (the max-min loss
        in O(nk^2)), read-only."""
        reg = self.setting.regressor
        phi0, t0 = reg(self.y), reg.targets(self.u)
        return _read_only(phi0, t0, least_squares(phi0, t0)[0], phi0.T @ phi0, phi0.T @ t0)

    @property
    def N(self) -> int:
        return self.u.size

    def value(self, theta: np.ndarray) -> float:
        """Attacker objective J(theta) (to maximize)."""
        if self.objective == "maxmin":
            r = self.t0 - self.phi0 @ theta
            return float(r @ r / self.n)
        if self.objective == "targeted":
            d = self.theta_target - theta
            return -float(d @ d / d.size)
        return self._surrogate(theta)[0]

    def _surrogate(self, theta: np.ndarray) -> tuple[float, np.ndarray]:
        """The modelled loop's log-sum-exp and its gradient at theta, the last theta's kept (an ascent reads both at
        each point: one root finding, not two)."""
        key = (np.asarray(theta, dtype=float).tobytes(), self.surrogate_beta)
        if self.__dict__.get("_last_surrogate", (None,))[0] != key:
            self.__dict__["_last_surrogate"] = (key, self.model_loop.surrogate(theta, self.surrogate_beta))
        return self.__dict__["_last_surrogate"][1]

    def grad_theta(self, theta: np.ndarray) -> np.ndarray:
        """dJ/dtheta."""
        if self.objective == "maxmin":
            return -2.0 / self.n * (self.cross0 - self.gram0 @ theta)
        if self.objective == "targeted":
            return 2.0 / theta.size * (self.theta_target - theta)
        return self._surrogate(theta)[1]

    @cached_property
    def learner(self) -> AffineLeastSquares:
        """The learner's least squares on (u + a_u, y + a_y) as the engine's affine kind: C = Phi(y) + Phi(a_y),
        d = t(u) + t(a_u), the regressor's filters and prefilter as its maps."""
        reg, N = self.setting.regressor, self.N
        target = None if reg.prefilter is None else (reg.targets, lambda g: reg.targets_adjoint(g, N))
        return AffineLeastSquares(self.phi0, self.t0, AffineMaps(reg, reg.adjoint, *(target or (None, None)),
                                                                 regressors=reg.stack), N, N)

    @cached_property
    def conditioning_key(self) -> tuple:
        """All the engine's conditioning start depends on besides the declared start (zero) and its step count
        (ConditioningParts.key): the learner's Hessian C'C moves with a_y alone, so a_u stays at zero whatever its
        budget and objective, and the start is a function of the clean regressor, the filters and the output budget."""
        reg = self.setting.regressor
        arrays = [reg.basis_num, reg.basis_den] + [a for op in (reg.error, reg.prefilter) if op is not None
                                                   for a in (op.num, op.den, [op.advance])]
        filters = tuple((np.shape(a), np.asarray(a, dtype=float).tobytes()) for a in arrays)
        return ("vrft", self.phi0.tobytes(), filters, reg.drop, self.N, self.budget_y.norm, self.budget_y.rho,
                self.delta_y)

    @cached_property
    def upper(self) -> UpperObjective:
        """J as the engine's affine-least-squares ascent reads it (a constant Hessian for the quadratic objectives)."""
        k = self.theta0.size
        hessian = {"maxmin": 2.0 * self.gram0 / self.n, "targeted": -2.0 * np.eye(k) / k}.get(self.objective)
        return UpperObjective(self.value, self.grad_theta, hessian)

    @property
    def searched(self) -> Projection | None:
        """Projection onto both budgets (a_u the first N entries, a_y the last N) where the declared problem relaxes
        them (l1, sparsity: the set the structured attacks search, MethodRun.feasible_set), else None (declared)."""
        if all(b.norm in ("l2", "linf") and b.rho is None for b in (self.budget_u, self.budget_y)):
            return None
        N = self.N
        return Blocks([(slice(0, N), self.budget_u.projection(self.u)),
                       (slice(N, 2 * N), self.budget_y.projection(self.y))], 2 * N)

    @property
    def no_exact_input(self) -> str:
        """Why the exact input step (J quadratic in theta, a plain l2 ball on a_u) does not apply ("" where it does)."""
        if self.upper.hessian is None:
            return f"the {self.objective} objective is not quadratic in theta"
        plain = self.budget_u.norm == "l2" and self.budget_u.rho is None
        return "" if plain else f"the input budget {self.budget_u} is not a plain l2 ball"

    def stats(self, theta: np.ndarray) -> dict[str, Any]:
        """What an attack result adds at the poisoned theta: the attack's own criterion (value), the learner's loss on
        the clean data, the true closed loop's spectral radius, and the same at the clean theta; budgets."""
        loop, r = self.setting.loop, self.t0 - self.phi0 @ theta
        return {"objective": self.objective, "value": self.value(theta), "learner_loss": float(r @ r / self.n),
                "theta_clean": self.theta0, "value_clean": self.value(self.theta0),
                "spectral_radius": loop.spectral_radius(theta),
                "spectral_radius_clean": loop.spectral_radius(self.theta0),
                "delta_u": self.delta_u, "delta_y": self.delta_y}

    @staticmethod
    def save_path(path: str) -> str:
        """The .npz file `save` writes for `path`; ModelError if its directory does not exist."""
        folder = os.path.dirname(os.path.abspath(os.fspath(path)))
        if not os.path.isdir(folder):
            raise ModelError(f"VRFTAttack.save: directory {folder!r} of {path!r} does not exist; create it first")
        return os.fspath(path) if os.fspath(path).endswith(".npz") else os.fspath(path) + ".npz"  # as np.savez names it

    def save(self, result: BilevelResult, path: str) -> None:
        """Write the clean data, the attack's signals, the clean and poisoned theta with their true closed-loop poles
        and the attack's criterion at the poisoned theta (value) to an .npz file."""
        if not isinstance(result, BilevelResult) or "theta" not in result.y or "a_y" not in result.x:
            raise ModelError(f"VRFTAttack.save: expected the BilevelResult of a VRFT attack (x: a_u, a_y; y: theta), "
                             f"got {type(result).__name__}; pass what an attack function returned")
        target = self.save_path(path)
        loop, theta = self.setting.loop, result.y["theta"]
        with atomic_path(target) as tmp:
            np.savez(tmp, u=self.u, y=self.y, a_u=result.x["a_u"], a_y=result.x["a_y"], theta_clean=self.theta0,
                     theta_poisoned=theta, poles_clean=loop.poles(self.theta0), poles_poisoned=loop.poles(theta),
                     delta_u=self.delta_u, delta_y=self.delta_y, data_convention=self.setting.data,
                     boundary=self.setting.boundary, method=result.method, objective=self.objective,
                     value=self.value(theta))


@cache
def _convention_setting(convention: str) -> VRFTSetting:
    """flexible_transmission_setting of a convention, built once per process (its regressor and loop with it)."""
    return flexible_transmission_setting(*CONVENTIONS[convention])


def attack_instance(objective: Objective, scenario: Literal["A", "B"] = "B", eps_u: float = 0.1,
                    eps_y: float = 0.057, seed: int = 0, N: int = 512, convention: str = "paper",
                    norm: str = "l2") -> VRFTAttack:
    """The paper's flexible-transmission attack instance (data drawn with default_rng(seed), kept per process for
    an integer seed: KEPT_DATA)."""
    if convention not in CONVENTIONS:
        raise ModelError(f"convention {convention!r} is not one of {', '.join(CONVENTIONS)}")
    check_common_options({"seed": seed})
    setting = _convention_setting(convention)
    reg = setting.regressor
    if not isinstance(N, (int, np.integer)) or isinstance(N, bool) or reg.rows(int(N)) <= reg.n_params:
        raise InvalidData(f"N={N!r} samples: the learner needs more regression rows than its {reg.n_params} "
                          "parameters; pass an integer N of at least a few dozen (the paper uses 512)")
    draw = lambda: _read_only(*scenario_data(setting, scenario, N, np.random.default_rng(seed)))  # noqa: E731
    # an integer seed draws the same data each time, so they are kept; None or a Generator draws new data each call
    u, y = kept(_DATA, (convention, scenario, int(N), int(seed)), draw, KEPT_DATA)[0] \
        if isinstance(seed, (int, np.integer)) else draw()
    target = 3 * PAPER_THETA0 if objective == "targeted" else None
    return VRFTAttack(setting, u, y, Budget(eps_u, norm), Budget(eps_y, norm), objective, target)
