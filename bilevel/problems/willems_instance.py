"""A De Persis–Tesi poisoning instance (paper appendix B, Willems' lemma): its setting (WillemsSetting) and, built by
bilevel.problems.willems.build_attack, the clean data, identified model and declared problem with the instance's
quantities at a poisoning (WillemsAttack: gain and identified loop, criterion, a result's stats) and the engine's oracle
on the problem its shape shares (the data as parameters), the learner's selection ("Selection" in
bilevel.problems.willems) given to its SDP lower level.

Data: one noise-free trajectory (X, U) of a state-feedback plant x_{t+1} = A x_t + B u_t (WillemsSetting.plant,
the paper's batch reactor by default), drawn from the plant or given (WillemsSetting.data).
"""

from __future__ import annotations

import copy
import dataclasses
import threading
from dataclasses import dataclass, fields
from functools import cache
from typing import Any

import casadi as ca
import numpy as np
from numpy.typing import ArrayLike

from ..ddc.data import white_noise_trajectory
from ..ddc.depersis_tesi import lqr_controller, stabilizing_controller, state_data
from ..ddc.plants import batch_reactor
from ..ddc.systems import StatePlantLike, state_matrices
from ..defaults import param
from ..errors import InvalidData, ModelError
from ..kept import kept
from ..model import BilevelProblem
from ..parameters import CompiledFunction
from ..result import BilevelResult
from ..solvers.engine.prepared import prepare
from ..solvers.engine.implicit import Hypergradient, shared_oracle
from ..solvers.engine.options import check_common_options, check_counts, check_flags, check_numbers

DESIGNS = ("lqr", "lqr-r", "stabilizing")
POISONS = ("u", "x", "xu")
SELECTIONS = ("min-norm", "tikhonov", "clarabel", "scs")
SOLVER_SELECTIONS = ("clarabel", "scs")
"""Selections that take the unregularized SDP solver's own Q (bilevel.ddc.depersis_tesi.SOLVERS)."""
OBJECTIVES = ("maxmin", "eigen", "destabilize")
GELFAND_POWER = 16
"""p in the destabilizing criterion log ||Acl^p||_F / p (a power of two; the VRFT attack's too)."""
DEFAULT_REG = 1e-8
"""Tikhonov weight on ||Q||_F^2 / 2: small enough that clean-data gains match the unregularized SDP to 1e-7."""
Matrix = tuple[tuple[float, ...], ...]
DEFAULT_HORIZON = 15


def _frozen(a: np.ndarray) -> Matrix:
    """An array as nested tuples of floats (exact: the setting stays hashable and its arrays round-trip bit for bit)."""
    return tuple(map(tuple, np.asarray(a, dtype=float).tolist()))


@cache
def _batch_reactor() -> tuple[Matrix, Matrix]:
    """The paper's plant as (A, B) tuples, read once (a setting checks its plant's sizes when it is made)."""
    reactor = batch_reactor()
    return _frozen(reactor.A), _frozen(reactor.B)


