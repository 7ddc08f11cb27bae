"""Attack budgets as in the paper: ||a||_q <= eps * ||signal||_q, at most floor(rho N) samples changed."""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Literal

import numpy as np

from ..errors import ModelError
from ..real_data import real_number
from ..solvers.engine.projections import NormBall, Projection, SparseNormBall

Norm = Literal["l2", "linf", "l1"]
_ORDER = {"l2": 2, "linf": np.inf, "l1": 1}


@dataclass(frozen=True)
class Budget:
    """Relative budget eps in norm q, optional sparsity fraction rho (the paper's (delta, rho))."""

    eps: float
    norm: Norm = "l2"
    rho: float | None = None

    def __post_init__(self) -> None:
        if real_number(self.eps, "budget eps") < 0:
            raise ModelError(f"budget eps must be finite and >= 0, got {self.eps}")
        if self.norm not in _ORDER:
            raise ModelError(f"budget norm {self.norm!r} is not one of {', '.join(_ORDER)}")
        if self.rho is not None and not 0.0 <= real_number(self.rho, "sparsity fraction rho") <= 1.0:
            raise ModelError(f"sparsity fraction rho must be in [0, 1], got {self.rho}")

    @classmethod
    def of(cls, value: "Budget | float") -> "Budget":
        """`value` as a Budget: a plain number eps means Budget(eps), the l2 budget eps * ||signal||_2."""
        if isinstance(value, Budget):
            return value
        if isinstance(value, (int, float, np.integer, np.floating)) and not isinstance(value, bool):
            return cls(float(value))
        raise ModelError(f"a budget must be a Budget or a number eps (meaning Budget(eps), l2), got "
                         f"{type(value).__name__} {value!r}; e.g. Budget(0.1, norm='linf', rho=0.2)")

    @property
    def order(self) -> float:
        return float(_ORDER[self.norm])

    def radius(self, signal: np.ndarray) -> float:
        """delta = eps * ||signal||_q."""
        return float(self.eps * np.linalg.norm(np.asarray(signal, dtype=float), self.order))

    def max_changed(self, n: int) -> int | None:
        """floor(rho N), or None without a sparsity constraint."""
        return None if self.rho is None else int(math.floor(self.rho * n))

    def projection(self, signal: np.ndarray) -> Projection:
        """Euclidean projection onto this budget's feasible set for attacks on `signal`."""
        k = self.max_changed(np.size(signal))
        if k is None:
            return NormBall(self.radius(signal), self.order)
        return SparseNormBall(self.radius(signal), k, self.order)
