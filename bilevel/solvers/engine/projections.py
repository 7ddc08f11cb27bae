"""Euclidean projections onto the sets projected-gradient methods keep the flat upper vector x in.

Each set is a callable `proj(v) -> P(v)` with `contains(v, tol)` and `with_box(lb, ub)`, the projection
onto its intersection with a box (how a method adds the declared bounds). What is exact:

* Box, and every NormBall (l2, linf, l1; with or without a box): exact Euclidean projections. The l1
  ball uses the sort-based method of Duchi et al. (2008); a ball intersected with a box is projected by
  bisection on the multiplier of the norm constraint (to machine precision, always on the feasible side).
* SparseNormBall (at most k entries differ from the center, and the norm budget): exact for all three
  norms without a box (keep the k largest deviations, then project them onto the ball: an exchange
  argument shows this support is optimal for any sign- and permutation-invariant norm), and exact for
  linf with a box (the set is then separable). For l2 and l1 with a box the support is chosen by the
  per-entry gain inside the box, a heuristic: the result is feasible but may not be the nearest point.
* Blocks: applies one projection per block of entries; exact when each block's projection is.
"""

from __future__ import annotations

from abc import ABC, abstractmethod
from dataclasses import dataclass
from typing import Any, Callable, Iterable, Mapping

import numpy as np

from ...errors import InvalidData, ModelError
from ...model import BilevelProblem

NORMS = (1, 2, np.inf)
_BISECTIONS = 200


class Projection(ABC):
    """A closed set with its Euclidean projection `proj(v)`, membership test and box intersection."""

    @abstractmethod
    def __call__(self, v: np.ndarray) -> np.ndarray:
        """The projection of v onto the set."""

    @abstractmethod
    def contains(self, v: np.ndarray, tol: float = 1e-9) -> bool:
        """Whether v lies in the set up to tol."""

    @abstractmethod
    def with_box(self, lb: np.ndarray, ub: np.ndarray) -> "Projection":
        """The projection onto this set intersected with the box lb <= v <= ub."""


def _vector(v: Any) -> np.ndarray:
    out = np.asarray(v, dtype=float).ravel()
    if not np.all(np.isfinite(out)):
        raise InvalidData("cannot project a vector containing NaN or inf")
    return out


def _norm_order(norm: Any) -> float:
    order = np.inf if norm in ("inf", "linf", np.inf) else norm
    if order not in NORMS:
        raise ModelError(f"norm {norm!r} is not supported; use 1, 2 or np.inf ('inf')")
    return float(order)


def _norm(d: np.ndarray, order: float) -> float:
    d = np.ravel(d)
    return float(np.linalg.norm(d, ord=order)) if d.size else 0.0


@dataclass(frozen=True, eq=False)
class Box(Projection):
    """lb <= v <= ub entrywise (scalars broadcast; -inf/inf for missing bounds)."""

    lb: Any = -np.inf
    ub: Any = np.inf

    def __post_init__(self) -> None:
        lb, ub = np.asarray(self.lb, dtype=float), np.asarray(self.ub, dtype=float)
        if np.isnan(lb).any() or np.isnan(ub).any():
            raise ModelError("box bounds contain NaN; use -inf/inf for a missing bound")
        if np.any(lb > ub):
            raise ModelError("box is empty: a lower bound exceeds its upper bound")
        object.__setattr__(self, "lb", lb)
        object.__setattr__(self, "ub", ub)

    def __call__(self, v: np.ndarray) -> np.ndarray:
        """Clip v into the box."""
        return np.clip(_vector(v), self.lb, self.ub)

    def contains(self, v: np.ndarray, tol: float = 1e-9) -> bool:
        """Whether lb - tol <= v <= ub + tol."""
        v = _vector(v)
        return bool(np.all(v >= self.lb - tol) and np.all(v <= self.ub + tol))

    def with_box(self, lb: np.ndarray, ub: np.ndarray) -> "Box":
        """The intersection of two boxes (a box)."""
        return Box(np.maximum(self.lb, lb), np.minimum(self.ub, ub))

    @property
    def is_free(self) -> bool:
        """True when no bound is finite (the box is the whole space)."""
        return not (np.isfinite(self.lb).any() or np.isfinite(self.ub).any())


