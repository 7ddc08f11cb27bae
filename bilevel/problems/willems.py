"""Poisoning attacks on the De Persis–Tesi learners (paper appendix B, Willems' lemma) as bilevel problems.

Data: one noise-free trajectory (X, U) of a state-feedback plant x_{t+1} = A x_t + B u_t (WillemsSetting.plant,
the paper's batch reactor by default), drawn from the plant or given (WillemsSetting.data).

Upper level (attacker): perturbations Du (m x T) of the inputs and, if poisoned, Dx of the states,
in linf boxes |Du| <= delta_u, |Dx| <= delta_x; it maximizes the max-min criterion (closed-loop H2
cost trace((Qx + K'RK) W), W = Acl W Acl' + I), the eigenvalue criterion log det(Acl Acl') or the
destabilizing criterion log ||Acl^p||_F / p (Gelfand: -> log rho(Acl) as p -> inf, p = GELFAND_POWER), with
Acl = A_id + B_id K and [B_id A_id] = X1 [U0; X0]^+ identified from the *clean* data (the attacker
does not know (A, B)). Lower level (learner): the De Persis–Tesi SDP on the poisoned data, with
lower variable Q (T x n), S = X0' Q (symmetric by equality constraints) and

    lqr          min tr(Qx S)            s.t. [[S - I, X1' Q], [Q' X1'^T, S]] >= 0      (paper appendix)
    lqr-r        min tr(Qx S) + tr(Xr)   s.t. the same LMI and [[Xr, R^1/2 U0' Q], [., S]] >= 0  (DPT Thm 4)
    stabilizing  min tr(S)               s.t. [[S - I, X1' Q], [Q' X1'^T, S - I]] >= 0  (DPT Thm 3)

each plus reg/2 ||Q||_F^2, and K = U0' Q S^{-1}. Why reg: the SDP sees Q only through D Q with
D = [X0; X1] ([X0; X1; U0] for lqr-r); on poisoned data the optimal set in Q is an affine family
whose gains U0' Q S^{-1} fill all of R^{m x n} (lqr, stabilizing), so "the learned K" is not a
function of the data. The Tikhonov term selects the minimum-norm optimal Q as reg -> 0; the
attacker's criteria depend on Q only through K.

Selection (`WillemsSetting.selection`). At an exact KKT point of the regularized SDP, reg Q lies in
the row space of D, but the null-space directions of Q carry curvature reg only, so a solver's KKT
residual r leaves an error ~ r / reg there (up to 7.7e-4 relative in Q at N = 50). "min-norm"
(default) projects the learner's Q onto the row space of D after solving, which leaves D Q, the
SDP's value and the constraints unchanged and makes the selection reproducible to solver accuracy;
"tikhonov" keeps the solver's Q (the selection of the sweep committed in session 1). "clarabel" and "scs"
are the unregularized learner bilevel.ddc.lqr_controller / stabilizing_controller with that SDP solver, whose Q
is the solver's own optimum (same SDP value, another gain); they are defined where the SDP does not see the
poisoning (poison="u", designs lqr and stabilizing), so Q is fixed and K is affine in Du.
"""

from __future__ import annotations

import copy
from dataclasses import dataclass, fields
from functools import cache
from typing import Any

import casadi as ca
import numpy as np
import scipy.linalg
from numpy.typing import ArrayLike

from ..ddc.data import white_noise_trajectory
from ..ddc.depersis_tesi import check_persistency, state_data
from ..ddc.plants import batch_reactor
from ..ddc.systems import StatePlantLike, state_matrices
from ..errors import InvalidData, ModelError, NotPersistentlyExciting
from ..model import BilevelProblem
from ..solvers.options import check_common_options, check_counts, check_flags, check_numbers
from ..vech import symmetric_sx
from .registry import register
from .surrogates import gelfand_log_radius

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

SOURCE = ("Russo & Proutiere, Poisoning attacks against data-driven control methods (extended), appendix "
          "'Attacks on methods based on Willems lemma'; De Persis & Tesi, IEEE TAC 2020, Thms 3-4")


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


