"""Certify a bilevel point: KKT residuals of the lower level plus an independent re-solve of it.

Residuals are absolute; a check passes when residual <= tol * (1 + scale), with scale the size of
the quantity it is compared against (|grad_y f| for stationarity, |f*(x)| for the optimality gap).
Upper-level optimality is not certified (no method can for a non-convex bilevel program).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import TYPE_CHECKING

import numpy as np

from .errors import BilevelError
from .lower.base import psd_violation

if TYPE_CHECKING:  # pragma: no cover
    from .canonical import CanonicalBilevel
    from .reduction import KKTPoint

DEFAULT_TOL = 1e-6


@dataclass(frozen=True)
class GlobalBound:
    """Proof of global optimality (method "global"): bounds on the optimal upper value in the declared sense,
    gap = (upper_bound - lower_bound) / max(1, |best value|), and how each big-M was justified."""

    lower_bound: float
    upper_bound: float
    gap: float
    tolerance: float
    proven: bool
    algorithm: str
    nodes: int
    big_m: tuple[str, ...] = ()


@dataclass(frozen=True)
class Certificate:
    """Residuals at a point and the verdict. lower_gap = f(x, y) - f*(x), f* from an independent solve."""

    stationarity: float
    lower_feasibility: float
    dual_feasibility: float
    complementarity: float
    upper_feasibility: float
    lower_gap: float
    lower_reference: float
    lower_reference_y: list[float]
    lower_solver: str
    tolerance: float
    passed: bool
    failed: tuple[str, ...] = field(default_factory=tuple)
    note: str = ""
    global_bound: GlobalBound | None = None

    def __repr__(self) -> str:
        verdict = "passed" if self.passed else f"FAILED ({', '.join(self.failed)})"
        return (f"Certificate({verdict}; stationarity={self.stationarity:.2e}, lower_feas={self.lower_feasibility:.2e}, "
                f"dual_feas={self.dual_feasibility:.2e}, compl={self.complementarity:.2e}, "
                f"upper_feas={self.upper_feasibility:.2e}, gap={self.lower_gap:.2e} via {self.lower_solver}"
                + ("" if self.global_bound is None else
                   f"; global bounds [{self.global_bound.lower_bound:.10g}, {self.global_bound.upper_bound:.10g}], "
                   f"gap {self.global_bound.gap:.1e}{' proven' if self.global_bound.proven else ' NOT proven'}")
                + ")")


def certify(canon: "CanonicalBilevel", point: "KKTPoint", tol: float = DEFAULT_TOL) -> Certificate:
    """KKT residuals of the lower level at `point` and its gap to an independent lower-level solve."""
    low = canon.lower
    x, y = point.x, point.y
    f, g, h, mats = low.evaluate(x, y)
    stat, grad_f = low.stationarity(x, y, point.lam, point.mu, point.Z)
    top = lambda a: float(np.max(a)) if np.size(a) else 0.0  # noqa: E731
    stationarity = top(np.abs(stat))
    lower_feas = max(top(np.maximum(g, 0.0)), top(np.abs(h)), max((psd_violation(m) for m in mats), default=0.0))
    dual_feas = max(top(np.maximum(-point.lam, 0.0)), max((psd_violation(z) for z in point.Z), default=0.0))
    comp = max(top(np.abs(point.lam * g)), max((abs(float(np.sum(z * m))) for z, m in zip(point.Z, mats)), default=0.0))
    out = canon.functions(x, y)
    G, H = np.asarray(out[1]).ravel(), np.asarray(out[2]).ravel()
    bounds = np.maximum(np.maximum(canon.x_lb - x, x - canon.x_ub), 0.0)
    upper_feas = max(top(np.maximum(G, 0.0)), top(np.abs(H)), top(bounds))
    note = ""
    try:
        ref = low.solve(x)
        f_ref, y_ref, solver = ref.objective, ref.y, ref.solver
    except BilevelError as exc:
        f_ref, y_ref, solver, note = np.nan, np.full(low.n_y, np.nan), "none", f"independent lower solve failed: {exc}"
    gap = f - f_ref if np.isfinite(f_ref) else np.inf
    checks = {
        "stationarity": stationarity <= tol * (1.0 + top(np.abs(grad_f))),
        "lower_feasibility": lower_feas <= tol,
        "dual_feasibility": dual_feas <= tol,
        "complementarity": comp <= tol,
        "upper_feasibility": upper_feas <= tol,
        "lower_gap": gap <= tol * (1.0 + abs(f_ref)) if np.isfinite(gap) else False,
    }
    failed = tuple(k for k, ok in checks.items() if not ok)
    return Certificate(stationarity, lower_feas, dual_feas, comp, upper_feas, float(gap), float(f_ref),
                       [float(v) for v in y_ref], solver, tol, not failed, failed, note)
