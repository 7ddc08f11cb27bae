"""Solution methods for the single-level (KKT) reformulation and the dispatcher `solve`."""

from .registry import METHODS, register_method, show_options, solve

__all__ = ["METHODS", "register_method", "show_options", "solve"]
