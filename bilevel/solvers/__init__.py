"""Solution methods for the single-level (KKT) reformulation and the dispatcher `solve`; engine/ holds what methods
share, verdict/ how a run becomes a result, globalopt/ method "global"."""

from .engine.prepared import MethodRun, Prepared, prepare
from .registry import METHODS, register_method, show_options, solve

__all__ = ["METHODS", "MethodRun", "Prepared", "prepare", "register_method", "show_options", "solve"]