def _boundary(feasible: Callable[[float], bool], inside: float, outside: float) -> float:
    """Bisect between feasible(inside) and not feasible(outside); return the last feasible parameter."""
    for _ in range(_BISECTIONS):
        mid = 0.5 * (inside + outside)
        if mid in (inside, outside):
            break
        if feasible(mid):
            inside = mid
        else:
            outside = mid
    return inside


def _project_l1(d: np.ndarray, radius: float) -> np.ndarray:
    """Projection of d onto the l1 ball of given radius at 0 (Duchi, Shalev-Shwartz, Singer, Chandra 2008)."""
    a = np.abs(d)
    if a.sum() <= radius:
        return d.copy()
    if radius <= 0:
        return np.zeros_like(d)
    u = np.sort(a)[::-1]
    cssv = np.cumsum(u) - radius
    support = np.nonzero(u * np.arange(1, u.size + 1) > cssv)[0]  # empty when radius is below u[0]'s round-off
    rho = support[-1] if support.size else 0
    theta = cssv[rho] / (rho + 1.0)
    return np.sign(d) * np.maximum(a - theta, 0.0)


def _project_ball(d: np.ndarray, radius: float, order: float, lo: np.ndarray | None,
                  hi: np.ndarray | None) -> np.ndarray:
    """Project a deviation d from the center onto {||t|| <= radius, lo <= t <= hi} (box optional)."""
    if order == np.inf:
        lo_, hi_ = -radius, radius
        if lo is not None:
            lo_, hi_ = np.maximum(lo, -radius), np.minimum(hi, radius)
        return np.clip(d, lo_, hi_)
    if lo is None:
        if order == 1:
            return _project_l1(d, radius)
        n = _norm(d, 2)
        return d.copy() if n <= radius else d * (radius / n)
    if order == 2:  # t(s) = clip(s d, lo, hi) with s = 1 / (1 + multiplier); ||t(s)|| is nondecreasing in s
        point = lambda s: np.clip(s * d, lo, hi)  # noqa: E731
        inside, outside = 0.0, 1.0
    else:  # t(theta) = clip(soft-threshold(d, theta), lo, hi); ||t(theta)||_1 is nonincreasing in theta
        point = lambda theta: np.clip(np.sign(d) * np.maximum(np.abs(d) - theta, 0.0), lo, hi)  # noqa: E731
        inside, outside = float(np.abs(d).max(initial=0.0)), 0.0
    feasible = lambda s: _norm(point(s), order) <= radius  # noqa: E731
    return point(outside if feasible(outside) else _boundary(feasible, inside, outside))


def _box_offsets(box: Box | None, center: np.ndarray, size: int) -> tuple[np.ndarray | None, np.ndarray | None]:
    if box is None:
        return None, None
    return (np.broadcast_to(box.lb, (size,)) - center, np.broadcast_to(box.ub, (size,)) - center)


@dataclass(frozen=True, eq=False)
class NormBall(Projection):
    """||v - center|| <= radius in the l2, linf or l1 norm (center 0 by default), optionally within a box."""

    radius: float
    norm: Any = 2
    center: Any = None
    box: Box | None = None

    def __post_init__(self) -> None:
        if not (np.isfinite(self.radius) and self.radius >= 0):
            raise ModelError(f"norm-ball radius must be finite and >= 0, got {self.radius}")
        object.__setattr__(self, "norm", _norm_order(self.norm))
        if self.center is not None:
            object.__setattr__(self, "center", _vector(self.center))
        if self.box is not None:
            c = np.zeros(np.broadcast(self.box.lb, self.box.ub).shape) if self.center is None else self.center
            gap = _norm(np.clip(c, self.box.lb, self.box.ub) - c, self.norm)
            if gap > self.radius:
                raise ModelError(f"the norm ball (radius {self.radius}) does not meet the box: the box is at "
                                 f"distance {gap:.6g} from the center; enlarge the radius or the bounds")

    def _center(self, size: int) -> np.ndarray:
        c = np.zeros(size) if self.center is None else self.center
        if c.shape != (size,):
            raise InvalidData(f"norm ball centered at {c.size} entries applied to a vector of {size}")
        return c

    def __call__(self, v: np.ndarray) -> np.ndarray:
        """The nearest point of the ball (and box) to v."""
        v = _vector(v)
        c = self._center(v.size)
        lo, hi = _box_offsets(self.box, c, v.size)
        return c + _project_ball(v - c, float(self.radius), float(self.norm), lo, hi)

    def contains(self, v: np.ndarray, tol: float = 1e-9) -> bool:
        """Whether ||v - center|| <= radius + tol (and v is in the box up to tol)."""
        v = _vector(v)
        inside = _norm(v - self._center(v.size), self.norm) <= self.radius + tol
        return inside and (self.box is None or self.box.contains(v, tol))

    def with_box(self, lb: np.ndarray, ub: np.ndarray) -> "NormBall":
        """The same ball intersected with the box (an exact projection)."""
        box = Box(lb, ub) if self.box is None else self.box.with_box(lb, ub)
        return NormBall(self.radius, self.norm, self.center, None if box.is_free else box)


