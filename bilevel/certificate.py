"""Certify a bilevel point: KKT residuals of the lower level plus an independent re-solve of it.

Every residual is scaled row by row: a row passes when r_i <= tol * (1 + s_i), and the certificate
reports max_i r_i / (1 + s_i) (so a check passes when its reported value is <= tol), with s_i the size
of what the row balances:

- stationarity, row j of grad_y L: the largest of |grad_y f|_j, |J_g' lam|_j, |J_h' mu|_j, |LMI term|_j;
- lower feasibility, row i of g (violation max(g_i, 0)) or h (|h_i|): sum_j |dg_i/dy_j y_j|, the size
  of its y-terms; an LMI: its largest entry;
- dual feasibility (max(-lam_i, 0), and the negative eigenvalues of Z_k): the largest multiplier;
- complementarity |lam_i g_i|: |lam_i| (1 + s_i of g_i); <Z_k, M_k>: |Z_k|_F |M_k|_F;
- upper feasibility, rows of G, H and the bounds of x: the size of the row's terms, as for g;
- the lower-level gap f(x, y) - f*(x): |f*(x)|.

f*(x) is the re-solve's value, unless the re-solve reports itself inaccurate or f(x, y) is below it: then, for an
LP/QP/SDP lower level (quadratic f, affine constraints), weak duality bounds it, f*(x) >= the minimum in y of the
Lagrangian at the point's multipliers and at the re-solve's (lam clipped at 0, Z_k projected onto the PSD cone;
finite where the Lagrangian's gradient lies in the range of the Hessian of f), and where either is finite the gap
is measured from the larger (`lower_bound`): y passes when its value is within tol of a proven lower bound. An
interior-point re-solve can stop short of the optimum where the objective is nearly flat on the optimal face of its
dominant term (a tiny ridge on a non-unique SDP solution set, the Willems learner's reg = 1e-8: Clarabel then
reports AlmostSolved at a value 1e-5 above the optimum); its value alone would fail an exact y.

`worst` names the worst row of every check. The independent re-solve is cvxpy + Clarabel (or a closed
form) for LP/QP/LS/SDP lower levels, a global optimum; a nonlinear lower level is re-solved by IPOPT
from several starts inside the declared bounds, which is local evidence, not a proof.

Convexity of the lower level is checked at the certified point ("lower_convexity": the Hessians of f and of the
constraints nonlinear in y, scaled smallest eigenvalue, the worst named); the LP/QP re-solve also refuses a Hessian
that is not PSD. For LP/QP/SDP lower levels this is exact at x. For a nonlinear one it is local, so interval bounds
on its Hessians over the declared bounds of y try to prove convexity at x (`convexity_proven`); when they cannot,
the note says that lower-level optimality is local evidence and the method's SOLVED is reported as INACCURATE
(solvers/verdict/finalize.py). The lower_gap check is two-sided: f(x, y) below the re-solved optimum by more than tol
means the re-solve is wrong or y infeasible, and fails.

When the re-solve says the lower solution is unique (reduced Hessian positive definite at it, or, for a
nonlinear lower level, every start reaching the same y), y is compared with the re-solved y through
the upper objective: `upper_at_reference` = F(x, y_ref) is the bilevel-feasible value at x, and the
check "lower_solution" fails when F(x, y) differs from it by more than tol * (1 + |F|) plus what the
spread of the re-solves allows. Upper-level optimality is not certified (no method can for a
non-convex bilevel program).
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace
from typing import TYPE_CHECKING

import numpy as np

from .canonical import in_sense
from .defaults import param
from .errors import BilevelError
from .lower.convexity import convex_on_box, convexity_violation, psd_from_eigen, psd_violation, symmetric_eigen
from .sampling import sample_in_bounds

if TYPE_CHECKING:  # pragma: no cover
    from .canonical import CanonicalBilevel
    from .lower.base import LowerLevel
    from .reduction import KKTPoint

LOCAL_EVIDENCE = "lower-level optimality is local evidence (convexity not proven)"


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
    """Scaled residuals at a point and the verdict (see the module docstring for the scaling).

    lower_gap = f(x, y) - f*(x), f* from an independent solve or lower_bound (scaled by 1 + |f*|); worst: the worst
    row of each check; lower_unique: whether the re-solve found a unique lower solution (None: not decided);
    y_distance: max |y - y_ref|; upper_at_reference: F(x, y_ref) in the canonical (minimization) sense.
    """

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
    worst: dict[str, str] = field(default_factory=dict)
    lower_unique: bool | None = None
    y_distance: float = 0.0
    upper_at_reference: float | None = None
    global_bound: GlobalBound | None = None
    convexity_proven: bool = True
    """False for a nonlinear lower level whose convexity in y (at this x, on the declared bounds of y) interval
    bounds could not prove: lower-level optimality is then local evidence, and a method's SOLVED becomes
    INACCURATE."""
    lower_bound: float | None = None
    """The weak-duality lower bound on f*(x) that lower_gap is measured from (None: from the re-solve's value)."""

    @classmethod
    def bounds_only(cls, bound: GlobalBound) -> "Certificate":
        """The certificate of a global search stopped before any incumbent: no point to check (every residual NaN,
        failed on "point"), only the proven bounds on the optimal value."""
        nan = float("nan")
        return cls(nan, nan, nan, nan, nan, nan, nan, [], "none", nan, False, ("point",),
                   "no incumbent: the search stopped before it found a feasible point; only its bounds are proven",
                   {"point": "no incumbent"}, global_bound=bound)

    def describe_failures(self) -> str:
        """'check (row name), ...' for the failed checks."""
        return ", ".join(f"{k} ({self.worst[k]})" if self.worst.get(k) else k for k in self.failed)

    def __repr__(self) -> str:
        verdict = "passed" if self.passed else f"FAILED ({self.describe_failures()})"
        return (f"Certificate({verdict}; stationarity={self.stationarity:.2e}, lower_feas={self.lower_feasibility:.2e}, "
                f"dual_feas={self.dual_feasibility:.2e}, compl={self.complementarity:.2e}, "
                f"upper_feas={self.upper_feasibility:.2e}, gap={self.lower_gap:.2e} via {self.lower_solver}"
                + ("" if self.global_bound is None else
                   f"; global bounds [{self.global_bound.lower_bound:.10g}, {self.global_bound.upper_bound:.10g}], "
                   f"gap {self.global_bound.gap:.1e}{' proven' if self.global_bound.proven else ' NOT proven'}")
                + ")")


def _worst(residual: np.ndarray, scale: np.ndarray, names: list[str] | str) -> tuple[float, str]:
    """max_i r_i / (1 + s_i) and the name of that row (0 and '' for no rows; NaN counts as worst); names: one per row,
    or a pattern with {} for the row's index (the worst row's name alone is formed: x has thousands of entries)."""
    r = np.asarray(residual, dtype=float).ravel()
    if not r.size:
        return 0.0, ""
    v = r / (1.0 + np.abs(np.asarray(scale, dtype=float).ravel()))
    v = np.where(np.isnan(v), np.inf, v)
    i = int(np.argmax(v))
    return float(v[i]), names.format(i) if isinstance(names, str) else names[i]


def _row_scale(jac: np.ndarray, v: np.ndarray) -> np.ndarray:
    """sum_j |J_ij v_j|: the size of the terms of each row that involve v."""
    jac = np.asarray(jac, dtype=float).reshape(-1, v.size) if v.size else np.zeros((0, 0))
    return np.abs(jac * v[None, :]).sum(axis=1) if jac.size else np.zeros(jac.shape[0])


def _re_solve(canon: "CanonicalBilevel", x: np.ndarray, y: np.ndarray, tol: float):
    """The independent lower solve; for an NLP lower level a multistart. Returns (best, spread, unique, note).

    A problem that carries its own lower solver (e.g. the user's cvxpy problem) is re-solved with it; uniqueness
    is then judged on the canonical lower level's solution."""
    low = canon.lower
    if canon.lower_reference is not None:
        ref = canon.lower_reference(canon.x, x, y)
        own = None if low.psd else low.solve(x)
        unique = None if own is None else _reduced_hessian_unique(low, x, own, tol)
        face = _on_face(low, ref, own, tol)
        return face, 0.0, unique, f"independent re-solve: {ref.solver}" + (
            "; y from the canonical re-solve polished onto its optimal face (the same value)" if face is not ref else "")
    if not low.nonlinear:
        ref = low.reference_solve(x)
        return ref, 0.0, _reduced_hessian_unique(low, x, ref, tol), ""
    rng = np.random.default_rng(0)
    lb, ub = canon.y_lb, canon.y_ub
    starts = [np.clip(y, lb, ub), np.clip(np.zeros_like(y), lb, ub)]
    starts += [sample_in_bounds(lb, ub, rng, 3.0) for _ in range(param("certificate.nlp_starts") - 2)]
    sols, errors = [], []
    for y0 in starts:
        try:
            sols.append(low.solve(x, y0))
        except BilevelError as exc:
            errors.append(exc)
    if not sols:
        raise errors[0]
    best = min(sols, key=lambda s: s.objective)
    near = [s for s in sols if s.objective <= best.objective + tol * (1.0 + abs(best.objective))]
    spread = max(float(np.max(np.abs(s.y - best.y), initial=0.0)) for s in near)
    unique = len(near) == len(sols) and spread <= np.sqrt(tol) * (1.0 + float(np.max(np.abs(best.y), initial=0.0)))
    note = (f"nonlinear lower level: re-solved by IPOPT from {len(starts)} starts ({len(sols)} converged), "
            "local evidence, not a proof of lower-level optimality")
    return best, spread, unique, note


def _on_face(low: "LowerLevel", ref, own, tol: float):
    """The user's re-solve `ref` with y replaced by the canonical convex re-solve `own` (polished onto its optimal
    face), where both reach the same value within tol: an interior-point solve of the user's formulation stops
    ~sqrt(eps) off a degenerate face (e.g. DeePC's l1 slack penalty: 5e-5 in y at equal values), which would fail a
    correct y. A nonlinear lower level's local solve, or values differing (a wrong canonical form), keep the user's y."""
    if own is None or low.nonlinear or abs(own.objective - ref.objective) > tol * (1.0 + abs(ref.objective)):
        return ref
    return replace(ref, y=own.y)


def _dual_bound(low: "LowerLevel", x: np.ndarray, y: np.ndarray, lam: np.ndarray, mu: np.ndarray,
                Z: list[np.ndarray], curvature: tuple[np.ndarray, np.ndarray | None]) -> float:
    """min over y' of the Lagrangian f + lam'g + mu'h - sum <Z_k, M_k> of an LP/QP/SDP lower level at x, with lam
    clipped at 0 and Z_k projected onto the PSD cone: a lower bound on f*(x) by weak duality. The Lagrangian is
    quadratic in y: from its value and gradient s at y and the eigenpairs (w, V) of the Hessian of f (symmetric_eigen),
    L(y) - sum_i (V's)_i^2 / (2 w_i), or -inf where V's has a component with w_i = 0 (unbounded below)."""
    lam, Z = np.maximum(lam, 0.0), [psd_from_eigen(*symmetric_eigen(np.asarray(z, dtype=float))) for z in Z]
    f, g, h, mats = low.evaluate(x, y)
    grad_f, jg, jh, jpsd = low.derivatives(x, y)
    value = f + lam @ g + mu @ h - sum(float(np.sum(z * m)) for z, m in zip(Z, mats))
    s = grad_f + jg.T @ lam + jh.T @ mu
    for jac, z in zip(jpsd, Z):
        s = s - jac.T @ z.reshape(-1, order="F")
    w, v = curvature
    sv = s if v is None else v.T @ s
    curved = w > w.size * np.finfo(float).eps * float(np.abs(w).max(initial=0.0))
    if np.any(sv[~curved] != 0.0) or not np.isfinite(value):
        return -np.inf
    return float(value - 0.5 * np.sum(sv[curved] ** 2 / w[curved]))


def _y_box(canon: "CanonicalBilevel") -> tuple[np.ndarray, np.ndarray]:
    """The declared bounds of y (infinite where none)."""
    n = int(canon.y.numel())
    return (np.full(n, -np.inf) if canon.y_lb is None else canon.y_lb,
            np.full(n, np.inf) if canon.y_ub is None else canon.y_ub)


def _reduced_hessian_unique(low, x: np.ndarray, ref, tol: float) -> bool | None:
    """Unique if the Hessian of f is positive definite on the null space of the equalities and the
    strongly active inequalities at the re-solved point (sufficient for a convex program); None with LMIs."""
    if low.psd:
        return None
    _, g, _, _ = low.evaluate(x, ref.y)
    _, jg, jh, _ = low.derivatives(x, ref.y)
    strong = (ref.lam > np.sqrt(tol)) & (g > -np.sqrt(tol))
    rows = np.vstack([jh, jg[strong]])
    if rows.size:
        _, sv, vt = np.linalg.svd(rows)
        rank = int(np.sum(sv > param("certificate.unique_rtol") * max(1.0, float(sv.max(initial=0.0)))))
        null = vt[rank:].T
    else:
        null = np.eye(low.n_y)
    if null.shape[1] == 0:
        return True
    hess = low.hessian(x, ref.y)
    reduced = hess if rows.size == 0 else null.T @ hess @ null
    shift = param("certificate.unique_rtol") * max(1.0, float(np.abs(hess).max()))
    try:  # smallest eigenvalue > shift, by a Cholesky factorization of the shifted matrix
        np.linalg.cholesky(0.5 * (reduced + reduced.T) - shift * np.eye(reduced.shape[0]))
    except np.linalg.LinAlgError:
        return False
    return True


def certify_point(canon: "CanonicalBilevel", point: "KKTPoint", tol: float | None = None, sense: str = "min") -> Certificate:
    """Scaled KKT residuals of the lower level at `point` and its gap to an independent lower-level solve, accepted
    up to tol (None: defaults["certificate.tol"]). The independent re-solve of a nonlinear lower level starts from
    the point's y, the default and random points (defaults["certificate.nlp_starts"] in all). sense: the declared
    upper sense ("max" or "min"), in which messages quote upper objective values."""
    tol = float(param("certificate.tol", tol))
    low = canon.lower
    x, y = point.x, point.y
    f, g, h, mats = low.evaluate(x, y)
    grad_f, jg, jh, jpsd = low.derivatives(x, y)
    terms = [np.abs(grad_f), np.abs(jg.T @ point.lam), np.abs(jh.T @ point.mu)]
    terms += [np.abs(j.T @ np.asarray(z).reshape(-1, order="F")) for j, z in zip(jpsd, point.Z)]
    stat, _ = low.stationarity(x, y, point.lam, point.mu, point.Z)
    y_names = "grad_y L[{}]"
    sg, sh = _row_scale(jg, y), _row_scale(jh, y)
    checks: dict[str, tuple[float, str]] = {}
    checks["stationarity"] = _worst(np.abs(stat), np.max(terms, axis=0), y_names)
    feas = [_worst(np.maximum(g, 0.0), sg, low.g_names), _worst(np.abs(h), sh, low.h_names)]
    feas += [_worst(np.array([psd_violation(m)]), np.array([np.abs(m).max(initial=0.0)]), [n])
             for m, n in zip(mats, low.psd_names)]
    checks["lower_feasibility"] = max(feas, key=lambda t: t[0])
    lam_size = float(np.max(np.abs(np.concatenate([point.lam, point.mu])), initial=0.0))
    dual = [_worst(np.maximum(-point.lam, 0.0), np.full(point.lam.size, lam_size), low.g_names)]
    dual += [_worst(np.array([psd_violation(z)]), np.array([np.abs(z).max(initial=0.0)]), [f"Z of {n}"])
             for z, n in zip(point.Z, low.psd_names)]
    checks["dual_feasibility"] = max(dual, key=lambda t: t[0])
    comp = [_worst(np.abs(point.lam * g), np.abs(point.lam) * (1.0 + sg), low.g_names)]
    comp += [_worst(np.array([abs(float(np.sum(z * m)))]), np.array([np.linalg.norm(z) * np.linalg.norm(m)]), [n])
             for z, m, n in zip(point.Z, mats, low.psd_names)]
    checks["complementarity"] = max(comp, key=lambda t: t[0])
    checks["lower_convexity"] = convexity_violation(low, x, y)
    F, G, H, jG, jH = canon.upper_values(x, y)
    xy = np.concatenate([x, y])
    upper = [_worst(np.maximum(G, 0.0), _row_scale(jG, xy), canon.G_names or "G[{}]"),
             _worst(np.abs(H), _row_scale(jH, xy), "H[{}]"),
             _worst(np.maximum(canon.x_lb - x, 0.0), np.where(np.isfinite(canon.x_lb), canon.x_lb, 0.0),
                    "x.lb[{}]"),
             _worst(np.maximum(x - canon.x_ub, 0.0), np.where(np.isfinite(canon.x_ub), canon.x_ub, 0.0),
                    "x.ub[{}]")]
    checks["upper_feasibility"] = max(upper, key=lambda t: t[0])
    note, unique, spread, F_ref = "", None, 0.0, None
    try:
        ref, spread, unique, note = _re_solve(canon, x, y, tol)
        f_ref, y_ref, solver = ref.objective, ref.y, ref.solver
    except BilevelError as exc:
        f_ref, y_ref, solver, note = np.nan, np.full(low.n_y, np.nan), "none", f"independent lower solve failed: {exc}"
    gap = (f - f_ref) / (1.0 + abs(f_ref)) if np.isfinite(f_ref) and np.isfinite(f) else np.inf
    checks["lower_gap"] = (abs(gap), "" if gap >= -tol else "f(x, y) is below the re-solved optimum f*(x): the "
                           "re-solve is wrong or y is infeasible")
    bound = None
    if low.dual_bounded and np.isfinite(gap) and (gap < -tol or ref.status != "optimal"):
        curvature = symmetric_eigen(np.asarray(low.hessian(x, y), dtype=float).reshape(low.n_y, low.n_y))
        bound = max(_dual_bound(low, x, y, point.lam, point.mu, point.Z, curvature),
                    -np.inf if canon.lower_reference is not None else
                    _dual_bound(low, x, y_ref, ref.lam, ref.mu, ref.Z, curvature))
        bound = bound if np.isfinite(bound) else None
    if bound is not None:
        gap = (f - bound) / (1.0 + abs(bound))
        checks["lower_gap"] = (abs(gap), f"f*(x) >= {bound:.12g} by weak duality; y's value {f:.12g}, the re-solve's "
                               f"{f_ref:.12g} ({ref.status})" + ("" if gap >= -tol else ": y is below a proven lower "
                                                                 "bound on f*(x), so y is infeasible"))
        if f_ref - f > tol * (1.0 + abs(f_ref)):
            short = (f"the independent re-solve ({ref.status}) is {f_ref - f:.2e} above y's value, which weak duality "
                     f"proves within {max(f - bound, 0.0):.1e} of f*(x)")
            note = "; ".join(filter(None, [note, short]))
    y_distance = float(np.max(np.abs(y - y_ref), initial=0.0)) if np.all(np.isfinite(y_ref)) else np.inf
    if unique and np.isfinite(y_distance):
        F_ref, grad_F = canon.upper_objective_y(x, y_ref)
        F_ref, grad_F = float(F_ref), np.abs(grad_F)
        slack = tol * (1.0 + abs(F_ref)) + float(grad_F @ np.full(low.n_y, spread + tol * (1.0 + np.abs(y_ref).max())))
        checks["lower_solution"] = (abs(F - F_ref) / (slack / tol) if np.isfinite(F) else np.inf,
                                    f"y is {y_distance:.2e} from the unique re-solved y; F there = "
                                    f"{in_sense(F_ref, sense):.10g}")
    proven = not low.nonlinear or convex_on_box(low, x, *_y_box(canon))
    if not proven:
        note = "; ".join(filter(None, [note, LOCAL_EVIDENCE]))
    checks["upper_objective"] = (0.0 if np.isfinite(F) else np.inf, "" if np.isfinite(F) else f"F = {F}")
    failed = tuple(k for k, (v, _) in checks.items() if not v <= tol)
    values = {k: v for k, (v, _) in checks.items()}
    return Certificate(values["stationarity"], values["lower_feasibility"], values["dual_feasibility"],
                       values["complementarity"], values["upper_feasibility"], float(gap),
                       float(f_ref), [float(v) for v in y_ref], solver, tol, not failed, failed, note,
                       {k: name for k, (_, name) in checks.items() if name}, unique, y_distance, F_ref, None, proven,
                       bound)
