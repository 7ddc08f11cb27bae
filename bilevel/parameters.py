"""Model parameters: data symbols whose values are re-set without rebuilding the problem (like CasADi Opti's
parameter / set_value).

Every CasADi function the framework builds from a problem's expressions takes the parameters as a last input
and is called with their current values (`ParameterSet.function`), so a solve after `set_value` reuses the
canonical form, the lower level's classification, the reduction and the compiled functions of the last one.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Sequence

import casadi as ca
import numpy as np

from .errors import InvalidData, ModelError


@dataclass
class Parameter:
    """A declared parameter: its symbol, shape and current value (flattened column-major; None until set)."""

    name: str
    sym: ca.SX
    value: np.ndarray | None = None

    @property
    def size(self) -> int:
        return int(self.sym.numel())


class BoundFunction:
    """A CasADi function whose last input is the parameter vector, called with the parameters' current values."""

    def __init__(self, fun: ca.Function, params: "ParameterSet") -> None:
        self.fun, self.params = fun, params

    def __call__(self, *args: Any) -> Any:
        return self.fun(*args, self.params.value)

    def __getattr__(self, name: str) -> Any:  # sparsity_out, sx_in, n_out, ... of the wrapped function
        return getattr(self.fun, name)


class ParameterSet:
    """The parameters of a problem: one flat symbol, one flat current value, and functions that read it."""

    def __init__(self) -> None:
        self.items: list[Parameter] = []
        self.revision = 0
        """Incremented by every set_value: caches of value-dependent quantities compare it."""
        self._flat: np.ndarray | None = None

    def __len__(self) -> int:
        return len(self.items)

    @property
    def sym(self) -> ca.SX:
        """All parameter symbols, flattened column-major in declaration order (0 x 1 without parameters)."""
        return ca.vertcat(*[ca.vec(p.sym) for p in self.items]) if self.items else ca.SX(0, 1)

    @property
    def value(self) -> np.ndarray:
        """The current values in the order of `sym`; ModelError if a parameter has none."""
        if self._flat is None:
            missing = [p.name for p in self.items if p.value is None]
            if missing:
                raise ModelError(f"parameter(s) {', '.join(map(repr, missing))} have no value; call "
                                 "problem.set_value(name, value) before solving")
            self._flat = np.concatenate([p.value for p in self.items]) if self.items else np.zeros(0)
        return self._flat

    def add(self, name: str, sym: ca.SX, value: Any = None) -> Parameter:
        """Register a parameter symbol (with an optional first value)."""
        param = Parameter(name, sym)
        self.items.append(param)
        if value is not None:
            self.set(name, value)
        return param

    def set(self, name: str, value: Any) -> None:
        """Give parameter `name` a new value (its shape, or flattened column-major); finite numbers only."""
        param = next((p for p in self.items if p.name == name), None)
        if param is None:
            names = ", ".join(p.name for p in self.items) or "none"
            raise ModelError(f"no parameter named {name!r}; parameters: {names}")
        try:
            arr = np.asarray(value, dtype=float)
        except (TypeError, ValueError):
            raise ModelError(f"value of parameter {name!r} must be numbers, got {type(value).__name__}") from None
        shape = (int(param.sym.size1()), int(param.sym.size2()))
        if arr.shape not in (shape, (param.size,)) and not (arr.ndim == 0 and param.size == 1):
            raise ModelError(f"value of parameter {name!r} has shape {arr.shape}; the parameter has shape {shape} "
                             f"(or pass {param.size} values flattened column-major)")
        if not np.all(np.isfinite(arr)):
            raise InvalidData(f"value of parameter {name!r} contains NaN or inf; clean or impute the data first")
        param.value = arr.reshape(-1, order="F").copy()
        self._flat = None
        self.revision += 1

    def function(self, name: str, inputs: Sequence[ca.SX], outputs: Sequence[ca.SX]) -> ca.Function | BoundFunction:
        """ca.Function(name, inputs, outputs), reading the parameters' current values when there are any."""
        if not self.items:
            return ca.Function(name, list(inputs), list(outputs))
        return BoundFunction(ca.Function(name, [*inputs, self.sym], list(outputs)), self)

    def substitute(self, expr: ca.SX) -> ca.SX:
        """expr with the parameters replaced by their current values."""
        return ca.substitute(expr, self.sym, ca.DM(self.value)) if self.items else expr