@dataclass(frozen=True)
class WillemsSetting:
    """Parameters of one attack instance: the plant, its data, the learner, the budgets and the attacker's criterion.

    plant: a discrete-time python-control StateSpace with C = I, D = 0, or (A, B); None is the paper's batch reactor.
    It generates drawn data and judges results (the true closed loop A + B K); the attacker never uses it.
    data: (X, U) with X n x (T+1) and U m x T, or None to draw one experiment from the plant: U i.i.d.
    N(0, input_std^2) from default_rng(seed), X from x0 (0 when None; "random": N(0, I) drawn after U).
    horizon: T of the drawn data (15 when None); with given data None or their T.
    The arrays are stored as tuples of floats: a setting is hashable and equal settings have equal data.
    """

    objective: str = "eigen"
    horizon: int | None = None
    seed: int = 0
    delta_u: float = 0.1
    delta_x: float = 0.0
    poison: str = "u"
    design: str = "lqr"
    qx: Matrix | None = None
    r: Matrix | None = None
    reg: float = DEFAULT_REG
    poison_x0: bool = False
    selection: str = "min-norm"
    plant: StatePlantLike | tuple[Matrix, Matrix] | None = None
    data: tuple[ArrayLike, ArrayLike] | tuple[Matrix, Matrix] | None = None
    input_std: float = 1.0
    x0: tuple[float, ...] | str | None = None

    def __post_init__(self) -> None:
        for name, value, allowed in (("objective", self.objective, OBJECTIVES), ("design", self.design, DESIGNS),
                                     ("poison", self.poison, POISONS), ("selection", self.selection, SELECTIONS)):
            if value not in allowed:
                raise ModelError(f"willems: {name}={value!r} is not one of {', '.join(allowed)}")
        check_numbers({"delta_u": self.delta_u, "delta_x": self.delta_x, "reg": self.reg, "input_std": self.input_std},
                      positive=("input_std",), nonnegative=("delta_u", "delta_x", "reg"))
        if self.horizon is not None:
            check_counts({"horizon": self.horizon}, ("horizon",))
        check_flags({"poison_x0": self.poison_x0}, ("poison_x0",))
        check_common_options({"seed": self.seed})
        if "u" not in self.poison and self.delta_u > 0:
            raise ModelError(f"willems: poison={self.poison!r} leaves U clean but delta_u={self.delta_u}; "
                             "set delta_u=0 or poison='u'/'xu'")
        if "x" in self.poison and self.delta_x <= 0:
            raise ModelError(f"willems: poison={self.poison!r} needs delta_x > 0")
        if not selection_applies(self.selection, self.poison, self.design):
            raise ModelError(f"willems: selection={self.selection!r} (the solver's own Q) is defined only where the "
                             f"SDP ignores the poisoning; got poison={self.poison!r}, design={self.design!r}: use "
                             "poison='u' with design 'lqr' or 'stabilizing', or selection 'min-norm'/'tikhonov'")
        for name in ("qx", "r"):  # as tuples, so that the setting stays hashable (build_attack checks them)
            if getattr(self, name) is not None:
                try:
                    object.__setattr__(self, name, _frozen(getattr(self, name)))
                except (TypeError, ValueError):
                    raise ModelError(f"willems: {name} must be a square matrix of numbers") from None
        a, b = self.plant_matrices() if self.plant is None else state_matrices(self.plant)
        if self.plant is not None:
            object.__setattr__(self, "plant", (_frozen(a), _frozen(b)))
        n, m = b.shape
        if self.data is None:
            object.__setattr__(self, "horizon", DEFAULT_HORIZON if self.horizon is None else self.horizon)
            if self.x0 is not None and not isinstance(self.x0, str):
                x0 = np.asarray(self.x0, dtype=float).ravel()
                if x0.shape != (n,) or not np.all(np.isfinite(x0)):
                    raise InvalidData(f"willems: x0 must be the plant's {n} initial states (finite), None (0) or "
                                      f"'random'; got shape {x0.shape}")
                object.__setattr__(self, "x0", tuple(x0.tolist()))
            elif self.x0 is not None and self.x0 != "random":
                raise InvalidData(f"willems: x0={self.x0!r}: give n numbers, None (x0 = 0) or 'random'")
            return
        if self.x0 is not None or self.input_std != 1.0:
            raise ModelError("willems: x0 and input_std describe drawn data; with data=(X, U) given, drop them")
        try:
            x, u = self.data
        except (TypeError, ValueError):
            raise InvalidData("willems: data must be the pair (X, U), X n x (T+1) states and U m x T inputs") from None
        split = state_data(x, u)
        if split.x0.shape[0] != n or split.u0.shape[0] != m:
            which = "the plant" if self.plant is not None else "the default plant (the batch reactor; pass plant=)"
            raise InvalidData(f"willems: {which} has n = {n} states and m = {m} inputs, the data X {np.shape(x)} "
                              f"and U {np.shape(u)}; pass X as n x (T+1) and U as m x T of the plant's experiment")
        t = split.u0.shape[1]
        if self.horizon is not None and self.horizon != t:
            raise ModelError(f"willems: horizon={self.horizon} but the data have T = {t} samples; pass horizon=None "
                             f"(the data's length) or horizon={t}")
        object.__setattr__(self, "horizon", t)
        object.__setattr__(self, "data", (_frozen(np.asarray(x, dtype=float)), _frozen(np.atleast_2d(u))))

    def plant_matrices(self) -> tuple[np.ndarray, np.ndarray]:
        """(A, B) of the true plant (the batch reactor when plant is None)."""
        a, b = _batch_reactor() if self.plant is None else self.plant
        return np.array(a), np.array(b)

    def experiment(self) -> tuple[np.ndarray, np.ndarray]:
        """The clean data (X, U): the given ones, or one experiment drawn from the plant with default_rng(seed)."""
        if self.data is not None:
            return np.array(self.data[0]), np.array(self.data[1])
        return white_noise_trajectory(*self.plant_matrices(), self.horizon, np.random.default_rng(self.seed),
                                      self.input_std, self.x0)


