"""One BLAS thread for small dense linear algebra (threaded BLAS on 6x6 or 512x6 arrays is slower, and
much slower when sweeps already occupy every core)."""

from __future__ import annotations

import functools
from typing import Any, Callable, ContextManager

import casadi as ca
import threadpoolctl
from threadpoolctl import OpenBLASController, ThreadpoolController


class CasadiOpenBLAS(OpenBLASController):
    """The OpenBLAS CasADi bundles for IPOPT's MUMPS (libcasadi-tp-openblas), which threadpoolctl does not know by
    name: with its second thread the DeePC attacks' IPOPT solves (918-row KKT systems) took 1.1x the wall time and
    twice the CPU time on a nearly idle 2-core machine, up to 1.8x the wall time on a loaded one
    (benchmarks/results/bench_deepc.txt)."""

    filename_prefixes = ("libcasadi-tp-openblas",)


threadpoolctl.register(CasadiOpenBLAS)


@functools.cache
def _controller() -> ThreadpoolController:
    """The BLAS/OpenMP pools, with IPOPT's (loaded with CasADi's IPOPT plugin first), scanned once (a scan costs
    ~0.3 ms; a limit from it ~0.02 ms)."""
    ca.load_nlpsol("ipopt")
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
