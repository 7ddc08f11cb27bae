"""Registered bilevel problem instances (literature problems with known optima, attack problems)."""

from .registry import ProblemSpec, get, names, register, spec

__all__ = ["ProblemSpec", "get", "names", "register", "spec"]
