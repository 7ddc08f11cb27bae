"""The one check that numeric data a user passes are real numbers: complex values (even with zero imaginary parts)
are refused by name, where numpy would drop the imaginary part with a warning or carry it into a complex answer."""

from __future__ import annotations

from typing import Any

import numpy as np

from .errors import InvalidData


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
