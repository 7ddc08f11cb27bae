"""What every attack result (a BilevelResult of its registered problem) adds in stats: the true closed loop."""

from __future__ import annotations

from typing import Any

from ..errors import ModelError
from ..result import BilevelResult


def attack_stat(result: BilevelResult, key: str) -> Any:
    """stats[key] of an attack's result; ModelError if `result` is not an attack's BilevelResult."""
    if not isinstance(result, BilevelResult) or key not in result.stats:
        raise ModelError(f"expected the BilevelResult of a VRFT or Willems attack (with stats[{key!r}]), got "
                         f"{type(result).__name__}; pass what an attack function returned")
    return result.stats[key]


def unstable(result: BilevelResult) -> bool:
    """The true plant with the learner's poisoned controller has a pole on or outside the unit circle
    (stats['spectral_radius'], which every VRFT and Willems attack reports)."""
    return attack_stat(result, "spectral_radius") >= 1.0
