"""Reductions that can be undone (apply/invert), and the single-level (KKT) reduction to an MPCC."""

from __future__ import annotations

from abc import ABC, abstractmethod
from dataclasses import dataclass
from typing import Any, Callable

import casadi as ca
import numpy as np

from .vech import unvech, vech
from .mpcc import MPCC, PSDPair, ScalarPair


class Reduction(ABC):
    """A problem transformation: apply(problem) -> (new problem, inverse data); invert maps solutions back."""

    @abstractmethod
    def apply(self, problem: Any) -> tuple[Any, Any]:
        """Transform `problem`; return the new problem and what invert() needs."""

    @abstractmethod
    def invert(self, solution: Any, inverse_data: Any) -> Any:
        """Map a solution of the transformed problem back to one of the original."""


class Chain(Reduction):
    """Apply reductions in order; invert them in reverse order with their own inverse data."""

    def __init__(self, reductions: list[Reduction]) -> None:
        self.reductions = list(reductions)

    def apply(self, problem: Any) -> tuple[Any, list[Any]]:
        inverse = []
        for r in self.reductions:
            problem, data = r.apply(problem)
            inverse.append(data)
        return problem, inverse

    def invert(self, solution: Any, inverse_data: list[Any]) -> Any:
        for r, data in zip(reversed(self.reductions), reversed(inverse_data)):
            solution = r.invert(solution, data)
        return solution


@dataclass(frozen=True)
class KKTInverse:
    """Where each block (x, y, lam, mu, vech Z_k) sits in the MPCC variable vector."""

    slices: dict[str, slice]
    psd_sizes: tuple[int, ...]
    lift: Callable[[np.ndarray], np.ndarray] | None = None
    """x -> [x; z(x)] when the x block also holds the problem's definitions (Lifting), else None."""
    n_x: int = 0


@dataclass
class KKTPoint:
    """A point of the canonical bilevel problem: upper x, lower y and lower multipliers (lam, mu, Z)."""

    x: np.ndarray
    y: np.ndarray
    lam: np.ndarray
    mu: np.ndarray
    Z: list[np.ndarray]


class SingleLevelReduction(Reduction):
    """Replace the convex lower level by its KKT conditions: stationarity, feasibility, complementarity.

    Variables w = [x, y, lam, mu, vech Z_1, ...]; equalities: upper equalities, stationarity, lower
    equalities; inequalities: upper inequalities; pairs: 0 <= -g ⟂ lam >= 0 and M_k >= 0 ⟂ Z_k >= 0.
    A problem with definitions is reduced in its lifted form: the x block is [x; z], the definitions'
    equations are upper equalities, and invert/pack drop and restore z.
    """

    @staticmethod
    def layout(canon: Any) -> KKTInverse:
        """Where each block sits in w, from the sizes alone (no expression is built)."""
        lifting = canon.lifting
        canon = canon if lifting is None else lifting.raw
        low = canon.lower
        dims = tuple(int(m.size1()) for m in low.psd)
        sizes = [("x", low.n_x), ("y", low.n_y), ("lam", low.n_g), ("mu", low.n_h)]
        sizes += [(f"Z{k}", n * (n + 1) // 2) for k, n in enumerate(dims)]
        slices, start = {}, 0
        for name, size in sizes:
            slices[name] = slice(start, start + size)
            start += size
        n_x = low.n_x - (0 if lifting is None else int(lifting.z.numel()))
        return KKTInverse(slices, dims, None if lifting is None else lifting.lift, n_x)

    def apply(self, canon: Any) -> tuple[MPCC, KKTInverse]:
        inverse = self.layout(canon)
        canon = canon if canon.lifting is None else canon.lifting.raw
        low = canon.lower.symbolic()
        kkt = low.kkt()
        blocks = [("x", canon.x), ("y", low.y), ("lam", kkt.lam), ("mu", kkt.mu)]
        blocks += [(f"Z{k}", v) for k, v in enumerate(kkt.Z_vech)]
        w = ca.vertcat(*[sym for _, sym in blocks])
        slices, start = inverse.slices, int(w.numel())
        lbw = np.full(start, -np.inf)
        ubw = np.full(start, np.inf)
        lbw[slices["x"]], ubw[slices["x"]] = canon.x_lb, canon.x_ub
        pairs: list[ScalarPair | PSDPair] = []
        if low.g.numel():
            pairs.append(ScalarPair("lower", -low.g, kkt.lam, tuple(low.g_names)))
        for k, (m, z) in enumerate(zip(low.psd, kkt.Z)):
            pairs.append(PSDPair(low.psd_names[k], m, z))
        mpcc = MPCC(
            w=w, lbw=lbw, ubw=ubw, objective=canon.F,
            equalities=ca.vertcat(canon.H, kkt.stationarity, low.h),
            inequalities=canon.G, pairs=pairs,
            blocks={name: slices[name] for name, _ in blocks}, params=canon.params,
        )
        return mpcc, inverse

    def invert(self, w: np.ndarray, inverse_data: KKTInverse) -> KKTPoint:
        s = inverse_data.slices
        w = np.asarray(w, dtype=float).ravel()
        zs = [unvech(w[s[f"Z{k}"]], n) for k, n in enumerate(inverse_data.psd_sizes)]
        x = w[s["x"]]
        return KKTPoint(x if inverse_data.lift is None else x[: inverse_data.n_x], w[s["y"]], w[s["lam"]],
                        w[s["mu"]], zs)

    @staticmethod
    def pack(point: KKTPoint, inverse_data: KKTInverse) -> np.ndarray:
        """The MPCC vector w of a point (the inverse of invert), e.g. to warm start from a lower solve."""
        x = point.x if inverse_data.lift is None else inverse_data.lift(np.asarray(point.x, dtype=float))
        parts = [x, point.y, point.lam, point.mu] + [vech(z) for z in point.Z]
        return np.concatenate([np.asarray(p, dtype=float).ravel() for p in parts])
