"""Other ways to declare a lower level: a cvxpy Problem, translated into the framework's declarations."""

from .cvxpy_lower import CvxpyLower

__all__ = ["CvxpyLower"]
