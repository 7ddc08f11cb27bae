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
from typing import Any, Callable, Hashable, Mapping, Sequence

import numpy as np

from ..defaults import param
from ..errors import ModelError
from ..model import BilevelProblem
from ..result import BilevelResult
from ..threads import single_threaded
from .engine.options import check_common_options
from .engine.prepared import MethodRun, Prepared, prepare
from .engine.structure import budget_scale
from .registry import METHODS, solve
from .verdict.batch_probe import ProbeInstance, ProbeParts, covered, probe_many
from .verdict.finalize import finalize
from .verdict.probe import ProbeOutcome

Value = Mapping[str, Any] | Callable[[BilevelProblem], None]
"""One instance: parameter values by name (set_value each), or a function that loads the instance into the problem
(its parameters, suggested starts)."""


@dataclass(frozen=True)
class BatchMethod:
    """A method's batched form: gather(prepared, options) -> what one loaded instance contributes (None: that
    instance runs alone, through `solve`); run(gathered, options) -> one MethodRun per gathered instance, computed
    together; probe_parts(gathered, runs), where given, what the batched local probe needs (ProbeParts), so that the
    verdicts' probes run together too."""

    gather: Callable[[Prepared, dict[str, Any]], Any]
    run: Callable[[list[Any], dict[str, Any]], list[MethodRun]]
    probe_parts: Callable[[list[Any], list[MethodRun]], ProbeParts] | None = None


BATCH_METHODS: dict[Callable[..., MethodRun], BatchMethod] = {}
"""Method function -> its batched form (register_batch)."""


def register_batch(method: Callable[..., MethodRun], batched: BatchMethod) -> None:
    """Give method function `method` a batched form, which solve_many runs on batches of defaults["batch.min_size"]
    instances or more."""
    if not callable(method) or not isinstance(batched, BatchMethod):
        raise ModelError("register_batch needs a method function and a BatchMethod(gather, run)")
    BATCH_METHODS[method] = batched


def in_groups(items: Sequence[Any], key: Callable[[Any], Hashable],
              run: Callable[[list[Any]], Sequence[Any]]) -> list[Any]:
    """run(part) on the items sharing key(item), at most defaults["batch.max_rows"] of them at a time (consecutive
    batched runs), groups in order of first appearance; one result per item, in the items' order."""
    groups: dict[Hashable, list[int]] = {}
    for i, item in enumerate(items):
        groups.setdefault(key(item), []).append(i)
    out: list[Any] = [None] * len(items)
    size = int(param("batch.max_rows"))
    for idx in groups.values():
        for s in range(0, len(idx), size):
            part = idx[s: s + size]
            for i, r in zip(part, run([items[i] for i in part])):
                out[i] = r
    return out


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
    name = str(method).lower() if isinstance(method, str) else getattr(method, "__name__", "custom")
    check_common_options(options, certificate_tol)
    t0 = time.perf_counter()
    gathered: list[Any] = []
    sets: list[tuple[Any, Any, list]] = []  # each instance's feasible set, scale and balls, for the batched probe
    for value, e in zip(values, each):
        load(problem, value)
        prep = prepare(problem)
        gathered.append(batched.gather(prep, {**options, **e}))
        sets.append((prep.projection, budget_scale(prep.canon, prep.balls), prep.balls))
    together = [i for i, g in enumerate(gathered) if g is not None]
    small = prep.canon.lower.n_y <= param("solvers.small_lower")
    with single_threaded() if small else contextlib.nullcontext():
        runs = dict(zip(together, batched.run([gathered[i] for i in together], options) if together else []))
        probed = _probe(prep, batched, [gathered[i] for i in together], [runs[i] for i in together],
                        [sets[i] for i in together])
        probed = dict(zip(together, probed))
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
            result = finalize(prep, runs[i], name, share, certificate_tol, probed[i])
            results.append(dataclasses.replace(result, wall_time=share + time.perf_counter() - t1))
    return results


def _alone(problem: BilevelProblem, value: Value, method: Any, certificate_tol: float | None,
           options: dict[str, Any]) -> BilevelResult:
    load(problem, value)
    return solve(problem, method, certificate_tol, **options)


def _probe(prep: Prepared, batched: BatchMethod, gathered: list[Any], runs: list[MethodRun],
           sets: list[tuple[Any, Any, list]]) -> list[ProbeOutcome | None]:
    """The local probe's outcome at each run's point, found together (bilevel.solvers.verdict.batch_probe) where the
    method gives ProbeParts and the problem is in the batched probe's class; None where finalize probes itself."""
    canon = prep.canon
    if batched.probe_parts is None or not runs or not covered(prep.balls, int(canon.G.numel()), int(canon.H.numel()),
                                                               int(canon.x.numel())):
        return [None] * len(runs)
    parts = batched.probe_parts(gathered, runs)
    have = [i for i, r in enumerate(runs) if r.w is not None and r.feasible_set is None]
    if not have:
        return [None] * len(runs)
    points = [prep.point(runs[i].w) for i in have]
    size = int(param("batch.chunk"))
    F = np.concatenate([parts.objective(np.array(have[s: s + size]), np.array([p.x for p in points[s: s + size]]),
                                        np.array([p.y for p in points[s: s + size]]))
                        for s in range(0, len(have), size)])
    free = not np.isfinite(canon.x_lb).any() and not np.isfinite(canon.x_ub).any()
    outcomes = probe_many([ProbeInstance(p.x, float(f), *sets[i]) for i, p, f in zip(have, points, F)],
                          ProbeParts(lambda idx, X: parts.solve(np.array(have)[idx], X),
                                     lambda idx, X, Y: parts.objective(np.array(have)[idx], X, Y),
                                     lambda j: parts.gradient(have[j])), balls_only=free)
    out: list[ProbeOutcome | None] = [None] * len(runs)
    for i, o in zip(have, outcomes):
        out[i] = o
    return out
