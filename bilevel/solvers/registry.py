"""Method registry and the `solve` dispatcher: names map to functions, callables plug in directly."""

from __future__ import annotations

import contextlib
import dataclasses
import inspect
import time
from typing import Any, Callable

import casadi as ca
import numpy as np

from ..defaults import param
from ..errors import ModelError, did_you_mean
from ..model import BilevelProblem
from ..threads import single_threaded
from ..result import BilevelResult, Status
from .engine.prepared import MethodRun, Prepared, options_of, prepare
from .verdict.finalize import finalize
from .evolution import solve_evolution
from .globalopt.form import linear_mpcc
from .globalopt.method import solve_global
from .globalopt.scip import scip_available
from .hypergradient import solve_block_exact, solve_hypergradient
from .ipopt import solve_ipopt
from .engine.options import check_common_options
from .reduced import solve_reduced
from .relaxation import solve_relaxation

Method = Callable[..., MethodRun]

METHODS_VERSION = "methods-9"
"""Part of every `bilevel compare` task, so a resumed comparison never reuses a row of an older method: bump it when a
registered method changes its answers for the same call (methods-2: hypergradient takes the exact block by default;
methods-3: the structured vrft-targeted attack runs to convergence; methods-4: SDP lower levels get the engine's
minimum-norm selection; methods-5: exact-block ties broken towards the current point, KKT answers projected onto the
declared box and balls, statuses no longer `solved` where lower-level convexity or local optimality is not shown;
methods-6: the conditioning start of least-squares learners, differential-evolution's budget by dimension, time
limits; methods-7: the structured VRFT attacks go through the engine's finalize, so their statuses come from its probe,
and least squares from 10,000 Hessian terms are solved in residual form; methods-8: SDP lower levels are solved through
Clarabel's own interface and Newton-polished, the Willems attacks go through the engine's finalize, and the structured
VRFT attacks run on the engine's multistart ascent from its start sequence (the joint attack starts at the
conditioning start, not at zero poisoning) and attack the registry's instance (N = 64 by default) in a comparison;
methods-9: method `reduced`, which auto runs where upper constraints read a least-squares lower solution)."""

METHODS: dict[str, Method] = {
    "ipopt": solve_ipopt,
    "hypergradient": solve_hypergradient,
    "relaxation": solve_relaxation,
    "block-exact": solve_block_exact,
    "global": solve_global,
    "differential-evolution": solve_evolution,
    "reduced": solve_reduced,
}
"""Registered methods: name -> function(prepared, **options) -> MethodRun."""


BUILTIN_METHODS = frozenset(METHODS)
"""The methods this package registers: register_method replaces one only with replace=True."""


def register_method(name: str, method: Method, *, replace: bool = False) -> None:
    """Make `method` available as solve(..., method=name); replacing a registered name needs replace=True."""
    if not isinstance(name, str) or not name.strip():
        raise ModelError(f"register_method: name {name!r} must be a non-empty string")
    if not callable(method):
        raise ModelError(f"register_method: method for {name!r} is a {type(method).__name__}, not callable; pass a "
                         "function(prepared, **options) -> MethodRun")
    key = name.lower()
    if key in METHODS and not replace:
        what = "the built-in method" if key in BUILTIN_METHODS else "the method registered as"
        raise ModelError(f"register_method: {what} {key!r} is already registered (for every solve in this process); "
                         "choose another name, or pass replace=True to replace it")
    METHODS[key] = method


AUTO = "auto"
"""The default method name: a registered method chosen by the problem's structure (choose_method)."""


def coupled_upper_rows(prep: Prepared) -> int:
    """The number of upper constraint rows (G <= 0, H = 0) that depend on the lower variables y."""
    canon = prep.canon
    rows = ca.vertcat(canon.G, canon.H)
    return len(set(ca.jacobian_sparsity(rows, canon.y).get_triplet()[0])) if rows.numel() else 0


