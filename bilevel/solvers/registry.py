"""Method registry and the `solve` dispatcher: names map to functions, callables plug in directly."""

from __future__ import annotations

import contextlib
import time
from typing import Any, Callable

from ..certificate import DEFAULT_TOL
from ..errors import ModelError
from ..model import BilevelProblem
from ..threads import single_threaded
from ..result import BilevelResult
from .base import MethodRun, Prepared, finalize, prepare
from .block_exact import solve_block_exact
from .global_method import solve_global
from .hypergradient import solve_hypergradient
from .ipopt import solve_ipopt
from .relaxation import solve_relaxation

Method = Callable[..., MethodRun]
SMALL_LOWER = 256
"""Lower levels with at most this many variables are solved with one BLAS thread."""

METHODS: dict[str, Method] = {
    "ipopt": solve_ipopt,
    "hypergradient": solve_hypergradient,
    "relaxation": solve_relaxation,
    "block-exact": solve_block_exact,
    "global": solve_global,
}
"""Registered methods: name -> function(prepared, **options) -> MethodRun."""


def register_method(name: str, method: Method) -> None:
    """Make `method` available as solve(..., method=name)."""
    METHODS[name.lower()] = method


def solve(problem: BilevelProblem, method: str | Method = "ipopt", certificate_tol: float = DEFAULT_TOL,
          **options: Any) -> BilevelResult:
    """Solve a bilevel problem with a registered method name or a callable(prepared, **options) -> MethodRun."""
    if callable(method):
        fn, name = method, getattr(method, "__name__", "custom")
    else:
        name = str(method).lower()
        if name not in METHODS:
            raise ModelError(f"unknown method {method!r}; registered methods: {', '.join(sorted(METHODS))}")
        fn = METHODS[name]
    t0 = time.perf_counter()
    prep: Prepared = prepare(problem)
    small = prep.canon.lower.n_y <= SMALL_LOWER  # dense algebra of lower-level size: one BLAS thread is faster
    with single_threaded() if small else contextlib.nullcontext():
        run = fn(prep, **options)
        return finalize(prep, run, name, time.perf_counter() - t0, certificate_tol)
