"""The lower level in canonical form, min_y f(x, y) s.t. g <= 0, h = 0, M_k >= 0, and its KKT system."""

from __future__ import annotations

from abc import ABC, abstractmethod
from dataclasses import dataclass, field
from functools import cached_property
from typing import ClassVar

import casadi as ca
import numpy as np

from ..errors import InvalidData
from ..parameters import ParameterSet
from ..vech import symmetric_from_vech


def psd_violation(m: np.ndarray) -> float:
    """How far the symmetric part of m is from PSD: max(-lambda_min, 0), 0 for an empty matrix."""
    return max(-float(np.linalg.eigvalsh(0.5 * (m + m.T)).min()), 0.0) if m.size else 0.0


@dataclass
class LowerSolution:
    """A lower-level solution at a fixed upper point, with multipliers in our sign convention.

    Convention: L = f + lam' g + mu' h - sum_k <Z_k, M_k>, lam >= 0, Z_k >= 0.
    """

    y: np.ndarray
    objective: float
    lam: np.ndarray
    mu: np.ndarray
    Z: list[np.ndarray] = field(default_factory=list)
    status: str = "optimal"
    solver: str = ""


@dataclass(frozen=True)
class KKTSystem:
    """Symbolic KKT conditions of the lower level: multiplier symbols and the stationarity residual."""

    lam: ca.SX
    mu: ca.SX
    Z: tuple[ca.SX, ...]
    Z_vech: tuple[ca.SX, ...]
    stationarity: ca.SX


@dataclass
class LowerLevel(ABC):
    """min_y f(x, y) s.t. g(x, y) <= 0, h(x, y) = 0, M_k(x, y) >= 0 (PSD), convex in y for fixed x.

    Subclasses state their kind and solve themselves independently of the single-level reduction.
    """

    x: ca.SX
    y: ca.SX
    f: ca.SX
    g: ca.SX
    h: ca.SX
    psd: list[ca.SX]
    g_names: list[str]
    h_names: list[str]
    psd_names: list[str]
    hess_f: ca.SX | None = field(default=None, repr=False)
    """d^2 f / dy^2, symbolic; computed here unless the classification already did (one AD pass on f)."""
    params: ParameterSet = field(default_factory=ParameterSet, repr=False)
    """The problem's parameters (data symbols in f, g, h, M_k): functions built here read their current values."""
    kind: ClassVar[str] = "nlp"

    def __post_init__(self) -> None:
        if self.hess_f is None:
            self.hess_f = ca.hessian(self.f, self.y)[0]
        self._eval = self.params.function("lower_eval", [self.x, self.y], [self.f, self.g, self.h, *self.psd])
        jac_psd = [ca.jacobian(ca.vec(m), self.y) for m in self.psd]
        self._derivs = self.params.function("lower_derivs", [self.x, self.y],
                                            [ca.gradient(self.f, self.y), ca.jacobian(self.g, self.y),
                                             ca.jacobian(self.h, self.y), *jac_psd])
        self._hess = self.params.function("lower_hess", [self.x, self.y], [self.hess_f])

    @cached_property
    def fixed(self) -> bool:
        """True when f, g, h and the LMIs do not depend on x: y*(x) is then one point, solved once."""
        return not ca.depends_on(ca.vertcat(self.f, self.g, self.h, *[ca.vec(m) for m in self.psd]), self.x)

    @property
    def n_x(self) -> int:
        return int(self.x.numel())

    @property
    def n_y(self) -> int:
        return int(self.y.numel())

    def kkt(self) -> KKTSystem:
        """Multiplier symbols and stationarity grad_y f + J_g' lam + J_h' mu - grad_y sum <Z_k, M_k>."""
        lam = ca.SX.sym("lam", self.g.numel())
        mu = ca.SX.sym("mu", self.h.numel())
        lagrangian = self.f + ca.dot(lam, self.g) + ca.dot(mu, self.h)
        zs, zv = [], []
        for k, m in enumerate(self.psd):
            z, v = symmetric_from_vech(f"Z{k}", m.size1())
            zs.append(z)
            zv.append(v)
            lagrangian -= ca.trace(ca.mtimes(z, m))
        return KKTSystem(lam, mu, tuple(zs), tuple(zv), ca.gradient(lagrangian, self.y))

    def evaluate(self, x: np.ndarray, y: np.ndarray) -> tuple[float, np.ndarray, np.ndarray, list[np.ndarray]]:
        """f, g, h and the LMI matrices at (x, y)."""
        out = self._eval(x, y)
        return (float(out[0]), np.asarray(out[1]).ravel(), np.asarray(out[2]).ravel(),
                [np.asarray(m) for m in out[3:]])

    def derivatives(self, x: np.ndarray, y: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, list[np.ndarray]]:
        """grad_y f, J_g, J_h (rows by constraint) and d vec(M_k) / dy at (x, y)."""
        out = self._derivs(x, y)
        return (np.asarray(out[0]).ravel(), np.asarray(out[1]).reshape(-1, self.n_y),
                np.asarray(out[2]).reshape(-1, self.n_y), [np.asarray(j) for j in out[3:]])

    def hessian(self, x: np.ndarray, y: np.ndarray) -> np.ndarray:
        """Hessian of f in y at (x, y)."""
        return np.asarray(self._hess(x, y))

    def stationarity(self, x: np.ndarray, y: np.ndarray, lam: np.ndarray, mu: np.ndarray,
                     Z: list[np.ndarray]) -> tuple[np.ndarray, np.ndarray]:
        """The Lagrangian gradient in y at (x, y, multipliers), and grad_y f (for scaling)."""
        out = self._derivs(x, y)
        grad_f = np.asarray(out[0]).ravel()
        res = grad_f + np.asarray(out[1]).reshape(-1, self.n_y).T @ lam + np.asarray(out[2]).reshape(-1, self.n_y).T @ mu
        for jac, z in zip(out[3:], Z):
            res = res - np.asarray(jac).T @ np.asarray(z).reshape(-1, order="F")
        return res, grad_f

    def check_point(self, x: np.ndarray) -> np.ndarray:
        """Validate an upper point (shape, finiteness) and return it as a float vector."""
        x = np.asarray(x, dtype=float).ravel()
        if x.shape != (self.n_x,):
            raise InvalidData(f"upper point has {x.size} entries, the problem has {self.n_x} upper variables")
        if not np.all(np.isfinite(x)):
            raise InvalidData("upper point contains NaN or inf")
        return x

    @abstractmethod
    def solve(self, x: np.ndarray) -> LowerSolution:
        """Solve the lower level at upper point x, independently of the reduction (raises on failure)."""
