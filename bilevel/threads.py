"""One BLAS thread for small dense linear algebra (threaded BLAS on 6x6 or 512x6 arrays is slower, and
much slower when sweeps already occupy every core)."""

from __future__ import annotations

import functools
from typing import Any, Callable, ContextManager

from threadpoolctl import ThreadpoolController


@functools.cache
def _controller() -> ThreadpoolController:
    """The BLAS/OpenMP pools loaded so far, scanned once (a scan costs ~0.3 ms; a limit from it ~0.02 ms)."""
    return ThreadpoolController()


def single_threaded() -> ContextManager[Any]:
    """Context manager limiting the BLAS/OpenMP pools to one thread."""
    return _controller().limit(limits=1)


def single_threaded_call(fn: Callable[..., Any]) -> Callable[..., Any]:
    """fn wrapped to run with one BLAS/OpenMP thread."""
    @functools.wraps(fn)
    def wrapper(*args: Any, **kwargs: Any) -> Any:
        with single_threaded():
            return fn(*args, **kwargs)
    return wrapper
