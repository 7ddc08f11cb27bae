"""Solution methods for the single-level (KKT) reformulation, the dispatcher `solve` and `solve_many` (many instances of
one declaration at once, bilevel.solvers.batch); engine/ holds what methods share, verdict/ how a run becomes a
result, globalopt/ method "global"."""

from .engine.prepared import MethodRun, Prepared, prepare
from .batch import BatchMethod, register_batch, solve_many
from .registry import METHODS, register_method, show_options, solve

__all__ = ["METHODS", "BatchMethod", "MethodRun", "Prepared", "prepare", "register_batch", "register_method",
           "show_options", "solve", "solve_many"]
