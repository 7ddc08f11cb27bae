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
from .real_data import refuse_complex


@dataclass
class Parameter:
    """A declared parameter: its symbol, shape and current value (flattened column-major; None until set)."""

    name: str
    sym: ca.SX
    value: np.ndarray | None = None

    @property
    def size(self) -> int:
        return int(self.sym.numel())


def scalar(value: Any) -> float:
    """The number in a 1 x 1 output (numpy array or CasADi DM)."""
    return float(np.asarray(value, dtype=float).reshape(-1)[0])


class CompiledFunction:
    """A CasADi function called on numpy arrays through preallocated buffers (CasADi's FunctionBuffer), with the
    parameters' current values as its last input when it has parameters.

    Numeric calls return 2-D numpy arrays of the outputs' shapes (read scalars with `scalar`), as np.asarray of the
    ca.Function's results would, without its DM conversions (about 85 us per 1000 entries each way, which made
    the conversions cost ten times the evaluation on the VRFT problems). Symbolic arguments go to the ca.Function.
    """

    def __init__(self, fun: ca.Function, params: "ParameterSet | None" = None) -> None:
        self.fun, self.params = fun, params
        n_args = fun.n_in() - (1 if params is not None else 0)
        self._sizes = [fun.nnz_in(i) for i in range(fun.n_in())]
        self._dense_in = all(fun.sparsity_in(i).is_dense() for i in range(fun.n_in()))
        self._buffer, self._eval = fun.buffer()
        self._args = [np.zeros(n) for n in self._sizes[:n_args]]  # the parameters' input reads params.value in place
        for i, arg in enumerate(self._args):
            self._buffer.set_arg(i, memoryview(arg))
        self._n_args, self._revision = n_args, -1
        self._outs = []
        for k in range(fun.n_out()):
            sp = fun.sparsity_out(k)
            rows, cols = sp.get_triplet()
            index = None if sp.is_dense() else np.asarray(cols, dtype=int) * sp.size1() + np.asarray(rows, dtype=int)
            self._outs.append((sp.nnz(), (sp.size1(), sp.size2()), index))

    def __call__(self, *args: Any) -> Any:
        if (len(args) != self._n_args or not self._dense_in
                or any(isinstance(a, (ca.SX, ca.MX, ca.DM)) for a in args)):
            return self.fun(*args, *([self.params.value] if self.params is not None else []))
        for buf, arg in zip(self._args, args):
            flat = np.asarray(arg, dtype=float).ravel(order="F")
            if flat.size != buf.size:  # let CasADi broadcast or name the mismatch
                return self.fun(*args, *([self.params.value] if self.params is not None else []))
            buf[:] = flat
        if self.params is not None and self._revision != self.params.revision:
            self._values = self.params.value  # kept alive while the buffer points at it
            self._buffer.set_arg(self._n_args, memoryview(self._values))
            self._revision = self.params.revision
        nonzeros = [np.empty(n) for n, _, _ in self._outs]
        for k, nz in enumerate(nonzeros):
            self._buffer.set_res(k, memoryview(nz))
        self._eval()
        results = []
        for nz, (_, shape, index) in zip(nonzeros, self._outs):
            if index is not None:
                dense = np.zeros(shape[0] * shape[1])
                dense[index] = nz
                nz = dense
            results.append(nz.reshape(shape, order="F"))
        return results[0] if len(results) == 1 else results

    def __getattr__(self, name: str) -> Any:  # sparsity_out, sx_in, n_out, ... of the wrapped function
        return getattr(self.fun, name)


class ValueAndJacobian:
    """(inputs) -> (e, de/d inputs[wrt]) of a vector expression e, numerically, reading the parameters' current values:
    the Jacobian's rows by one reverse sweep each (a vector-Jacobian product mapped over the unit seeds). Exact like a
    symbolic Jacobian, which costs far more to build on long expressions (an SDP's LMI, M = A + B V S^-1 of its
    variables: 5-20x), though slower to evaluate."""

    def __init__(self, params: "ParameterSet", name: str, inputs: Sequence[ca.SX], expr: ca.SX, wrt: int) -> None:
        n = int(expr.numel())
        seed = ca.SX.sym("seed", n)
        args = [*inputs, seed] + ([params.sym] if len(params) else [])
        vjp = ca.Function(f"{name}_vjp", args, [ca.jtimes(expr, inputs[wrt], seed, True)])
        rows = vjp.map(f"{name}_rows", "serial", n, [i for i in range(len(args)) if i != len(inputs)], [])
        self._value = params.function(name, inputs, [expr])
        self._rows = CompiledFunction(rows, params if len(params) else None)
        self._seeds = np.eye(n)

    def value(self, *args: np.ndarray) -> np.ndarray:
        """e (a column) at args, without its Jacobian."""
        return np.asarray(self._value(*args), dtype=float)

    def __call__(self, *args: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """e (a column) and de/d inputs[wrt] (rows by entry of e; column-major, as CompiledFunction returns matrices:
        BLAS then sums in the same order) at args."""
        return np.asarray(self._value(*args), dtype=float), np.asfortranarray(self._rows(*args, self._seeds).T)


class ParameterSet:
    """The parameters of a problem: one flat symbol, one flat current value, and functions that read it."""

    def __init__(self) -> None:
        self.items: list[Parameter] = []
        self.revision = 0
        """Incremented by every set_value: caches of value-dependent quantities compare it."""
        self._flat: np.ndarray | None = None
        self._sym: ca.SX | None = None

    def __len__(self) -> int:
        return len(self.items)

    @property
    def sym(self) -> ca.SX:
        """All parameter symbols, flattened column-major in declaration order (0 x 1 without parameters)."""
        if self._sym is None:
            self._sym = ca.vertcat(*[ca.vec(p.sym) for p in self.items]) if self.items else ca.SX(0, 1)
        return self._sym

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
        self._sym = self._flat = None
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
            raw = np.asarray(value)
        except (TypeError, ValueError):  # e.g. a ragged list
            raw = np.asarray(None)
        refuse_complex(raw, f"value of parameter {name!r}")
        if raw.dtype.kind not in "biuf":
            raise InvalidData(f"value of parameter {name!r} must be real numbers, got {type(value).__name__}"
                              f"{f' of dtype {raw.dtype}' if raw.dtype.kind != 'O' else ''}; pass a float array")
        arr = raw.astype(float)
        shape = (int(param.sym.size1()), int(param.sym.size2()))
        if arr.shape not in (shape, (param.size,)) and not (arr.ndim == 0 and param.size == 1):
            raise ModelError(f"value of parameter {name!r} has shape {arr.shape}; the parameter has shape {shape} "
                             f"(or pass {param.size} values flattened column-major)")
        if not np.all(np.isfinite(arr)):
            raise InvalidData(f"value of parameter {name!r} contains NaN or inf; clean or impute the data first")
        param.value = arr.reshape(-1, order="F").copy()
        self._flat = None
        self.revision += 1

    def function(self, name: str, inputs: Sequence[ca.SX], outputs: Sequence[ca.SX]) -> CompiledFunction:
        """ca.Function(name, inputs, outputs), called through buffers, reading the parameters' current values."""
        if not self.items:
            return CompiledFunction(ca.Function(name, list(inputs), list(outputs)))
        return CompiledFunction(ca.Function(name, [*inputs, self.sym], list(outputs)), self)

    def substitute(self, expr: ca.SX) -> ca.SX:
        """expr with the parameters replaced by their current values."""
        return ca.substitute(expr, self.sym, ca.DM(self.value)) if self.items else expr