def choose_method(prep: Prepared, options: dict[str, Any]) -> tuple[str, str]:
    """The method "auto" runs, and why: `reduced` where upper constraints read the solution of a least-squares lower
    level (unique and smooth in x: IPOPT over x alone keeps those rows as constraints); `hypergradient` where the
    upper objective is a numeric function of a matrix, or where the lower level is least squares (solved in closed
    form, y*(x) smooth) or does not depend on x (solved once), with at least defaults["auto.min_upper"] upper entries
    or an l_inf budget row, and no upper constraint on the lower solution; `ipopt` otherwise (constrained lower levels
    whose solution depends on x: its KKT system is solved with the upper level in one NLP). Options only one of the
    methods accepts decide for it."""
    low, n = prep.canon.lower, int(prep.canon.x.numel())
    given, hypergradient, ipopt = set(options), options_of(solve_hypergradient), options_of(solve_ipopt)
    coupled = coupled_upper_rows(prep)
    if coupled and low.closed_form and prep.canon.spectral is None and given <= options_of(solve_reduced):
        return "reduced", (f"{coupled} upper constraint(s) on the solution of a least-squares lower level (unique, "
                           "in closed form), which reduced keeps as constraints over the upper variables alone")
    if not given <= hypergradient:
        return "ipopt", f"option(s) {', '.join(sorted(given - hypergradient))} belong to ipopt"
    if not given <= ipopt:
        return "hypergradient", f"option(s) {', '.join(sorted(given - ipopt))} belong to hypergradient"
    if prep.canon.spectral is not None:
        return "hypergradient", "a numeric objective of a matrix (the KKT methods cannot use it)"
    if coupled:
        return "ipopt", (f"{coupled} upper constraint(s) on the lower solution, which ipopt keeps as constraints and "
                         "hypergradient would only penalize")
    closed = "a least-squares lower level" if low.closed_form else (
        "a lower level independent of x" if low.fixed else "")
    if closed and any(b.norm == np.inf for b in prep.balls):
        return "hypergradient", (f"{closed} and an l_inf budget (a norm_inf row), which hypergradient projects onto "
                                 "exactly and the KKT methods would see as a nonsmooth row")
    if closed and n >= (least := param("auto.min_upper")):
        return "hypergradient", f"{closed} and {n} upper entries (>= {least})"
    if closed:
        return "ipopt", f"{closed} but only {n} upper entries (< {least})"
    return "ipopt", f"a {low.kind} lower level whose solution depends on x"


GLOBAL_FIRST_OPTIONS = frozenset({"seed", "starts", "verbose", "time_limit"})
"""Options that leave auto free to try global first (every method takes them; global ignores starts and seed)."""


def global_first(prep: Prepared, options: dict[str, Any]) -> str | None:
    """Why auto tries `global` first on this problem, or None where it does not: the problem is small
    (defaults["auto.global_size"] variables at most), no method-specific option was given, and the global method's
    reformulation accepts it (LP / convex-QP lower level; a nonconvex leader where SCIP is installed)."""
    canon = prep.canon
    size = int(canon.x.numel()) + canon.lower.n_y
    if not set(options) <= GLOBAL_FIRST_OPTIONS or size > param("auto.global_size") or canon.spectral is not None:
        return None
    try:
        linear_mpcc(prep, nonconvex_leader=scip_available())
    except ModelError:
        return None
    return f"a {canon.lower.kind} lower level in global's class and {size} variables (<= {param('auto.global_size')})"


def _try_global(prep: Prepared, options: dict[str, Any], reason: str, t0: float,
                certificate_tol: float | None) -> tuple[BilevelResult | None, str]:
    """Run global for at most defaults["auto.global_time"] (or the user's time_limit, if smaller): its result where
    it proves an optimum, else None and what it ended with (for the fallback's message)."""
    limit = min(float(param("auto.global_time")), float(options.get("time_limit", np.inf)))
    try:
        run = solve_global(prep, time_limit=limit, verbose=bool(options.get("verbose", False)))
    except ModelError as exc:  # refused after all (e.g. SCIP needs bounds the problem does not give)
        return None, f"global refused it ({exc})"
    result = finalize(prep, run, "global", time.perf_counter() - t0, certificate_tol)
    if result.status is Status.SOLVED:
        return dataclasses.replace(result, message=f"auto: global, for {reason}: proven; {result.message}",
                                   stats={**result.stats, "auto": {"method": "global", "reason": reason}}), ""
    return None, f"global ended {result.status.value} within {limit:g} s"


