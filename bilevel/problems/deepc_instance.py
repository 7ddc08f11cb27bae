"""A poisoning instance of data-enabled predictive control (DeePC; Coulson, Lygeros & Doerfler 2019): the plant, the
recorded data, the controller's weights, the attacker's budgets and objective.

The learner, from depth-(t_ini + horizon) Hankel matrices [Up; Yp; Uf; Yf] of the recorded (u, y):

    min_{g, u, y, s}  q ||y - r||^2 + r_weight ||u||^2 + lambda_g ||g||^2 + lambda_y ||s||_1
    s.t.  Up g = u_ini,  Yp g = y_ini + s,  Uf g = u,  Yf g = y,  |u_k| <= u_max (u_max = None: no bound),

a QP once cvxpy moves the l1 term to auxiliary variables. The true plant answers the planned inputs u from the state
its past (u_ini, y_ini) left it in with y_true = free + S u (free response and impulse-response Toeplitz S): an
affine map of u. The attacker changes each recorded signal within ||dS||_q <= eps ||S||_q (q = 2 or inf) and
maximizes the true tracking cost q ||y_true - r||^2 + r_weight ||u||^2 of the plan ("tracking") or the squared
deviation (u_0 - u_0^clean)^2 of its first action ("first-action"). bilevel.problems.deepc declares it.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Literal

import casadi as ca
import control
import cvxpy as cp
import numpy as np
from scipy.linalg import toeplitz

from ..ddc.data import simulate
from ..ddc.plants import flexible_transmission
from ..ddc.systems import num_den
from ..errors import InvalidData, ModelError, NotPersistentlyExciting
from ..real_data import integer, real_array, real_number
from ..solvers.engine.options import check_common_options
from .budget import Budget

Norm = Literal["l2", "linf"]
Objective = Literal["tracking", "first-action"]
OBJECTIVES = ("tracking", "first-action")
PAST = 50
"""Samples of the past trajectory that sets the initial state (its last t_ini samples are u_ini, y_ini)."""


def hankel(signal: ca.SX | np.ndarray, depth: int) -> ca.SX | ca.DM:
    """The depth x (n - depth + 1) Hankel matrix [s_j .. s_{j+depth-1}]_j of a column signal (numbers or expression)."""
    s = ca.DM(np.asarray(signal, dtype=float).ravel()) if isinstance(signal, np.ndarray) else signal
    return ca.horzcat(*[s[j:j + depth] for j in range(int(s.numel()) - depth + 1)])


@dataclass
class DeePCAttack:
    """One attack instance: the true plant, recorded data (u, y), the past trajectory (past_u, past_y, the plant's
    own; its last t_ini samples are u_ini, y_ini), the controller's weights and the attacker's budget and objective."""

    plant: control.TransferFunction
    u: np.ndarray
    y: np.ndarray
    past_u: np.ndarray
    past_y: np.ndarray
    budget: Budget
    objective: Objective = "tracking"
    t_ini: int = 4
    horizon: int = 10
    reference: float = 1.0
    q: float = 1.0
    r_weight: float = 0.01
    lambda_g: float = 0.1
    lambda_y: float = 1000.0
    u_max: float | None = None
    free: np.ndarray = field(init=False)
    step: np.ndarray = field(init=False)
    u0_clean: float = field(init=False)

    def __post_init__(self) -> None:
        if self.budget.norm not in ("l2", "linf") or self.budget.rho is not None:
            raise ModelError(f"a DeePC budget is l2 or linf without sparsity, got {self.budget}")
        if self.objective not in OBJECTIVES:
            raise ModelError(f"objective {self.objective!r} is not one of {', '.join(OBJECTIVES)}")
        self.t_ini, self.horizon = integer(self.t_ini, "t_ini", 1), integer(self.horizon, "horizon", 1)
        for name in ("u", "y", "past_u", "past_y"):
            s = real_array(getattr(self, name), f"signal {name}").ravel()
            if not np.all(np.isfinite(s)):
                raise InvalidData(f"signal {name} contains NaN or inf")
            setattr(self, name, s)
        if self.u.size != self.y.size or self.past_u.size != self.past_y.size or self.past_u.size < self.t_ini:
            raise InvalidData(f"u and y have {self.u.size} and {self.y.size} samples, past_u and past_y "
                              f"{self.past_u.size} and {self.past_y.size}: give equal lengths, a past of >= t_ini")
        weights = {"q": self.q, "r_weight": self.r_weight, "lambda_g": self.lambda_g, "lambda_y": self.lambda_y}
        if not all(real_number(v, k) >= 0 for k, v in weights.items()) or self.q + self.r_weight == 0:
            raise ModelError(f"the weights must be finite and >= 0, q + r_weight > 0, got {weights}")
        self.reference = self._reference(self.reference)
        if self.u_max is not None and not real_number(self.u_max, "u_max") > 0:
            raise ModelError(f"u_max must be a positive bound or None (no input bound), got {self.u_max}")
        depth = self.t_ini + self.horizon
        order = len(num_den(self.plant)[1]) - 1
        if self.u.size - depth + 1 < 2 * depth:
            raise InvalidData(f"{self.u.size} samples give {self.u.size - depth + 1} Hankel columns for depth {depth}"
                              f": record at least {3 * depth - 1} samples")
        if np.linalg.matrix_rank(np.array(hankel(self.u, depth + order))) < depth + order:
            raise NotPersistentlyExciting(f"the recorded input is not persistently exciting of order {depth + order} "
                                          "(t_ini + horizon + plant order): use a richer input (e.g. white noise)")
        P, N = self.past_u.size, self.horizon
        self.free = simulate(self.plant, np.concatenate([self.past_u, np.zeros(N)]))[P:]
        impulse = simulate(self.plant, np.eye(N)[0])
        self.step = toeplitz(impulse, np.zeros(N))
        self.u0_clean = float(self.plan(self.u, self.y)[0])

    @staticmethod
    def _reference(reference: object) -> float:
        """The setpoint r: one finite number (the tracking cost's and the closed loop's)."""
        r = real_array(reference, "reference")
        if r.size != 1:
            raise InvalidData(f"reference has shape {r.shape}: the setpoint r is one finite number")
        return real_number(float(r.ravel()[0]), "reference")

    def _recorded(self, u: object, y: object) -> tuple[np.ndarray, np.ndarray]:
        """Recorded data (u, y) as the learner takes them: finite real 1-D signals of the instance's length (its
        Hankel matrices have that many columns; a longer record is not cut)."""
        u, y = (real_array(s, name).ravel() for s, name in ((u, "recorded u"), (y, "recorded y")))
        if u.size != self.u.size or y.size != self.u.size:
            raise InvalidData(f"recorded u and y have {u.size} and {y.size} samples; this learner's Hankel matrices "
                              f"are built from {self.u.size} (make a DeePCAttack of the new length instead)")
        if not (np.all(np.isfinite(u)) and np.all(np.isfinite(y))):
            raise InvalidData("recorded u or y contains NaN or inf")
        return u, y

    def learner(self) -> tuple[cp.Problem, dict[str, cp.Parameter | cp.Variable]]:
        """The DeePC QP as a cvxpy Problem with Parameters "Hu", "Hy" (the depth t_ini + horizon Hankel matrices;
        values: the clean data's) and "u_ini", "y_ini" (values: the past's), and its variables "g", "u", "y",
        "sigma_y"."""
        depth, cols, k = self.t_ini + self.horizon, self.u.size - self.t_ini - self.horizon + 1, self.t_ini
        Hu = cp.Parameter((depth, cols), name="Hu", value=np.array(hankel(self.u, depth)))
        Hy = cp.Parameter((depth, cols), name="Hy", value=np.array(hankel(self.y, depth)))
        u_ini = cp.Parameter(k, name="u_ini", value=self.past_u[-k:])
        y_ini = cp.Parameter(k, name="y_ini", value=self.past_y[-k:])
        g, u, y, s = cp.Variable(cols), cp.Variable(self.horizon), cp.Variable(self.horizon), cp.Variable(k)
        constraints = [Hu[:k] @ g == u_ini, Hy[:k] @ g == y_ini + s, Hu[k:] @ g == u, Hy[k:] @ g == y]
        if self.u_max is not None:
            constraints += [u <= self.u_max, u >= -self.u_max]
        cost = (self.q * cp.sum_squares(y - self.reference) + self.r_weight * cp.sum_squares(u)
                + self.lambda_g * cp.sum_squares(g) + self.lambda_y * cp.norm1(s))
        return cp.Problem(cp.Minimize(cost), constraints), {"Hu": Hu, "Hy": Hy, "u_ini": u_ini, "y_ini": y_ini,
                                                            "g": g, "u": u, "y": y, "sigma_y": s}

    def plan(self, u: np.ndarray, y: np.ndarray) -> np.ndarray:
        """The planned inputs of the learner on recorded data (u, y) (cvxpy + Clarabel)."""
        return self.closed_loop(u, y, 0)[2]

    def closed_loop(self, u: np.ndarray, y: np.ndarray, steps: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Receding horizon on the true plant with the learner fitted to recorded data (u, y): at each of `steps`
        steps it re-solves DeePC from the last t_ini inputs and outputs and applies the first planned input.
        Returns the applied inputs, the outputs at the same times (y_t before u_t acts) and the last plan."""
        u, y = self._recorded(u, y)
        steps = integer(steps, "closed_loop steps", 0)
        problem, v = self.learner()
        depth, k = self.t_ini + self.horizon, self.t_ini
        v["Hu"].value, v["Hy"].value = np.array(hankel(u, depth)), np.array(hankel(y, depth))
        inputs, outputs = list(self.past_u), list(self.past_y)
        for t in range(steps + 1):
            v["u_ini"].value, v["y_ini"].value = np.array(inputs[-k:]), np.array(outputs[-k:])
            problem.solve(solver=cp.CLARABEL)
            if problem.status != cp.OPTIMAL:
                raise InvalidData(f"the DeePC learner on these data ended {problem.status} at step {t}; check the "
                                  "data and u_max")
            if t < steps:
                inputs.append(float(v["u"].value[0]))
                outputs.append(float(simulate(self.plant, np.array(inputs))[-1]))
        P = self.past_u.size
        return np.array(inputs[P:]), np.array(outputs[P:]), np.asarray(v["u"].value, dtype=float)

    def closed_loop_cost(self, u: np.ndarray, y: np.ndarray, steps: int) -> float:
        """q sum (y_t - r)^2 + r_weight sum u_t^2 over `steps` receding-horizon steps (closed_loop)."""
        applied, outputs, _ = self.closed_loop(u, y, steps)
        return float(self.q * np.sum((outputs - self.reference) ** 2) + self.r_weight * applied @ applied)

    def true_output(self, plan: np.ndarray | ca.SX) -> np.ndarray | ca.SX:
        """The true plant's outputs under planned inputs, from the state its past left it in: free + S u."""
        if isinstance(plan, np.ndarray):
            plan = real_array(plan, "plan").ravel()
            if plan.size != self.horizon:
                raise InvalidData(f"a plan has {self.horizon} inputs (the horizon), got {plan.size}")
            return self.free + self.step @ plan
        return ca.DM(self.free) + ca.mtimes(ca.DM(self.step), plan)

    def tracking_cost(self, plan: np.ndarray | ca.SX) -> float | ca.SX:
        """q ||y_true - r||^2 + r_weight ||u||^2 of planned inputs on the true plant."""
        e = self.true_output(plan) - self.reference
        if isinstance(plan, np.ndarray):
            return float(self.q * e @ e + self.r_weight * plan @ plan)
        return self.q * ca.sumsqr(e) + self.r_weight * ca.sumsqr(plan)

    def value(self, plan: np.ndarray | ca.SX) -> float | ca.SX:
        """The attacker's objective of planned inputs."""
        if self.objective == "tracking":
            return self.tracking_cost(plan)
        return (plan[0] - self.u0_clean) ** 2

    def radius(self, name: str) -> float:
        """delta_S = eps ||S||_q of recorded signal "u" or "y"."""
        return self.budget.radius(getattr(self, name))


