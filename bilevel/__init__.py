"""bilevel: bilevel optimization with convex lower levels, reduced to KKT form, solved and certified."""

from .certificate import Certificate, certify_point
from .defaults import defaults, reset_defaults, set_defaults
from .errors import (BilevelError, InvalidData, LowerLevelInfeasible, LowerLevelUnbounded, ModelError,
                     NonConvexLowerLevel, NotPersistentlyExciting, RankDeficientRegressor, ReferenceModelError,
                     SolverFailed, UnknownName, UnknownOption, UnsupportedPair)
from .model import BilevelProblem
from .mpcc import MPCC, Branch, Exact, FischerBurmeister, KanzowSchwartz, Product, Scholtes
from .problems.registry import problem_builder
from .result import BilevelResult, Status
from .solvers import METHODS, register_method, show_options, solve

_ROBUST = ("Margin", "Proof", "RobustnessCertificate", "certified_margin", "certify")
"""Loaded on first use (bilevel.robust imports the learners, python-control and matplotlib: about a second)."""


def __getattr__(name: str):
    """The certified-robustness names, imported from bilevel.robust on first access."""
    if name in _ROBUST:
        from . import robust

        return getattr(robust, name)
    raise AttributeError(f"module 'bilevel' has no attribute {name!r}")

__all__ = [
    "BilevelError", "BilevelProblem", "BilevelResult", "Branch", "Certificate", "Exact", "FischerBurmeister",
    "InvalidData", "KanzowSchwartz", "LowerLevelInfeasible", "LowerLevelUnbounded", "METHODS", "MPCC", "Margin",
    "ModelError", "NonConvexLowerLevel", "NotPersistentlyExciting", "Product", "Proof", "RankDeficientRegressor",
    "ReferenceModelError", "RobustnessCertificate", "Scholtes", "SolverFailed", "Status", "UnknownName",
    "UnknownOption", "UnsupportedPair", "certified_margin", "certify", "certify_point", "defaults", "problem_builder",
    "register_method", "reset_defaults", "set_defaults", "show_options", "solve",
]