def solve(problem: BilevelProblem, method: str | Method = AUTO, certificate_tol: float | None = None,
          **options: Any) -> BilevelResult:
    """Solve a bilevel problem with a registered method name, "auto" (default: global first where a proof is cheap,
    see global_first, then the local method choose_method picks; the result's method is the one that ran, its message
    and stats["auto"] say why) or a callable(prepared, **options) -> MethodRun. The methods: ipopt, relaxation,
    hypergradient, block-exact, global, differential-evolution, reduced (and any registered with register_method);
    show_options(method) lists a method's options and their defaults. certificate_tol: None takes
    defaults["certificate.tol"] (bilevel.defaults)."""
    if not isinstance(problem, BilevelProblem):
        raise ModelError(f"solve: expected a BilevelProblem, got {type(problem).__name__}; declare one with "
                         "bilevel.BilevelProblem(...) or build a registered one with bilevel.problems.registry.get")
    auto = not callable(method) and str(method).lower() == AUTO
    if callable(method):
        fn, name = method, getattr(method, "__name__", "custom")
    elif not auto:
        name = str(method).lower()
        if name not in METHODS:
            raise ModelError(f"unknown method {method!r}; choose {AUTO!r} or a registered method: "
                             f"{', '.join(sorted(METHODS))}")
        fn = METHODS[name]
    check_common_options(options, certificate_tol)
    t0 = time.perf_counter()
    prep: Prepared = prepare(problem)
    prep.runs += 1
    tried = ""
    if auto and (reason := global_first(prep, options)) is not None:
        proven, tried = _try_global(prep, options, reason, t0, certificate_tol)
        if proven is not None:
            return proven
        if "time_limit" in options:  # the local method gets what global left of the user's limit
            options = {**options, "time_limit": max(options["time_limit"] - (time.perf_counter() - t0), 1e-3)}
    if auto:
        name, why = choose_method(prep, options)
        fn = METHODS[name]
    small = prep.canon.lower.n_y <= param("solvers.small_lower")  # dense algebra of that size: one BLAS thread
    with single_threaded() if small else contextlib.nullcontext():
        run = fn(prep, **options)
        if not isinstance(run, MethodRun):
            raise ModelError(f"method {name!r} returned {type(run).__name__}, not a MethodRun; a method must return "
                             "bilevel.solvers.MethodRun(w, status, message) (w None when it has no point)")
        result = finalize(prep, run, name, time.perf_counter() - t0, certificate_tol)
    if not auto:
        return result
    first = f" ({tried}; then the local rule)" if tried else ""
    return dataclasses.replace(result, message=f"auto: {name}, for {why}{first}; {result.message}",
                               stats={**result.stats, "auto": {"method": name, "reason": why}
                                      | ({"global_first": tried} if tried else {})})


def show_options(method: str | Method) -> str:
    """A method's options as its signature declares them (name: type = default; None: the registry's value,
    bilevel.defaults), followed by its docstring (scipy.optimize.show_options)."""
    fn = method if callable(method) else METHODS.get(str(method).lower())
    if fn is None:
        raise ModelError(f"unknown method {method!r}; {did_you_mean(str(method).lower(), METHODS)}choose a registered "
                         f"method: {', '.join(sorted(METHODS))}")
    params = [p for p in inspect.signature(fn).parameters.values() if p.kind is inspect.Parameter.KEYWORD_ONLY]
    lines = [f"{p.name}: {p.annotation} = {p.default!r}" for p in params]
    return "\n".join(lines + ["", inspect.getdoc(fn) or ""])
