"""A poisoning instance of least-squares system identification: the plant and noise (IdentificationSetting), the clean
data, the learner's regression, budgets, the attacker's objective and the optional stealth level.

Learners (both linear regressions Y ~ Theta Z, outputs x samples):
  "ss"   state space: [A B] = argmin ||X+ - [A B] [X; U]||_F^2 from states X (n x (T+1)) and inputs U (m x T);
  "arx"  ARX(na, nb): theta = [a; b] = argmin sum_t (y_t + a' y_{t-1..t-na} - b' u_{t-1..t-nb})^2, t >= max(na, nb).
The attacker adds dS to each signal S within ||dS||_F <= eps_S ||S||_F and maximizes the parameter error
(objective "frobenius": ||d Theta||_F^2; "spectral": ||d Theta||_2^2, the largest eigenvalue of dTheta dTheta') or,
for the state-space learner, a model-based quantity (bilevel.ddc.model_based): "h2", the identified model's H2 norm
from input to state, or "ce-lqr", the spectral radius of the true plant under the certainty-equivalence LQR gain of
the identified model (weights Q = q I, R = r I; rho >= 1: the true loop is unstable); with
stealth = delta it keeps each residual test statistic (bilevel.ddc.residual_tests) within |1 - stat'/stat| <= delta of
its clean value (stealth_kind "tests", the project's own definition), or, with stealth_kind "authors", bounds each
statistic of Russo & Proutiere's stealthy attack (bilevel.ddc.stealth_statistics: the residual energy, Z_d and the
correlation ratio of every lag tau = 1..s, s = 2 floor(0.025 T)) within delta of its clean value and every entry of dX
and dU within [-box, box] (their 0.5). bilevel.problems.identification declares the instance as a BilevelProblem.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Literal

import casadi as ca
import numpy as np
from scipy.signal import lfilter

from ..ddc.data import state_trajectory
from ..ddc.plants import flexible_transmission
from ..ddc.residual_tests import ResidualTest, regression_tests
from ..ddc.stealth_check import BOX
from ..ddc.stealth_statistics import StealthStatistics, authors_lags
from ..ddc.systems import num_den
from ..errors import InvalidData, ModelError, RankDeficientRegressor
from ..real_data import integer, real_array, real_number
from ..solvers.engine.options import check_common_options

Learner = Literal["ss", "arx"]
Objective = Literal["frobenius", "spectral", "h2", "ce-lqr"]
OBJECTIVES = ("frobenius", "spectral", "h2", "ce-lqr")
MODEL_BASED = ("h2", "ce-lqr")
"""Objectives of a state-space model: the state-space learner only."""
TEST_LAGS = 10
"""The whiteness test's lags of stealth_kind "tests" unless given."""
StealthKind = Literal["tests", "authors"]
STEALTH_KINDS = ("tests", "authors")
"""What stealth = delta bounds: "tests", the project's residual tests (bilevel.ddc.residual_tests: variance,
portmanteau whiteness over `lags` lags, input F-test); "authors", Russo & Proutiere's statistics, each lag apart, and a
box on every entry (bilevel.ddc.stealth_statistics; state-space learner only)."""