@dataclass(frozen=True, eq=False)
class SparseNormBall(Projection):
    """At most k entries of v differ from center and ||v - center|| <= radius (a non-convex set)."""

    radius: float
    k: int
    norm: Any = 2
    center: Any = None
    box: Box | None = None

    def __post_init__(self) -> None:
        if not (np.isfinite(self.radius) and self.radius >= 0):
            raise ModelError(f"sparse-ball radius must be finite and >= 0, got {self.radius}")
        if int(self.k) != self.k or self.k < 0:
            raise ModelError(f"sparsity k must be a nonnegative integer, got {self.k}")
        object.__setattr__(self, "norm", _norm_order(self.norm))
        if self.center is not None:
            object.__setattr__(self, "center", _vector(self.center))
        if self.box is not None:
            c = np.zeros(np.broadcast(self.box.lb, self.box.ub).shape) if self.center is None else self.center
            if not self.box.contains(c, 0.0):
                raise ModelError("a sparse ball intersected with a box needs its center inside the box "
                                 "(unchanged entries keep the center's value); move the center or the bounds")

    def _center(self, size: int) -> np.ndarray:
        c = np.zeros(size) if self.center is None else self.center
        if c.shape != (size,):
            raise InvalidData(f"sparse ball centered at {c.size} entries applied to a vector of {size}")
        return c

    def __call__(self, v: np.ndarray) -> np.ndarray:
        """Keep the k entries whose change gains most, then project them onto the ball (and box)."""
        v = _vector(v)
        c = self._center(v.size)
        d = v - c
        lo, hi = _box_offsets(self.box, c, v.size)
        reach = d if lo is None else np.clip(d, lo, hi)
        if self.norm == np.inf:
            reach = np.clip(reach, -self.radius, self.radius)
        gain = d ** 2 - (d - reach) ** 2
        keep = np.argsort(-gain, kind="stable")[: int(self.k)]
        out = np.zeros_like(d)
        out[keep] = _project_ball(d[keep], float(self.radius), float(self.norm),
                                  None if lo is None else lo[keep], None if hi is None else hi[keep])
        return c + out

    def contains(self, v: np.ndarray, tol: float = 1e-9) -> bool:
        """At most k entries differ from the center by more than tol, and the norm is within radius + tol."""
        v = _vector(v)
        d = v - self._center(v.size)
        sparse = int(np.count_nonzero(np.abs(d) > tol)) <= self.k
        return (sparse and _norm(d, self.norm) <= self.radius + tol
                and (self.box is None or self.box.contains(v, tol)))

    def with_box(self, lb: np.ndarray, ub: np.ndarray) -> "SparseNormBall":
        """The same sparse ball intersected with the box (exact for linf; see the module docstring)."""
        box = Box(lb, ub) if self.box is None else self.box.with_box(lb, ub)
        return SparseNormBall(self.radius, self.k, self.norm, self.center, None if box.is_free else box)


BlockSpec = Mapping[str, Projection] | Iterable[tuple[slice | str, Projection]]
"""Blocks as {name: projection} or [(slice or name, projection), ...]."""


