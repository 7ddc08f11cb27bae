"""Validation of solver and attack options, in one place: a bad value is a ModelError naming the option and what it
must be, raised before any work (never a float() ValueError or a silent clamp deep inside a method)."""

from __future__ import annotations

import math
from numbers import Integral, Real
from typing import Any, Iterable

import numpy as np

from ...defaults import check
from ...errors import ModelError


def _bad(name: str, value: Any, want: str) -> ModelError:
    return ModelError(f"option {name}={value!r} is invalid: it must be {want}")


def _integer(v: Any) -> bool:
    return isinstance(v, Integral) and not isinstance(v, bool)


def _real(v: Any) -> bool:
    return isinstance(v, Real) and not isinstance(v, bool) and math.isfinite(v)


def check_numbers(options: dict[str, Any], positive: Iterable[str] = (), nonnegative: Iterable[str] = ()) -> None:
    """Each named option that is given must be a finite number, > 0 (positive) or >= 0 (nonnegative)."""
    for name in positive:
        if name in options and not (_real(options[name]) and options[name] > 0):
            raise _bad(name, options[name], "a finite number > 0")
    for name in nonnegative:
        if name in options and not (_real(options[name]) and options[name] >= 0):
            raise _bad(name, options[name], "a finite number >= 0")


def check_counts(options: dict[str, Any], names: Iterable[str]) -> None:
    """Each named option that is given must be an integer >= 1 (a count: starts, population size)."""
    for name in names:
        if name in options and not (_integer(options[name]) and options[name] >= 1):
            raise _bad(name, options[name], "an integer >= 1")


def check_flags(options: dict[str, Any], names: Iterable[str]) -> None:
    """Each named option that is given must be True or False (a string such as "no" is not taken as true)."""
    for name in names:
        if name in options and not isinstance(options[name], (bool, np.bool_)):
            raise _bad(name, options[name], "True or False")


RENAMED_OPTIONS: dict[str, dict[str, str]] = {
    "hypergradient": {"tol": "gtol (the descent's projected step norm) or gain_tol (the exact-block mode's relative "
                             "gain over its window of steps)"},
    "block-exact": {"tol": "gain_tol (the relative gain over the ascent's window of steps)"},
    "ipopt": {"tol": "nlp_tol (IPOPT's tol on each NLP)", "polish": "branch_polish"},
    "relaxation": {"tol": "nlp_tol (IPOPT's tol on each NLP)", "polish": "branch_polish"},
    "differential-evolution": {"tol": "pop_tol (the population's relative spread)"},
    "de_attack": {"maxiter": "max_iter", "tol": "pop_tol (the population's relative spread)"},
}
"""Options renamed so that one name means one thing: method -> old name -> what to use (check_options says so)."""

TOLERANCES = ("gtol", "ftol", "gain_tol", "nlp_tol", "pop_tol")
"""The methods' stopping tolerances (bilevel.defaults documents each)."""


def check_common_options(options: dict[str, Any], certificate_tol: Any = None) -> None:
    """Validate the options every method (and every attack) shares, once, before dispatch: starts, max_iter, the
    tolerances (TOLERANCES), scale, time_limit (seconds), seed, certificate_tol (None: defaults["certificate.tol"]),
    and the switches polish, branch_polish and verbose."""
    if "starts" in options and not (_integer(options["starts"]) and options["starts"] >= 1):
        raise _bad("starts", options["starts"], "an integer >= 1 (the number of multistart starts)")
    if "max_iter" in options and not (_integer(options["max_iter"]) and options["max_iter"] >= 0):
        raise _bad("max_iter", options["max_iter"], "an integer >= 0")
    check_numbers(options, positive=("scale", "time_limit", *(t for t in TOLERANCES if t != "ftol")),
                  nonnegative=("ftol",))
    check_flags(options, ("polish", "branch_polish", "verbose"))
    if certificate_tol is not None:
        check("certificate.tol", certificate_tol, "certificate_tol")
    seed = options.get("seed")
    if not (seed is None or isinstance(seed, (np.random.Generator, np.random.SeedSequence))
            or (_integer(seed) and seed >= 0)):
        raise _bad("seed", seed, "None, an integer >= 0, or a numpy Generator / SeedSequence")