def controllable_canonical(num: np.ndarray, den: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(A, B, C) of a strictly proper SISO G(z) = num/den in controllable canonical form: A's first row -den[1:]
    (den monic), ones on the subdiagonal, B = e_1, C = num padded to the order."""
    num, den = np.atleast_1d(np.asarray(num, float)), np.atleast_1d(np.asarray(den, float))
    n = den.size - 1
    if n < 1 or num.size > n or den[0] == 0:
        raise ModelError(f"controllable_canonical: need a strictly proper G(z) with den of order >= 1, got num "
                         f"{num}, den {den}")
    A = np.vstack([-den[1:] / den[0], np.eye(n - 1, n)])
    B = np.eye(n, 1)
    C = np.concatenate([np.zeros(n - num.size), num / den[0]])[None, :]
    return A, B, C


@dataclass(frozen=True)
class IdentificationSetting:
    """The true plant (num, den of G(z); the state-space data use its controllable canonical realization), the input
    std and the process-noise std (white Gaussian, on every state; on the ARX equation error)."""

    num: np.ndarray
    den: np.ndarray
    input_std: float = 1.0
    noise_std: float = 0.1

    @property
    def state_space(self) -> tuple[np.ndarray, np.ndarray]:
        """(A, B) of the controllable canonical realization."""
        A, B, _ = controllable_canonical(self.num, self.den)
        return A, B

    def state_data(self, T: int, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
        """(X, U): states x_0 = 0 .. x_T of x+ = A x + B u + w, inputs u ~ N(0, input_std^2), w ~ N(0, noise_std^2 I)."""
        A, B = self.state_space
        U = self.input_std * rng.standard_normal((B.shape[1], T))
        W = self.noise_std * rng.standard_normal((A.shape[0], T))
        return state_trajectory(A, np.hstack([B, np.eye(A.shape[0])]), np.vstack([U, W])), U

    def arx_data(self, T: int, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
        """(u, y) of den(q) y = num(q) u + e from rest, u ~ N(0, input_std^2), e ~ N(0, noise_std^2)."""
        num, den = np.asarray(self.num, float), np.asarray(self.den, float)
        b = np.concatenate([np.zeros(den.size - num.size), num])  # in powers of q^-1: b[0] = 0 (strictly proper)
        u = self.input_std * rng.standard_normal(T)
        e = self.noise_std * rng.standard_normal(T)
        return u, lfilter(b, den, u) + lfilter([1.0], den, e)

    def arx_parameters(self, na: int, nb: int) -> np.ndarray:
        """The true theta = [a_1..a_na, b_1..b_nb] of the ARX(na, nb) regression (zeros beyond the plant's orders)."""
        num, den = np.asarray(self.num, float), np.asarray(self.den, float)
        b = np.concatenate([np.zeros(den.size - num.size), num])[1:]
        theta = np.zeros(na + nb)
        theta[:min(na, den.size - 1)] = den[1:na + 1] / den[0]
        theta[na:na + min(nb, b.size)] = b[:nb] / den[0]
        return theta


def flexible_transmission_setting(input_std: float = 1.0, noise_std: float = 0.1) -> IdentificationSetting:
    """Landau's flexible transmission (Ts = 0.05), the paper's VRFT plant, as an identification setting."""
    num, den = num_den(flexible_transmission())
    return IdentificationSetting(np.asarray(num, float), np.asarray(den, float), input_std, noise_std)


def ss_regression(X: ca.SX | np.ndarray, U: ca.SX | np.ndarray) -> tuple[ca.SX, ca.SX]:
    """(Y, Z) = (X[:, 1:], [X[:, :T]; U]) of the state-space learner, for numbers (as DM) or expressions."""
    T = U.shape[1]
    return X[:, 1:T + 1], ca.vertcat(X[:, :T], U)


def arx_regression(u: ca.SX | np.ndarray, y: ca.SX | np.ndarray, na: int, nb: int) -> tuple[ca.SX, ca.SX]:
    """(Y, Z) of the ARX(na, nb) learner: Y = y_t (1 x N), Z = [-y_{t-1}; ..; -y_{t-na}; u_{t-1}; ..; u_{t-nb}],
    t = max(na, nb) .. T-1, for numbers (as DM) or expressions (u, y column vectors)."""
    T, n0 = u.shape[0], max(na, nb)
    rows = [-y[n0 - i:T - i] for i in range(1, na + 1)] + [u[n0 - j:T - j] for j in range(1, nb + 1)]
    return y[n0:T].T, ca.horzcat(*rows).T


def _numbers(pair: tuple[ca.DM, ca.DM]) -> tuple[np.ndarray, np.ndarray]:
    return np.array(pair[0]), np.array(pair[1])


def least_squares_fit(Y: np.ndarray, Z: np.ndarray) -> np.ndarray:
    """Theta = argmin ||Y - Theta Z||_F (numpy lstsq); raises RankDeficientRegressor if Z Z' is singular."""
    theta, _, rank, _ = np.linalg.lstsq(Z.T, Y.T, rcond=None)
    if rank < Z.shape[0]:
        raise RankDeficientRegressor(f"the identification regressor has rank {rank} < {Z.shape[0]}: the data do not "
                                     "excite the model; use a richer input or a longer experiment")
    return theta.T


@dataclass
class IdentificationAttack:
    """One attack instance: clean signals (X, U for "ss"; u, y for "arx"), relative l2 budgets per signal (Frobenius
    norm), the objective, the ARX orders, the lags (of the whiteness test, or the authors' s), the stealth level
    (None: no stealth), the LQR weights (q, r) of objective "ce-lqr" (Q = q I, R = r I), the stealth kind
    (STEALTH_KINDS) and the box on every entry of the changes (None: none; "authors" defaults to their 0.5)."""

    setting: IdentificationSetting
    learner: Learner
    signals: dict[str, np.ndarray]
    eps: dict[str, float]
    objective: Objective = "frobenius"
    stealth: float | None = None
    lags: int = 10
    orders: tuple[int, int] = (4, 4)
    lqr_weights: tuple[float, float] = (1.0, 1.0)
    stealth_kind: StealthKind = "tests"
    box: float | None = None
    Y0: np.ndarray = field(init=False)
    Z0: np.ndarray = field(init=False)
    theta0: np.ndarray = field(init=False)

    def __post_init__(self) -> None:
        if self.learner not in ("ss", "arx"):
            raise ModelError(f"learner {self.learner!r} is not 'ss' (state space) or 'arx'")
        if self.objective not in OBJECTIVES:
            raise ModelError(f"objective {self.objective!r} is not one of {', '.join(OBJECTIVES)}")
        if self.objective in MODEL_BASED and self.learner != "ss":
            raise ModelError(f"objective {self.objective!r} is a property of a state-space model: use the 'ss' "
                             "learner (ident-ss)")
        if not all(real_number(w, "lqr weight") > 0 for w in self.lqr_weights):
            raise ModelError(f"lqr_weights (q, r) must be positive and finite, got {self.lqr_weights}")
        names = ("X", "U") if self.learner == "ss" else ("u", "y")
        if set(self.signals) != set(names) or set(self.eps) != set(names):
            raise ModelError(f"the {self.learner} learner takes signals and budgets {names}, got signals "
                             f"{sorted(self.signals)} and budgets {sorted(self.eps)}")
        self.lags = integer(self.lags, "lags (the whiteness test's)", 1)
        if self.learner == "arx":
            self.orders = (integer(self.orders[0], "ARX order na", 0), integer(self.orders[1], "ARX order nb", 1))
        for name in names:
            s = real_array(self.signals[name], f"signal {name}")
            if not np.all(np.isfinite(s)):
                raise InvalidData(f"signal {name} contains NaN or inf")
            if s.ndim > 2 or (self.learner == "arx" and s.ndim == 2 and 1 not in s.shape):
                raise InvalidData(f"signal {name} has shape {s.shape}: give " + ("a 1-D signal" if self.learner == "arx"
                                  else "a matrix (channels x samples)"))
            self.signals[name] = s.reshape(-1, 1) if self.learner == "arx" else np.atleast_2d(s)
            if real_number(self.eps[name], f"budget eps_{name}") < 0:
                raise ModelError(f"budget eps_{name} must be finite and >= 0, got {self.eps[name]}")
        self._check_lengths()
        if self.stealth is not None and not 0 < real_number(self.stealth, "stealth") < 1:
            raise ModelError(f"stealth must be a relative tolerance in (0, 1) (e.g. 0.05) or None, got {self.stealth}")
        if self.stealth_kind not in STEALTH_KINDS:
            raise ModelError(f"stealth_kind {self.stealth_kind!r} is not one of {', '.join(STEALTH_KINDS)}")
        if self.stealth_kind == "authors":
            if self.learner != "ss":
                raise ModelError("stealth_kind 'authors' constrains the state-space learner's statistics: use 'ss'")
            if self.lags != authors_lags(self.signals["U"].shape[1]):
                raise ModelError(f"stealth_kind 'authors' has s = 2 floor(0.025 T) = "
                                 f"{authors_lags(self.signals['U'].shape[1])} lags, got lags={self.lags}; pass "
                                 "lags=None to attack_instance")
            self.box = BOX if self.box is None else self.box
        if self.box is not None and not (np.isfinite(self.box) and self.box > 0):
            raise ModelError(f"box must be a positive bound on every entry of the changes or None, got {self.box}")
        self.Y0, self.Z0 = self.regression(self.signals)
        if self.Y0.shape[1] <= self.Z0.shape[0] + self.lags:
            raise InvalidData(f"{self.Y0.shape[1]} regression samples for {self.Z0.shape[0]} regressors and "
                              f"{self.lags} whiteness lags: record a longer experiment")
        self.theta0 = least_squares_fit(self.Y0, self.Z0)
        if self.stealth_kind == "authors":
            self.authors_statistics  # noqa: B018 (checks the sizes)

    def _check_lengths(self) -> None:
        """The signals' lengths fit the learner (never a signal cut to the others' length): X has one sample more
        than U (states x_0 .. x_T for inputs u_0 .. u_{T-1}); u and y are equally long."""
        if self.learner == "ss":
            (n, cols), (m, T) = self.signals["X"].shape, self.signals["U"].shape
            if cols != T + 1:
                raise InvalidData(f"signal X has shape {(n, cols)} and U {(m, T)}: X holds the states x_0 .. x_T of T "
                                  f"inputs, so it needs T + 1 = {T + 1} columns (states x samples; transposed?)")
        elif self.signals["u"].size != self.signals["y"].size:
            raise InvalidData(f"signals u and y have {self.signals['u'].size} and {self.signals['y'].size} samples; "
                              "the ARX learner needs them equally long")

    def regression(self, signals: dict[str, np.ndarray]) -> tuple[np.ndarray, np.ndarray]:
        """(Y, Z) of the learner on the signals given (as numbers)."""
        if self.learner == "ss":
            return _numbers(ss_regression(ca.DM(signals["X"]), ca.DM(signals["U"])))
        return _numbers(arx_regression(ca.DM(signals["u"]), ca.DM(signals["y"]), *self.orders))

    @property
    def input_rows(self) -> list[int]:
        """The rows of Z that carry the input (the F-test drops them)."""
        k = self.Z0.shape[0]
        q = self.signals["U"].shape[0] if self.learner == "ss" else self.orders[1]
        return list(range(k - q, k))

    @property
    def authors_statistics(self) -> StealthStatistics:
        """The authors' statistics of this instance's regression (stealth_kind "authors")."""
        keep = tuple(i for i in range(self.Z0.shape[0]) if i not in self.input_rows)
        return StealthStatistics(self.Y0.shape[0], self.Z0.shape[0], self.Y0.shape[1], keep, self.lags)

    def radius(self, name: str) -> float:
        """delta_S = eps_S ||S||_F."""
        return float(self.eps[name] * np.linalg.norm(self.signals[name]))

    def tests(self, signals: dict[str, np.ndarray] | None = None) -> dict[str, ResidualTest]:
        """The defender's tests of the least-squares model fitted on `signals` (default: the clean data)."""
        Y, Z = self.regression(self.signals if signals is None else signals)
        return regression_tests(Y, Z, least_squares_fit(Y, Z), self.input_rows, self.setting.noise_std, self.lags)


def attack_instance(learner: Learner, T: int = 100, eps: float = 0.05, objective: Objective = "frobenius",
                    stealth: float | None = None, seed: int = 0, lags: int | None = None, na: int = 4,
                    nb: int = 4, lqr_weights: tuple[float, float] = (1.0, 1.0), stealth_kind: StealthKind = "tests",
                    box: float | None = None) -> IdentificationAttack:
    """The flexible transmission's instance (data drawn with default_rng(seed)), budget eps on every signal; lags None:
    the kind's (10 for "tests", s = 2 floor(0.025 T) for "authors")."""
    check_common_options({"seed": seed})
    if not isinstance(T, (int, np.integer)) or isinstance(T, bool) or T < 1:
        raise InvalidData(f"T={T!r}: give a positive integer number of samples (e.g. 100)")
    setting = flexible_transmission_setting()
    rng = np.random.default_rng(seed)
    if learner == "ss":
        X, U = setting.state_data(int(T), rng)
        signals = {"X": X, "U": U}
    else:
        u, y = setting.arx_data(int(T), rng)
        signals = {"u": u, "y": y}
    if lags is None:
        lags = authors_lags(int(T)) if stealth_kind == "authors" else TEST_LAGS
    return IdentificationAttack(setting, learner, signals, {k: eps for k in signals}, objective, stealth, lags,
                                (na, nb), lqr_weights, stealth_kind, box)
