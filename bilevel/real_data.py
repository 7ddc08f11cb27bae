"""The checks of numbers a user passes: data are real numbers (complex values, even with zero imaginary parts,
are refused by name, where numpy would drop the imaginary part with a warning or carry it into a complex answer),
and a scalar setting is a finite real number or an integer, never a bool or a string read as one."""

from __future__ import annotations

from typing import Any

import numpy as np

from .errors import InvalidData, ModelError


def refuse_complex(value: Any, what: str) -> None:
    """InvalidData naming `what` where value (an array, scipy.sparse matrix, LinearOperator or number) is complex."""
    dtype = getattr(value, "dtype", None)
    if dtype is None:
        try:
            dtype = np.asarray(value).dtype
        except (TypeError, ValueError):  # ragged: not numbers at all, which the caller's conversion reports
            return
    if np.issubdtype(np.dtype(dtype), np.complexfloating):
        raise InvalidData(f"{what} is complex; it takes real numbers: pass its real part (np.real), or the real and "
                          "imaginary parts as separate real data")


def real_array(value: Any, what: str) -> np.ndarray:
    """value as a float array; InvalidData naming `what` where it is complex or not numbers (finiteness and shape are
    the caller's to check)."""
    refuse_complex(value, what)
    try:
        arr = np.asarray(value, dtype=float)
    except (TypeError, ValueError):
        raise InvalidData(f"{what} must be real numbers, got {type(value).__name__}") from None
    return arr


def real_number(value: Any, what: str) -> float:
    """value as a finite float; ModelError naming `what` where it is a bool, a string, complex, NaN or inf (a setting
    of a problem or learner: its range is the caller's to check)."""
    if isinstance(value, (bool, np.bool_)) or not isinstance(value, (int, float, np.integer, np.floating)) \
            or not np.isfinite(value):
        raise ModelError(f"{what}={value!r} is invalid: it must be a finite real number")
    return float(value)


def integer(value: Any, what: str, low: int) -> int:
    """value as an int >= low; ModelError naming `what` where it is a bool, a float, a string or below low."""
    if isinstance(value, (bool, np.bool_)) or not isinstance(value, (int, np.integer)) or value < low:
        raise ModelError(f"{what}={value!r} is invalid: it must be an integer >= {low}")
    return int(value)