def selection_applies(selection: str, poison: str, design: str) -> bool:
    """The solver selections (the SDP solver's own Q) are defined only where the SDP ignores the poisoning: input
    poisoning of the designs without an input-cost term ('lqr', 'stabilizing'). The others apply everywhere."""
    return selection not in SOLVER_SELECTIONS or (poison == "u" and design != "lqr-r")


def declaration_of(setting: WillemsSetting) -> tuple:
    """The setting's fields but its budgets (delta_u, delta_x), as (name, value) pairs: WillemsAttack.declaration."""
    return tuple((f.name, getattr(setting, f.name)) for f in fields(setting) if f.name not in ("delta_u", "delta_x"))


def criterion_values(closed_loop: np.ndarray, gain: np.ndarray, objective: str, qx: np.ndarray,
                     r_cost: np.ndarray) -> np.ndarray:
    """The attacker's criterion for batches Acl (..., n, n), K (..., m, n), numerically (same as the problem's)."""
    acl, k = np.asarray(closed_loop, dtype=float), np.asarray(gain, dtype=float)
    if objective == "eigen":
        return 2.0 * np.linalg.slogdet(acl)[1]
    if objective == "destabilize":
        return np.log(np.linalg.norm(np.linalg.matrix_power(acl, GELFAND_POWER), axis=(-2, -1))) / GELFAND_POWER
    n = acl.shape[-1]
    kron = np.einsum("...ij,...kl->...ikjl", acl, acl).reshape(acl.shape[:-2] + (n * n, n * n))
    rhs = np.broadcast_to(np.eye(n).reshape(n * n), kron.shape[:-1])
    w = np.linalg.solve(np.eye(n * n) - kron, rhs[..., None])[..., 0].reshape(acl.shape[:-2] + (n, n))
    cost = qx + np.swapaxes(k, -1, -2) @ r_cost @ k
    values = np.einsum("...ij,...ji->...", cost, w)
    radius = np.max(np.abs(np.linalg.eigvals(acl)), axis=-1)
    return np.where(radius >= 1.0, np.inf, values)


def _maximizing_radius(problem: BilevelProblem, closed_loop: ca.SX) -> BilevelProblem:
    """problem renamed NAME-radius with the upper objective rho(closed_loop) (maximize_spectral_radius)."""
    problem.name = f"{problem.name}-radius"
    problem.maximize_spectral_radius(closed_loop)
    return problem


_SHARED = threading.local()
"""Per thread, .problems: (shape, radius) -> the problem WillemsAttack.shared_problem prepared (the last few,
willems.shared_kept); per thread because an attack re-binds its shape's data and box (a worker with several threads)."""
DATA_FIELDS = ("seed", "data", "x0", "input_std", "plant")
"""Setting fields that only make the data (WillemsAttack.shape leaves them out)."""
DATA_PARAMETERS = {"X": "x", "U": "u", "A_id": "a_id", "B_id": "b_id"}
"""The shared problem's parameters and the attack's arrays that value them."""


