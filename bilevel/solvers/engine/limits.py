"""What every method shares for options time_limit and verbose: a wall-clock deadline and one-line progress reports.

time_limit (seconds, wall clock) bounds a method's own work (not the preparation before it, nor the certificate
after it): a method checks it between iterations, generations and starts, ends with the best point so far and
status MAX_ITERATIONS (the result is then `inaccurate` where the certificate passes). verbose=True writes one line
per iteration, generation or start to stderr, as "[method] text" (stdout stays for results).
"""

from __future__ import annotations

import math
import sys
import time
from typing import TYPE_CHECKING, Any

from ...result import Status

if TYPE_CHECKING:  # pragma: no cover
    from .prepared import MethodRun


GOAL_STOP = "stopped by the callback (the caller's goal)"
"""The message part of a run that the caller's callback ended (StopIteration) where its goal was reached."""


class Deadline:
    """The moment option time_limit runs out (never, without one), counted from construction."""

    def __init__(self, seconds: float | None) -> None:
        self.seconds = None if seconds is None else float(seconds)
        self._end = math.inf if seconds is None else time.perf_counter() + float(seconds)
        self.hit = False
        """Whether expired() has returned True: the limit stopped some work (ask it only where work remains)."""

    def expired(self) -> bool:
        """Whether the limit has passed (then `hit` is set)."""
        self.hit = self.hit or time.perf_counter() >= self._end
        return self.hit

    def remaining(self) -> float:
        """Seconds left (inf without a limit, 0 once passed)."""
        return max(self._end - time.perf_counter(), 0.0)

    def reached(self) -> str:
        """The message part saying that the limit stopped the method."""
        return f"time_limit = {self.seconds:g} s reached"


def progress(verbose: Any, method: str, text: str) -> None:
    """One progress line "[method] text" on stderr when verbose."""
    if verbose:
        print(f"[{method}] {text}", file=sys.stderr, flush=True)


def stopped(run: "MethodRun", limit: Deadline, done: int, total: int) -> "MethodRun":
    """A multistart method's run, as MAX_ITERATIONS with a message saying so where the deadline stopped it (after
    `done` of `total` starts)."""
    if limit.hit:
        run.status = Status.MAX_ITERATIONS
        run.message = f"{limit.reached()} after {done} of {total} starts; {run.message}"
    return run
