"""Exceptions of `bilevel`: one narrow class per broken contract, all under `BilevelError`; the "did you mean"
their messages offer for a misspelt name."""

from __future__ import annotations

import difflib
from typing import Any, Iterable


RENAMES_REMOVED_IN = "0.2.0"
"""The release that removes the rename shims (renamed options, attributes and the module bilevel.solvers.base): until
then an old name raises (or, for the module, warns) with its new one."""


def renamed(old: str, new: str) -> str:
    """The message for a renamed name: what to use, and the release that drops the note."""
    return f"{old} was renamed: use {new}; this note goes in bilevel {RENAMES_REMOVED_IN}"


class BilevelError(Exception):
    """Base class; `result` carries a partial result when one exists (never lost on raise)."""

    def __init__(self, message: str, result: Any = None) -> None:
        super().__init__(message)
        self.result = result


class ModelError(BilevelError, ValueError):
    """A bilevel problem is declared wrongly (shape mismatch, missing objective, bad bounds)."""


class NonConvexLowerLevel(ModelError):
    """The lower level is detectably non-convex in the lower variables."""


class LowerLevelInfeasible(BilevelError):
    """The lower level has no feasible point at the given upper point."""


class LowerLevelUnbounded(BilevelError):
    """The lower level is unbounded below at the given upper point."""


class InvalidData(BilevelError, ValueError):
    """Numerical data are unusable: NaN/inf, length mismatch, wrong shape."""


class NotPersistentlyExciting(InvalidData):
    """Data are not persistently exciting enough for the learner (rank test failed)."""


class RankDeficientRegressor(InvalidData):
    """A least-squares regressor is rank deficient, so the fit is not unique."""


class ReferenceModelError(InvalidData):
    """A reference model cannot be used (not invertible, unstable, improper)."""


class UnknownOption(BilevelError, TypeError):
    """An option name is not understood by the chosen method (typos must not pass silently)."""


class UnknownName(BilevelError, KeyError):
    """A name (registered problem, method) is not known; still a KeyError for lookups that expect one."""

    def __str__(self) -> str:  # KeyError would quote the message
        return str(self.args[0]) if self.args else ""


class UnsupportedPair(BilevelError):
    """A complementarity mode cannot transcribe a pair of this kind (e.g. PSD pairs)."""

    def __init__(self, mode: object, kind: str) -> None:
        super().__init__(
            f"complementarity mode {type(mode).__name__} does not support {kind} pairs; "
            f"choose a mode that does (e.g. Scholtes) or reformulate the constraint"
        )


class SolverFailed(BilevelError):
    """A backend failed in a way that leaves no usable point; `result` holds what there is."""


class WorkerLost(BilevelError):
    """A sweep task's worker process died (killed, out of memory, a crash in native code) on every retry."""


def did_you_mean(name: str, choices: Iterable[str]) -> str:
    """"did you mean 'a' or 'b'? " naming the choices closest to a misspelt `name` (those it begins first), or ""."""
    close = difflib.get_close_matches(name, sorted(choices), n=3, cutoff=0.6)
    close.sort(key=lambda c: not c.startswith(name))
    return f"did you mean {' or '.join(map(repr, close))}? " if close else ""
