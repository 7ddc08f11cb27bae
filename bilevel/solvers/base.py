"""Deprecated: the old home of Prepared, MethodRun and finalize, kept for user code until bilevel 0.2.0. Import
Prepared, MethodRun and prepare from bilevel.solvers, finalize from bilevel.solvers.verdict.finalize."""

import warnings

from ..errors import RENAMES_REMOVED_IN
from .engine.prepared import MethodRun, Prepared, best_of, check_options, options_of, prepare, unbounded_lower
from .verdict.finalize import finalize

warnings.warn(f"bilevel.solvers.base is deprecated and will be removed in bilevel {RENAMES_REMOVED_IN}: import "
              "Prepared, MethodRun and prepare from bilevel.solvers (finalize: bilevel.solvers.verdict.finalize)",
              DeprecationWarning, stacklevel=2)

__all__ = ["MethodRun", "Prepared", "best_of", "check_options", "finalize", "options_of", "prepare", "unbounded_lower"]
