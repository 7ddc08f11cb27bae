"""Deprecated: the old home of Prepared, MethodRun and finalize, kept for user code until bilevel 0.2.0. Import
Prepared, MethodRun and prepare from bilevel.solvers, finalize from bilevel.solvers.verdict.finalize."""

import warnings

from .engine.prepared import MethodRun, Prepared, best_of, check_options, options_of, prepare, unbounded_lower
from .verdict.finalize import finalize

warnings.warn("bilevel.solvers.base is deprecated and will be removed in bilevel 0.2.0: import Prepared, MethodRun "
              "and prepare from bilevel.solvers (finalize: bilevel.solvers.verdict.finalize)", DeprecationWarning,
              stacklevel=2)

__all__ = ["MethodRun", "Prepared", "best_of", "check_options", "finalize", "options_of", "prepare", "unbounded_lower"]
