"""Many instances of one declaration at once: solve_many(problem, values, method) loads each value (parameter values,
or a loader) into the declared problem and runs a method on all of them; a method with a batched form
(register_batch) runs every instance in one batched call, the others (and batches below defaults["batch.min_size"])
run one at a time through `solve`. Each instance gets its own result (status, certificate, probe) from the engine's
verdict, as `solve` gives it.
"""

from __future__ import annotations

import contextlib
import dataclasses
import time
from dataclasses import dataclass
from typing import Any, Callable, Mapping, Sequence

from ..defaults import param
from ..errors import ModelError
from ..model import BilevelProblem
from ..result import BilevelResult
from ..threads import single_threaded
from .engine.options import check_common_options
from .engine.prepared import MethodRun, Prepared, prepare
from .registry import METHODS, solve
from .verdict.finalize import finalize

Value = Mapping[str, Any] | Callable[[BilevelProblem], None]
"""One instance: parameter values by name (set_value each), or a function that loads the instance into the problem
(its parameters, suggested starts)."""


@dataclass(frozen=True)
class BatchMethod:
    """A method's batched form: gather(prepared, options) -> what one loaded instance contributes (None: that
    instance runs alone, through `solve`); run(gathered, options) -> one MethodRun per gathered instance, computed
    together."""

    gather: Callable[[Prepared, dict[str, Any]], Any]
    run: Callable[[list[Any], dict[str, Any]], list[MethodRun]]


BATCH_METHODS: dict[Callable[..., MethodRun], BatchMethod] = {}
"""Method function -> its batched form (register_batch)."""


def register_batch(method: Callable[..., MethodRun], batched: BatchMethod) -> None:
    """Give method function `method` a batched form, which solve_many runs on batches of defaults["batch.min_size"]
    instances or more."""
    if not callable(method) or not isinstance(batched, BatchMethod):
        raise ModelError("register_batch needs a method function and a BatchMethod(gather, run)")
    BATCH_METHODS[method] = batched


def load(problem: BilevelProblem, value: Value) -> None:
    """Load one instance into the declared problem: set_value for each parameter of a mapping, or call a loader."""
    if callable(value):
        value(problem)
    elif isinstance(value, Mapping):
        for name, v in value.items():
            problem.set_value(name, v)
    else:
        raise ModelError(f"solve_many: an instance is a mapping of parameter values or a loader function(problem), "
                         f"got {type(value).__name__}")


def solve_many(problem: BilevelProblem, values: Sequence[Value], method: str | Callable[..., MethodRun],
               certificate_tol: float | None = None, each: Sequence[Mapping[str, Any]] | None = None,
               **options: Any) -> list[BilevelResult]:
    """solve(problem, method, certificate_tol, **options) at each instance of `values` (module docstring), with
    each[i] (e.g. a seed) over the options for instance i; results in the order of `values`. A batched run's wall
    time is shared equally among its instances, each adding its own verdict's."""
    values = list(values)
    each = [{}] * len(values) if each is None else [dict(e) for e in each]
    if len(each) != len(values):
        raise ModelError(f"solve_many: {len(each)} per-instance option sets for {len(values)} instances")
    fn = method if callable(method) else METHODS.get(str(method).lower())
    batched = BATCH_METHODS.get(fn) if fn is not None else None
    if batched is None or len(values) < param("batch.min_size"):
        return [_alone(problem, v, method, certificate_tol, {**options, **e}) for v, e in zip(values, each)]
    name = method if isinstance(method, str) else getattr(method, "__name__", "custom")
    check_common_options(options, certificate_tol)
    t0 = time.perf_counter()
    gathered: list[Any] = []
    for value, e in zip(values, each):
        load(problem, value)
        gathered.append(batched.gather(prepare(problem), {**options, **e}))
    together = [i for i, g in enumerate(gathered) if g is not None]
    prep = prepare(problem)
    small = prep.canon.lower.n_y <= param("solvers.small_lower")
    with single_threaded() if small else contextlib.nullcontext():
        runs = dict(zip(together, batched.run([gathered[i] for i in together], options) if together else []))
        share = (time.perf_counter() - t0) / max(len(together), 1)
        results = []
        for i, (value, e) in enumerate(zip(values, each)):
            if i not in runs:
                results.append(_alone(problem, value, method, certificate_tol, {**options, **e}))
                continue
            t1 = time.perf_counter()
            load(problem, value)
            prep = prepare(problem)
            prep.runs += 1
            result = finalize(prep, runs[i], name, share, certificate_tol)
            results.append(dataclasses.replace(result, wall_time=share + time.perf_counter() - t1))
    return results


def _alone(problem: BilevelProblem, value: Value, method: Any, certificate_tol: float | None,
           options: dict[str, Any]) -> BilevelResult:
    load(problem, value)
    return solve(problem, method, certificate_tol, **options)