def identified_model(x: np.ndarray, u: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(A, B) from [B A] = X1 [U0; X0]^+ (De Persis–Tesi Thm 1; exact on noise-free, persistently exciting data)."""
    data = state_data(x, u)
    check_persistency(data)
    m = data.u0.shape[0]
    ba = data.x1 @ np.linalg.pinv(np.vstack([data.u0, data.x0]))
    return ba[:, m:], ba[:, :m]


def _weight(value: Any, size: int, what: str) -> np.ndarray:
    w = np.eye(size) if value is None else np.asarray(value, dtype=float)
    if w.shape != (size, size) or not np.allclose(w, w.T) or np.linalg.eigvalsh(w).min() <= 0:
        raise ModelError(f"willems: {what} must be a symmetric positive definite {size} x {size} matrix")
    return w


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


def _gramian_expr(acl: ca.SX) -> ca.SX:
    """W with W = Acl W Acl' + I, by the Kronecker linear system (valid where Acl is Schur stable)."""
    n = int(acl.size1())
    vec_w = ca.solve(ca.SX.eye(n * n) - ca.kron(acl, acl), ca.vec(ca.SX.eye(n)))
    return ca.reshape(vec_w, n, n)


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
        p = copy.copy(self.problem)
        p.name = f"{p.name}-radius"
        p.maximize_spectral_radius(self.closed_loop)
        return p

    @property
    def declaration(self) -> tuple:
        """The setting without its budgets (delta_u, delta_x): attacks with equal declarations have the same data,
        learner and criterion, and differ only in the box (bilevel.attacks.willems shares their oracle)."""
        return tuple((f.name, getattr(self.setting, f.name)) for f in fields(self.setting)
                     if f.name not in ("delta_u", "delta_x"))

    def budget(self) -> np.ndarray:
        """Upper bounds of |x| entrywise (the linf budgets of each upper entry)."""
        m, t = self.u.shape
        parts = [np.full(m * t, self.setting.delta_u)]
        if self.dx is not None:
            parts.append(np.full(self.n_states * (self.x.shape[1] - self.x_offset), self.setting.delta_x))
        return np.concatenate(parts)


def build_attack(setting: WillemsSetting | None = None, **params: Any) -> WillemsAttack:
    """The clean data of `setting` (or of keyword parameters), given or drawn from its plant, checked for the
    learner's rank condition, and the attack problem declared on them."""
    if setting is not None and params:
        raise ModelError("build_attack: pass either a WillemsSetting or keyword parameters, not both")
    try:
        s = setting if setting is not None else WillemsSetting(**params)
    except TypeError:
        known = ", ".join(f.name for f in fields(WillemsSetting))
        raise ModelError(f"build_attack: the parameters {', '.join(sorted(params))} include an unknown one; a "
                         f"WillemsSetting takes {known}") from None
    x, u = s.experiment()
    try:
        check_persistency(state_data(x, u))
    except NotPersistentlyExciting as err:
        n_m = x.shape[0] + u.shape[0]
        raise NotPersistentlyExciting(
            f"willems: the learner needs [U0; X0] of full row rank, so T >= n + m = {n_m} samples at least: {err}. "
            "Fix: a longer horizon (drawn data: horizon=; given data: a longer experiment) or a richer input, one "
            "that excites every state (from x0 = 0 an uncontrollable (A, B) never gives full rank)") from None
    a_id, b_id = identified_model(x, u)
    n, m, t = x.shape[0], u.shape[0], s.horizon
    qx, r = _weight(s.qx, n, "qx"), _weight(s.r, m, "r")
    p = BilevelProblem(f"willems-{s.objective}")
    du = p.upper_variable("Du", (m, t), lb=-s.delta_u, ub=s.delta_u, start=0.0)
    xs = ca.SX(ca.DM(x))
    dx = None
    if "x" in s.poison:
        offset = 0 if s.poison_x0 else 1
        dx = p.upper_variable("Dx", (n, t + 1 - offset), lb=-s.delta_x, ub=s.delta_x, start=0.0)
        xs = ca.horzcat(xs[:, :offset], xs[:, offset:] + dx) if offset else xs + dx
    us = ca.DM(u) + du
    x0p, x1p = xs[:, :t], xs[:, 1:]
    q = p.lower_variable("Q", (t, n))
    s_raw = ca.mtimes(x0p, q)
    p.lower_constraint(ca.vertcat(*[s_raw[i, j] - s_raw[j, i] for j in range(n) for i in range(j)]) == 0,
                       name="S_symmetric")
    s_mat = 0.5 * (s_raw + s_raw.T)
    m_mat = ca.mtimes(x1p, q)
    eye = ca.SX.eye(n)
    lower = ca.trace(ca.mtimes(ca.DM(qx), s_mat)) if s.design != "stabilizing" else ca.trace(s_mat)
    corner = s_mat - eye if s.design == "stabilizing" else s_mat
    p.lower_psd_constraint(ca.blockcat([[s_mat - eye, m_mat], [m_mat.T, corner]]), name="gramian")
    v_mat = ca.mtimes(us, q)
    if s.design == "lqr-r":
        xr = symmetric_sx(p.lower_variable("Xr", m * (m + 1) // 2), m)
        weighted = ca.mtimes(ca.DM(np.real(scipy.linalg.sqrtm(r))), v_mat)
        p.lower_psd_constraint(ca.blockcat([[xr, weighted], [weighted.T, s_mat]]), name="input_cost")
        lower += ca.trace(xr)
    p.minimize_lower(lower + 0.5 * s.reg * ca.sumsqr(q))
    gain = ca.mtimes(v_mat, ca.inv(s_mat))
    acl = ca.DM(a_id) + ca.mtimes(ca.DM(b_id), gain)
    if s.objective == "eigen":
        p.maximize_upper(2 * ca.log(ca.fabs(ca.det(acl))))
    elif s.objective == "destabilize":
        p.maximize_upper(gelfand_log_radius(acl, GELFAND_POWER))
    else:
        cost = ca.DM(qx) + (ca.mtimes([gain.T, ca.DM(r), gain]) if s.design == "lqr-r" else 0)
        p.maximize_upper(ca.trace(ca.mtimes(cost, _gramian_expr(acl))))
    upper = ca.vertcat(ca.vec(du), ca.vec(dx)) if dx is not None else ca.vec(du)
    seen = ca.vertcat(x0p, x1p, us) if s.design == "lqr-r" else ca.vertcat(x0p, x1p)
    return WillemsAttack(s, x, u, a_id, b_id, qx, r, p, du, dx, gain, acl, upper, seen)


def _register(objective: str, description: str) -> None:
    @register(f"willems-{objective}", source=SOURCE, tags=("willems", "attack", "sdp"), description=description,
              defaults={**{f.name: f.default for f in fields(WillemsSetting) if f.name != "objective"},
                        "horizon": DEFAULT_HORIZON})
    def build(**params: Any) -> BilevelProblem:
        if params.get("selection") in SOLVER_SELECTIONS:
            raise ModelError(f"willems-{objective}: the declared problem's learner is the regularized SDP; "
                             f"selection={params['selection']!r} (the solver's own Q) exists in the structured "
                             "attacks only (bilevel.attacks.willems; `bilevel solve willems-destabilize` without "
                             "--method)")
        return build_attack(WillemsSetting(objective=objective, **params)).problem


_register("maxmin", "max-min attack on De Persis-Tesi: maximize the closed-loop H2 cost through the Gramian")
_register("eigen", "eigenvalue attack on De Persis-Tesi: maximize log det((A+BK)(A+BK)')")
_register("destabilize", "destabilizing attack on De Persis-Tesi: maximize log ||(A+BK)^16||_F / 16 (-> log rho)")
