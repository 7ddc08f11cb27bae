"""Every attack's result: the engine's solve of the attack's problem (its finalize: certificate, probe), with the
instance's quantities in stats (the true closed loop)."""

from __future__ import annotations

import dataclasses
import time
from typing import Any, Callable

from ..errors import ModelError, SolverFailed
from ..model import BilevelProblem
from ..result import BilevelResult
from ..solvers.registry import solve


def attack_result(problem: BilevelProblem, method: Any, name: str | None, stats: Callable[[BilevelResult], dict],
                  started: float, **options: Any) -> BilevelResult:
    """solve(problem, method, **options), the options given as None left out, as attack `name` (None: the method's
    own), its stats extended by stats(result) and its wall time counted from `started` (perf_counter: the instance's
    set-up included); SolverFailed where the method found no point to certify."""
    result = solve(problem, method=method, **{k: v for k, v in options.items() if v is not None})
    if result.certificate is None:
        raise SolverFailed(f"{name or result.method} attack: {result.status.value}: {result.message}", result=result)
    return dataclasses.replace(result, method=name or result.method, wall_time=time.perf_counter() - started,
                               stats={**result.stats, **stats(result)})


def attack_stat(result: BilevelResult, key: str) -> Any:
    """stats[key] of an attack's result; ModelError if `result` is not an attack's BilevelResult."""
    if not isinstance(result, BilevelResult) or key not in result.stats:
        raise ModelError(f"expected the BilevelResult of a VRFT or Willems attack (with stats[{key!r}]), got "
                         f"{type(result).__name__}; pass what an attack function returned")
    return result.stats[key]


def unstable(result: BilevelResult) -> bool:
    """The true plant with the learner's poisoned controller has a pole on or outside the unit circle
    (stats['spectral_radius'], which every VRFT and Willems attack reports)."""
    return attack_stat(result, "spectral_radius") >= 1.0
