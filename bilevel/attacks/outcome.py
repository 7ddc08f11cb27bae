"""What every attack result (a BilevelResult of its registered problem) adds in stats: the true closed loop."""

from __future__ import annotations

from ..result import BilevelResult


def unstable(result: BilevelResult) -> bool:
    """The true plant with the learner's poisoned controller has a pole on or outside the unit circle
    (stats['spectral_radius'], which every VRFT and Willems attack reports)."""
    return result.stats["spectral_radius"] >= 1.0
