"""Method registry and the `solve` dispatcher: names map to functions, callables plug in directly."""

from __future__ import annotations

import time
from typing import Any, Callable

from ..certificate import DEFAULT_TOL
from ..errors import ModelError
from ..model import BilevelProblem
from ..result import BilevelResult
from .base import MethodRun, Prepared, finalize, prepare
from .global_method import solve_global
from .hypergradient import solve_hypergradient
from .ipopt import solve_ipopt
from .relaxation import solve_relaxation

Method = Callable[..., MethodRun]

METHODS: dict[str, Method] = {
    "ipopt": solve_ipopt,
    "hypergradient": solve_hypergradient,
    "relaxation": solve_relaxation,
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
    run = fn(prep, **options)
    return finalize(prep, run, name, time.perf_counter() - t0, certificate_tol)