def attack_instance(T: int = 200, eps: float = 0.05, norm: Norm = "l2", objective: Objective = "tracking",
                    seed: int = 0, noise_std: float = 0.01, past_std: float = 0.0, t_ini: int = 4,
                    horizon: int = 10, lambda_g: float = 0.1, lambda_y: float = 1000.0,
                    u_max: float | None = None) -> DeePCAttack:
    """The flexible transmission's instance (default_rng(seed)): T recorded samples, input N(0, 1), output measured
    with N(0, noise_std^2) noise; the past is the plant's response to PAST inputs N(0, past_std^2) (0: at rest);
    setpoint r = 1."""
    check_common_options({"seed": seed})
    if not isinstance(T, (int, np.integer)) or isinstance(T, bool) or T < 1:
        raise InvalidData(f"T={T!r}: give a positive integer number of samples (e.g. 200)")
    if not (real_number(noise_std, "noise_std") >= 0 and real_number(past_std, "past_std") >= 0):
        raise ModelError(f"noise_std and past_std must be finite and >= 0, got {noise_std}, {past_std}")
    plant = flexible_transmission()
    rng = np.random.default_rng(seed)
    u = rng.standard_normal(int(T))
    y = simulate(plant, u) + noise_std * rng.standard_normal(int(T))
    past_u = past_std * rng.standard_normal(PAST)
    return DeePCAttack(plant, u, y, past_u, simulate(plant, past_u), Budget(eps, norm), objective, t_ini, horizon,
                       lambda_g=lambda_g, lambda_y=lambda_y, u_max=u_max)