@dataclass
class WillemsAttack:
    """A built instance: clean data, identified model, the BilevelProblem, its gain K and closed loop A_id + B_id K
    (CasADi expressions of the upper and lower variables) and the flat upper vector `upper` = (vec Du, vec Dx); the
    true plant (`plant`, `true_closed_loop`) only judges results."""

    setting: WillemsSetting
    x: np.ndarray
    u: np.ndarray
    a_id: np.ndarray
    b_id: np.ndarray
    qx: np.ndarray
    r: np.ndarray
    problem: BilevelProblem
    du: ca.SX
    dx: ca.SX | None
    gain: ca.SX
    closed_loop: ca.SX
    upper: ca.SX
    seen: ca.SX
    """D(x): the poisoned data rows the SDP multiplies Q with ([X0; X1], plus U0 for lqr-r)."""
    compiled: dict[str, Any] = dataclasses.field(default_factory=dict, repr=False, compare=False)
    """Maps compiled from the declaration (loop; criteria's affine gain), shared by the attacks at_budget makes."""

    @property
    def n_states(self) -> int:
        return self.x.shape[0]

    @property
    def n_inputs(self) -> int:
        return self.u.shape[0]

    @property
    def plant(self) -> tuple[np.ndarray, np.ndarray]:
        """(A, B) of the true plant: it judges the attack's result, the attacker never uses it (it has a_id, b_id)."""
        return self.setting.plant_matrices()

    def true_closed_loop(self, gain: np.ndarray) -> np.ndarray:
        """A + B K of the true plant under gain K (m x n), or a batch of them for K (..., m, n)."""
        a, b = self.plant
        return a + b @ np.asarray(gain, dtype=float)

    @property
    def x_offset(self) -> int:
        """First state column that may be poisoned (1 unless x_0 is poisoned)."""
        return 0 if self.setting.poison_x0 else 1

    @property
    def cost_weight(self) -> np.ndarray:
        """R in the attacker's H2 cost trace((Qx + K'RK) W): the learner's R for lqr-r, else 0."""
        return self.r if self.setting.design == "lqr-r" else np.zeros_like(self.r)

    def split(self, xflat: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(Du, Dx) from the flat upper vector (column-major); Dx is n x (T+1), zero where not poisoned."""
        xflat = np.asarray(xflat, dtype=float).ravel()
        m, t = self.u.shape
        du = xflat[: m * t].reshape((m, t), order="F")
        dx = np.zeros_like(self.x)
        if self.dx is not None:
            dx[:, self.x_offset:] = xflat[m * t:].reshape((self.n_states, -1), order="F")
        return du, dx

    def join(self, du: np.ndarray, dx: np.ndarray | None = None) -> np.ndarray:
        """The flat upper vector of (Du, Dx) (inverse of split)."""
        parts = [np.asarray(du, dtype=float).reshape(-1, order="F")]
        if self.dx is not None:
            dx = np.zeros_like(self.x) if dx is None else np.asarray(dx, dtype=float)
            parts.append(dx[:, self.x_offset:].reshape(-1, order="F"))
        return np.concatenate(parts)

    def radius_problem(self) -> BilevelProblem:
        """The attack's problem with the upper objective rho(A_id + B_id K), declared by maximize_spectral_radius
        (solved by the generic engine exactly; the registered problem keeps its CasADi criterion)."""
        return _maximizing_radius(copy.copy(self.problem), self.closed_loop)

    @property
    def declaration(self) -> tuple:
        """The setting without its budgets (delta_u, delta_x): attacks with equal declarations have the same data,
        learner and criterion, and differ only in the box."""
        return declaration_of(self.setting)

    def at_budget(self, delta_u: float, delta_x: float) -> WillemsAttack:
        """This attack at the budgets (delta_u, delta_x): its data, learner, criterion and symbolic declaration with
        their compiled maps (loop, criteria's affine gain), none rebuilt. The declared problem is shared and its box
        re-set to the new budgets, so the attacks of one declaration are to be used one at a time."""
        new = copy.copy(self)
        new.setting = dataclasses.replace(self.setting, delta_u=delta_u, delta_x=delta_x)
        bound = new.budget()
        for name, part in new.problem.upper_layout().items():
            new.problem.set_bounds(name, -bound[part], bound[part])
        return new

    @property
    def shape(self) -> tuple:
        """The declaration without what only makes the data (seed, data, x0, input_std, plant), with the data's sizes:
        attacks of equal shape have one symbolic problem, their data its parameter values (shared_problem)."""
        return tuple((name, value) for name, value in self.declaration
                     if name not in DATA_FIELDS) + (self.x.shape, self.u.shape)

    def budget(self) -> np.ndarray:
        """Upper bounds of |x| entrywise (the linf budgets of each upper entry)."""
        m, t = self.u.shape
        parts = [np.full(m * t, self.setting.delta_u)]
        if self.dx is not None:
            parts.append(np.full(self.n_states * (self.x.shape[1] - self.x_offset), self.setting.delta_x))
        return np.concatenate(parts)

    def shared_problem(self, radius: bool = False) -> BilevelProblem:
        """The declared problem with the data as parameters (declare(..., parameters=True); radius: its objective
        rho(A_id + B_id K) as in radius_problem), prepared once per process for the last defaults["willems.shared_kept"]
        shapes and given this attack's data (set_value where they differ) and box (set_bounds): attacks of one
        shape share the engine's symbolic preparation, and attacks on one data set at several budgets or by several
        methods also the learner's solves. The learner's selection is given to its SDP lower level."""
        problem = kept(_SHARED.__dict__.setdefault("problems", {}), (self.shape, radius),
                       lambda: self._shape_problem(radius), param("willems.shared_kept"))[0]
        for item in problem.parameters.items:  # a new revision (and new learner solves) only for new data
            value = getattr(self, DATA_PARAMETERS[item.name])
            if not np.array_equal(item.value, value.reshape(-1, order="F")):
                problem.set_value(item.name, value)
        bound = self.budget()
        for name, part in problem.upper_layout().items():  # the budget: a declared box, re-set where it differs
            var = next(v for v in problem.upper_variables if v.name == name)
            if not (np.array_equal(var.ub, bound[part]) and np.array_equal(var.lb, -bound[part])):
                problem.set_bounds(name, -bound[part], bound[part])
        prep = prepare(problem)
        low, selection = prep.canon.lower, self.setting.selection
        low.min_norm = selection == "min-norm"
        if selection in SOLVER_SELECTIONS and low.chosen() is None:
            zero = np.zeros(low.n_x)
            ridge = low.select_min_norm(zero, low.kkt_newton(zero, low.reference_solve(zero))[0])
            learner = stabilizing_controller if self.setting.design == "stabilizing" else lqr_controller
            kwargs = {} if self.setting.design == "stabilizing" else {"qx": self.qx, "input_cost": False}
            q = learner(self.x, self.u, solver=selection, **kwargs).q.ravel(order="F")
            low.choose(dataclasses.replace(ridge, y=q, objective=float(low.evaluate(zero, q)[0]),
                                           solver=f"cvxpy+{selection}"))
        return problem

    def _shape_problem(self, radius: bool) -> BilevelProblem:
        """This attack's problem declared with its data as parameters (radius: maximizing rho(A_id + B_id K))."""
        from .willems import declare  # the declaration's module builds WillemsAttack: imported on use
        problem, *_, closed_loop, _, _ = declare(self.setting, self.x, self.u, self.a_id, self.b_id, self.qx, self.r,
                                                 parameters=True)
        return _maximizing_radius(problem, closed_loop) if radius else problem

    def oracle(self, radius: bool = False) -> Hypergradient:
        """The engine's implicit oracle on shared_problem(radius); `oracle().low` is the learner's SDP lower level."""
        return shared_oracle(prepare(self.shared_problem(radius)))

    @property
    def _lower(self) -> ca.SX:
        """The flat lower vector (vec of each lower variable)."""
        return ca.vertcat(*[ca.vec(v.sym) for v in self.problem.lower_variables])

    @property
    def _loop(self) -> CompiledFunction:
        """(x, y) -> (K, A_id + B_id K) of the declared gain and identified loop (compiled once per declaration), called
        through CasADi's buffers (bilevel.parameters.CompiledFunction: the same evaluation without the DM conversions,
        which cost three quarters of a call; the attacks' callbacks call it at every point)."""
        if "loop" not in self.compiled:
            self.compiled["loop"] = CompiledFunction(ca.Function("loop", [self.upper, self._lower],
                                                                 [self.gain, self.closed_loop]))
        return self.compiled["loop"]

    def loop(self, x: np.ndarray, y: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """The gain K and the attacker's identified loop A_id + B_id K at poisoning x (flat), learner solution y."""
        gain, acl = self._loop(x, y)
        return np.asarray(gain, dtype=float), np.asarray(acl, dtype=float)

    def identified_radius(self, x: np.ndarray, y: np.ndarray) -> float:
        """Spectral radius of the attacker's identified closed loop A_id + B_id K at poisoning x, learner solution y."""
        return float(np.max(np.abs(np.linalg.eigvals(self.loop(x, y)[1]))))

    def criteria(self, xs: np.ndarray, y: np.ndarray) -> np.ndarray:
        """The criterion at each column of xs for a learner that ignores the poisoning (y its solution): K =
        K0 + dK/dx x is affine in x (K0 and dK/dx from the declared gain at y, kept per y for the declaration's
        attacks at every budget), numerically."""
        if "affine" not in self.compiled:
            jacobian = ca.jacobian(ca.vec(self.gain), self.upper)
            self.compiled["affine"] = ca.Function("affine", [self.upper, self._lower], [self.gain, jacobian])
        y = np.asarray(y, dtype=float)
        k0, jac = kept(self.compiled.setdefault("affine_at", {}), y.tobytes(), lambda: tuple(
            np.asarray(v, dtype=float) for v in self.compiled["affine"](np.zeros(xs.shape[0]), y)), 4)[0]
        gains = k0[None] + (xs.T @ jac.T).reshape(xs.shape[1], self.n_states, self.n_inputs).transpose(0, 2, 1)
        return criterion_values(self.a_id + self.b_id @ gains, gains, self.setting.objective, self.qx, self.cost_weight)

    def stats(self, result: BilevelResult, evaluations: int, relearn: bool = False) -> dict[str, Any]:
        """What an attack's result adds: x, the gain, eigenvalues and spectral radius of the true loop, the identified
        radius, the criterion (numerically; +inf for an unstable max-min loop), the evaluations, the budget violation
        and the learner's largest scaled KKT residual (certificate); relearn: the gain of the oracle's learner solved at
        x, not of the result's y (a KKT method's y need not be the learner's response)."""
        p, cert = self.problem, result.certificate

        def flat(values: dict[str, np.ndarray], variables: list) -> np.ndarray:
            return np.concatenate([np.asarray(values[v.name], dtype=float).reshape(-1, order="F") for v in variables])
        x = flat(result.x, p.upper_variables)
        y = self.oracle().evaluate(x).lower.y if relearn else flat(result.y, p.lower_variables)
        gain, acl = self.loop(x, y)
        eig = np.linalg.eigvals(self.true_closed_loop(gain))
        criterion = float(criterion_values(acl, gain, self.setting.objective, self.qx, self.cost_weight))
        return {"objective": self.setting.objective, "x": x, "gain": gain, "eigenvalues": eig,
                "spectral_radius": float(np.max(np.abs(eig))), "identified_radius": self.identified_radius(x, y),
                "criterion": criterion, "evaluations": evaluations, "budget_violation": cert.upper_feasibility,
                "kkt_residual": max(cert.stationarity, cert.lower_feasibility, cert.dual_feasibility,
                                    cert.complementarity),
                "details": {"starts": len(result.start_records), "best_start": result.stats.get("best_start"),
                            "certificate_failed": list(cert.failed)}}