class Blocks(Projection):
    """One projection per block of entries of a vector of total_size; entries in no block are free.

    `blocks` maps keys to projections, as a dict or as (key, projection) pairs (slices are not hashable
    in Python 3.11); a key is a slice or an upper-variable name resolved through `layout`
    (see `Blocks.for_problem`).
    """

    def __init__(self, blocks: BlockSpec, total_size: int, layout: Mapping[str, slice] | None = None) -> None:
        owner = np.zeros(total_size, dtype=bool)
        parts = []
        for key, proj in (blocks.items() if isinstance(blocks, Mapping) else blocks):
            if not isinstance(proj, Projection):
                raise ModelError(f"block {key!r}: {type(proj).__name__} is not a Projection "
                                 "(use Box, NormBall, SparseNormBall or Blocks)")
            block = _block_slice(key, layout)
            idx = np.arange(total_size)[block]
            if idx.size == 0:
                raise ModelError(f"block {key!r} selects no entries of a vector of size {total_size}")
            if owner[idx].any():
                raise ModelError(f"block {key!r} overlaps another block; blocks must be disjoint")
            owner[idx] = True
            parts.append((block if block.step in (None, 1) else idx, proj))  # a slice reads a view, not a copy
        self.total_size = int(total_size)
        self._parts: tuple[tuple[np.ndarray | slice, Projection], ...] = tuple(parts)

    @classmethod
    def for_problem(cls, problem: BilevelProblem, blocks: BlockSpec) -> "Blocks":
        """Blocks over a problem's flat upper vector, keyed by upper-variable names or slices."""
        layout = problem.upper_layout()
        return cls(blocks, sum(s.stop - s.start for s in layout.values()), layout)

    def _check(self, v: np.ndarray) -> np.ndarray:
        v = _vector(v)
        if v.size != self.total_size:
            raise InvalidData(f"block projection of size {self.total_size} applied to a vector of {v.size}")
        return v

    def __call__(self, v: np.ndarray) -> np.ndarray:
        """Project each block with its own projection; other entries are unchanged."""
        v = self._check(v)
        out = v.copy()
        for idx, proj in self._parts:
            out[idx] = proj(v[idx])
        return out

    def contains(self, v: np.ndarray, tol: float = 1e-9) -> bool:
        """Whether every block lies in its set."""
        v = self._check(v)
        return all(proj.contains(v[idx], tol) for idx, proj in self._parts)

    def on(self, block: slice) -> Projection | None:
        """The projection of the entries in `block` alone (its parts shifted; one part covering it: that part's own
        projection), or None where a part is not a slice inside it or outside it."""
        inside = []
        for idx, proj in self._parts:
            if not isinstance(idx, slice):
                return None
            if idx.start >= block.start and idx.stop <= block.stop:
                inside.append((slice(idx.start - block.start, idx.stop - block.start), proj))
            elif idx.start < block.stop and idx.stop > block.start:
                return None
        size = block.stop - block.start
        if len(inside) == 1 and inside[0][0] == slice(0, size):
            return inside[0][1]
        out = Blocks((), size)
        out._parts = tuple(inside)
        return out

    def with_box(self, lb: np.ndarray, ub: np.ndarray) -> "Blocks":
        """Each block intersected with its part of the box; the entries in no block get the box itself."""
        lb = np.broadcast_to(np.asarray(lb, dtype=float), (self.total_size,))
        ub = np.broadcast_to(np.asarray(ub, dtype=float), (self.total_size,))
        free = np.ones(self.total_size, dtype=bool)
        parts = []
        for idx, proj in self._parts:
            free[idx] = False
            parts.append((idx, proj.with_box(lb[idx], ub[idx])))
        if free.any():
            parts.append((np.flatnonzero(free), Box(lb[free], ub[free])))
        out = Blocks((), self.total_size)
        out._parts = tuple(parts)
        return out


def _block_slice(key: Any, layout: Mapping[str, slice] | None) -> slice:
    if isinstance(key, slice):
        return key
    if isinstance(key, str) and layout is not None and key in layout:
        return layout[key]
    known = ", ".join(layout) if layout else "none (pass layout, or use Blocks.for_problem)"
    raise ModelError(f"block {key!r} is neither a slice nor a known upper variable; known: {known}")
