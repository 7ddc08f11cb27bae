"""SDP lower level: convex quadratic (or linear) objective, affine constraints and LMIs affine in y."""

from __future__ import annotations

import dataclasses
import functools
from dataclasses import dataclass
from functools import cached_property
from typing import Callable

import casadi as ca
import numpy as np

from ..defaults import param
from ..errors import ModelError, SolverFailed
from ..parameters import CompiledFunction, ValueAndJacobian
from ..vech import unvech, vech, vech_sx
from .base import LowerSolution
from .convexity import psd_violation
from .polish import Lmi
from .quadratic import QPData, QuadraticLower, clarabel_direct, point_context, solve_qp_clarabel

def range_basis(matrix: np.ndarray, rtol: float) -> np.ndarray:
    """Orthonormal basis (columns) of the column space of matrix: singular values <= rtol * the largest count as
    zero."""
    if not np.any(matrix):
        return np.zeros((matrix.shape[0], 0))
    u, sing, _ = np.linalg.svd(matrix, full_matrices=False)
    return u[:, : int(np.count_nonzero(sing > rtol * sing[0]))]


def solve_square(matrix: np.ndarray, rhs: np.ndarray) -> tuple[np.ndarray, int]:
    """matrix^-1 rhs, or the minimum-norm least-squares solution if matrix is singular (a non-unique solution); and
    the rank used (full when the LU solve succeeds)."""
    try:
        return np.linalg.solve(matrix, rhs), matrix.shape[0]
    except np.linalg.LinAlgError:
        solution, _, rank, _ = np.linalg.lstsq(matrix, rhs, rcond=None)
        return solution, int(rank)


@functools.cache
def _vech_maps(n: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The vec positions of vech's entries (vech(S) = vec(S)[rows]), the duplication matrix D (vec S = D vech S) and
    the symmetric basis matrices (unvech of each unit vector, stacked)."""
    index = np.arange(n * n).reshape(n, n, order="F")
    rows = vech(index)
    dup = np.zeros((n * n, rows.size))
    dup[rows, np.arange(rows.size)] = 1.0
    dup[vech(index.T), np.arange(rows.size)] = 1.0
    return rows, dup, dup.T.reshape(rows.size, n, n).transpose(0, 2, 1)


def _vech_stack(mats: np.ndarray, rows: np.ndarray) -> np.ndarray:
    """vech of each matrix of a stack (S, n, n), as columns (n(n+1)/2 x S)."""
    return mats.transpose(0, 2, 1).reshape(mats.shape[0], -1)[:, rows].T


@dataclass(frozen=True)
class ConicKKT:
    """r(w; x) = [grad_y L ; lam * g ; h ; vech((M_k Z_k + Z_k M_k) / 2)] = 0 in w = (y, lam, mu, vech Z_k).

    At a strictly complementary, nondegenerate solution dr/dw is nonsingular (Alizadeh, Haeberly & Overton
    1998): y*(x) is then differentiable with dw/dx = -(dr/dw)^-1 dr/dx.
    """

    residual: Callable      # (x, w) -> (r, dr/dw), numpy
    residual_x: Callable    # (x, w) -> dr/dx
    sizes: tuple[int, ...]     # n_y, n_g, n_h, then vech sizes of the Z_k
    psd_dims: tuple[int, ...]


@dataclass
class SemidefiniteLower(QuadraticLower):
    """min 1/2 y'Py + q'y s.t. Ay + b <= 0, Ey + e = 0, M_k(x, y) = M_k0(x) + sum_j y_j M_kj(x) >= 0."""

    kind = "sdp"

    def __post_init__(self) -> None:
        super().__post_init__()
        self._fixed_lmis: tuple[int, tuple[Lmi, ...]] | None = None  # (parameter revision, lmi_data) of a fixed SDP
        self._last_point: tuple[tuple, QPData, tuple] | None = None
        self._chosen: tuple[int, LowerSolution] | None = None  # (parameter revision, the learner's own solution)
        self._solved: dict[str, tuple[int, LowerSolution]] = {}  # conic solves of an SDP that ignores x, by role
        self.min_norm = True
        """Whether the hypergradient engine applies select_min_norm to its solutions (False: the polished solver's
        point, e.g. the exact ridge solution of a regularized learner as its solver returns it)."""

    def lmi_data(self, x: np.ndarray) -> tuple[Lmi, ...]:
        """(M_k0, d vec(M_k)/dy) for every LMI at upper point x. Where the SDP ignores x: once per parameter values, by
        reverse sweeps (no symbolic Jacobian, which on large LMIs costs more than the attack it serves)."""
        x = self.check_point(x)
        if not self.fixed:
            out = self._lmi(x)
            return tuple((np.asarray(out[2 * k]), np.asarray(out[2 * k + 1]).reshape(-1, self.n_y))
                         for k in range(len(self.psd)))
        if self._fixed_lmis is None or self._fixed_lmis[0] != self.params.revision:
            zero = np.zeros(self.n_y)
            sweeps = [sweep(x, zero) for sweep in self._lmi_sweeps]
            for value, jac in sweeps:  # kept and shared: read only
                value.setflags(write=False)
                jac.setflags(write=False)
            self._fixed_lmis = (self.params.revision, tuple((value.reshape(m.shape, order="F"), jac)
                                                            for (value, jac), m in zip(sweeps, self.psd)))
        return self._fixed_lmis[1]

    @cached_property
    def _lmi_sweeps(self) -> list[ValueAndJacobian]:
        """(x, y) -> vec M_k and d vec(M_k)/dy for every LMI, by reverse sweeps."""
        return [ValueAndJacobian(self.params, f"lmi{k}", [self.x, self.y], ca.vec(m), 1) for k, m in enumerate(self.psd)]

    @cached_property
    def _lmi(self) -> CompiledFunction:
        """x -> M_k(x, 0) and d vec(M_k)/dy for every LMI, symbolic (an SDP that moves with x reads them at every x)."""
        zero = ca.DM.zeros(self.n_y)
        outs = []
        for m in self.psd:
            outs += [ca.substitute(m, self.y, zero), ca.substitute(ca.jacobian(ca.vec(m), self.y), self.y, zero)]
        return self.params.function("lmi_coeffs", [self.x], outs)

    def lmi_jacobians(self, x: np.ndarray) -> list[np.ndarray]:
        """d vec(M_k)/dy at x for every LMI, from lmi_data."""
        return [jac for _, jac in self.lmi_data(x)]

    def reference_solve(self, x: np.ndarray) -> LowerSolution:
        """The SDP solved at x with cvxpy + Clarabel and polished onto its optimal face (the certificate's independent
        re-solve; where the SDP ignores x, once per parameter values); Z_k are the LMI multipliers
        (L = f - sum <Z_k, M_k>)."""
        return self._once("reference", x, lambda: solve_qp_clarabel(self.data(x), point_context(x), self.lmi_data(x)))

    def solve(self, x: np.ndarray) -> LowerSolution:
        """The learner's solution at x: the chosen one (choose), else Clarabel's point refined by kkt_newton on this
        SDP's KKT system and selected (select); where the SDP ignores x, once per parameter values (apart from
        reference_solve)."""
        chosen = self.chosen()
        return chosen if chosen is not None else self._once("solve", x, lambda: self._refined_solve(x))

    def _refined_solve(self, x: np.ndarray) -> LowerSolution:
        """Clarabel's point (its own interface) refined by kkt_newton and selected; SolverFailed where the SDP moves
        with x and the refined residual stays above defaults["sdp.polished_tol"] (no strictly complementary solution:
        y*(x) has no derivative there)."""
        verified = self.constant_hessian and self.convexity_probe is not None  # the declaration's PSD check
        raw = clarabel_direct(self.data(x), point_context(x), verified, self.lmi_data(x))
        sol, residual = self.kkt_newton(x, raw)
        if residual > (tol := param("sdp.polished_tol")) and not self.fixed:
            raise SolverFailed(f"the SDP {point_context(x)} has KKT residual {residual:.1e} > {tol:g} after "
                               "Newton polishing (no strictly complementary solution found): its solution's derivative "
                               "is not defined there; move x or regularize the lower objective (e.g. raise reg)")
        return self.select(x, sol)

    def select(self, x: np.ndarray, sol: LowerSolution) -> LowerSolution:
        """select_min_norm(x, sol), or sol where min_norm is off."""
        return self.select_min_norm(x, sol) if self.min_norm else sol

    def _once(self, role: str, x: np.ndarray, compute: Callable[[], LowerSolution]) -> LowerSolution:
        """compute(), kept under `role` while the SDP ignores x and the parameter values hold."""
        kept = self._solved.get(role)
        if self.fixed and kept is not None and kept[0] == self.params.revision:
            return dataclasses.replace(kept[1])
        sol = compute()
        if self.fixed:
            self._solved[role] = (self.params.revision, dataclasses.replace(sol))
        return sol

    def choose(self, sol: LowerSolution) -> None:
        """Make sol the solution of this SDP, which must not depend on x, until a parameter changes: a learner's own
        choice among non-unique optima (e.g. one conic solver's answer), used by every method, the hypergradient
        engine (unpolished, unselected) and the local probe; the certificate still re-solves independently."""
        if not self.fixed:
            raise ModelError("choose: this SDP depends on the upper variables, so no one solution serves every x")
        self._chosen = (self.params.revision, sol)

    def chosen(self) -> LowerSolution | None:
        """The solution set by choose, while the parameter values it was chosen at hold; else None."""
        return self._chosen[1] if self._chosen is not None and self._chosen[0] == self.params.revision else None

    @cached_property
    def conic_kkt(self) -> ConicKKT:
        """The KKT residual with PSD complementarity: r and dr/dw numerically from the SDP's data at x (it is affine in
        y with affine LMIs, so no symbolic derivative is needed); dr/dx symbolically, built on first use."""
        psd_dims = tuple(int(m.size1()) for m in self.psd)
        sizes = (self.n_y, int(self.g.numel()), int(self.h.numel()), *(k * (k + 1) // 2 for k in psd_dims))
        return ConicKKT(self._kkt_residual, lambda x, w: self._kkt_residual_x(x, w), sizes, psd_dims)

    def _point_data(self, x: np.ndarray) -> tuple[QPData, tuple[tuple[np.ndarray, np.ndarray], ...]]:
        """data(x) and lmi_data(x), kept for the last x and parameter values (Newton steps evaluate the residual at one
        x repeatedly)."""
        key = (np.asarray(x, dtype=float).tobytes(), self.params.revision)
        if self._last_point is None or self._last_point[0] != key:
            self._last_point = (key, self.data(x), self.lmi_data(x))
        return self._last_point[1], self._last_point[2]

    def _kkt_residual(self, x: np.ndarray, w: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(r, dr/dw) at (x, w): stationarity P y + q + A'lam + E'mu - sum_k J_k' vec Z_k, lam * g, h and
        vech((M_k Z_k + Z_k M_k) / 2), with J_k = d vec(M_k)/dy and vec Z_k = D_k vech Z_k (duplication)."""
        d, lmis = self._point_data(x)
        sizes = self.conic_kkt.sizes
        ny = sizes[0]
        y, lam, mu, *zv = np.split(np.asarray(w, dtype=float).ravel(), np.cumsum(sizes)[:-1])
        g = d.A @ y + d.b
        stationarity = d.P @ y + d.q + d.A.T @ lam + d.E.T @ mu
        n_lin = ny + lam.size + mu.size
        jac = np.zeros((sum(sizes), sum(sizes)))
        jac[:ny, :ny] = d.P
        jac[:ny, ny: ny + lam.size] = d.A.T
        jac[:ny, ny + lam.size: n_lin] = d.E.T
        jac[ny: ny + lam.size, :ny] = lam[:, None] * d.A
        jac[ny: ny + lam.size, ny: ny + lam.size] = np.diag(g)
        jac[ny + lam.size: n_lin, :ny] = d.E
        products, start = [], n_lin
        for (m0, jm), z_vech, k in zip(lmis, zv, self.conic_kkt.psd_dims):
            rows, dup, basis = _vech_maps(k)
            z = unvech(z_vech, k)
            m = m0.reshape(k, k, order="F") + (jm @ y).reshape(k, k, order="F")
            stationarity = stationarity - jm.T @ z.reshape(-1, order="F")
            products.append(vech(0.5 * (m @ z + z @ m)))
            block = slice(start, start + z_vech.size)
            m_y = jm.T.reshape(ny, k, k).transpose(0, 2, 1)  # d M / dy_j, stacked
            jac[:ny, block] = -jm.T @ dup
            jac[block, :ny] = _vech_stack(0.5 * (m_y @ z + z @ m_y), rows)
            jac[block, block] = _vech_stack(0.5 * (m @ basis + basis @ m), rows)
            start += z_vech.size
        r = np.concatenate([stationarity, lam * g, d.E @ y + d.e, *products])
        return r, jac

    @cached_property
    def _kkt_residual_x(self) -> Callable:
        """(x, w) -> dr/dx, symbolic (the x-derivative the adjoint needs where the SDP depends on x)."""
        kkt = self.kkt()
        products = [vech_sx(0.5 * (ca.mtimes(m, z) + ca.mtimes(z, m))) for m, z in zip(self.psd, kkt.Z)]
        r = ca.vertcat(kkt.stationarity, kkt.lam * self.g, self.h, *products)
        w = ca.vertcat(self.y, kkt.lam, kkt.mu, *kkt.Z_vech)
        return self.params.function("kkt_residual_x", [self.x, w], [ca.jacobian(r, self.x)])

    def pack(self, sol: LowerSolution) -> np.ndarray:
        """w = (y, lam, mu, vech Z_k) of a solution."""
        return np.concatenate([sol.y, sol.lam, sol.mu] + [vech(z) for z in sol.Z])

    def unpack(self, w: np.ndarray, like: LowerSolution, x: np.ndarray, solver: str) -> LowerSolution:
        """The solution with vector w (status from `like`, objective evaluated at x)."""
        parts = np.split(w, np.cumsum(self.conic_kkt.sizes)[:-1])
        zs = [unvech(v, n) for v, n in zip(parts[3:], self.conic_kkt.psd_dims)]
        return LowerSolution(parts[0], self.evaluate(x, parts[0])[0], parts[1], parts[2], zs, like.status, solver)

    def kkt_residual(self, x: np.ndarray, sol: LowerSolution) -> float:
        """max |r(w; x)| at a solution."""
        return float(np.abs(np.asarray(self.conic_kkt.residual(x, self.pack(sol))[0])).max(initial=0.0))

    def in_cones(self, x: np.ndarray, sol: LowerSolution) -> bool:
        """Whether g <= 0, lam >= 0 and every M_k, Z_k is PSD up to defaults["sdp.psd_tol"] (relative)."""
        _, g, _, mats = self.evaluate(x, sol.y)
        scalar = np.all(g <= param("sdp.psd_tol") * (1.0 + np.abs(g))) and np.all(sol.lam >= -param("sdp.psd_tol"))
        return bool(scalar) and all(psd_violation(m) <= param("sdp.psd_tol") * (1.0 + float(np.abs(m).max()))
                                    for m in list(mats) + list(sol.Z))

    def kkt_newton(self, x: np.ndarray, sol: LowerSolution, steps: int = 4) -> tuple[LowerSolution, float]:
        """Newton steps on r(w; x) = 0 from sol while the residual falls; returns the best iterate inside the
        cones and its residual (an iterate a hair outside a cone is stepped through, not returned)."""
        kkt = self.conic_kkt
        w = self.pack(sol)
        r, jac = (np.asarray(v) for v in kkt.residual(x, w))
        best = last = float(np.abs(r).max(initial=0.0))
        label = sol.solver if sol.solver.endswith(" + KKT Newton polish") else f"{sol.solver} + KKT Newton polish"
        for _ in range(steps):
            w = w + solve_square(jac, -r.ravel())[0]
            r, jac = (np.asarray(v) for v in kkt.residual(x, w))
            value = float(np.abs(r).max(initial=0.0))
            if not value < last:
                break
            last = value
            trial = self.unpack(w, sol, x, label)
            if value < best and self.in_cones(x, trial):
                sol, best = trial, value
            if value < 1e-14:
                break
        return sol, best

    def continue_from(self, x: np.ndarray, near: LowerSolution,
                      steps: int | None = None) -> tuple[LowerSolution, float] | None:
        """The solution at x by `steps` Newton steps (None: defaults["sdp.continuation_steps"]) on r(w; x) = 0 from
        `near`, a solution at a nearby upper point (continuation, no conic solve), with its residual; None unless an
        iterate inside the cones reaches defaults["sdp.continuation_tol"] (then solve afresh). A KKT point inside the
        cones is optimal (the SDP is convex)."""
        sol, residual = self.kkt_newton(x, near, param("sdp.continuation_steps", steps))
        return (sol, residual) if sol is not near and residual <= param("sdp.continuation_tol") else None

    def seen_directions(self, x: np.ndarray) -> np.ndarray:
        """Orthonormal basis S (n_y x k) of the smallest P-invariant subspace holding the rows of A, E, q' and every
        LMI coefficient d vec(M_k)/dy: the SDP sees y only through S'y and a ridge on the rest. Along the rest
        stationarity reads (T'PT) T'y = 0 (T spans the rest), so the exact solution of a ridge-regularized SDP lies
        in span S, and without a ridge its projection S S'y is the minimum-norm point of the optimal set (singular
        values below defaults["sdp.free_rtol"] times the largest count as zero)."""
        d = self.data(x)
        # + 0.0 turns -0 into 0: LAPACK's reflectors take the sign of a zero, so data declared as parameters (whose
        # products give -0) and as constants (folded to 0) would give two equally valid bases
        rows = np.vstack([d.A, d.E, d.q[None, :], *(jac for _, jac in self.lmi_data(x))]) + 0.0
        basis = range_basis(rows.T, param("sdp.free_rtol"))
        p_scale = float(np.abs(d.P).max(initial=0.0))
        while basis.shape[1] < self.n_y:  # close under P (Krylov): then the rest is P-invariant too
            moved = d.P @ basis
            leak = moved - basis @ (basis.T @ moved)
            if not np.abs(leak).max(initial=0.0) > param("sdp.free_rtol") * p_scale:
                break
            basis = range_basis(np.hstack([basis, leak / p_scale]), param("sdp.free_rtol"))
        return basis

    def select_min_norm(self, x: np.ndarray, sol: LowerSolution) -> LowerSolution:
        """sol projected onto the seen directions: the SDP's value, constraints and multipliers stay; it removes the
        solver's error where only a ridge acts (tiny curvature) or picks the minimum-norm optimum without one."""
        basis = self.seen_directions(x)
        if basis.shape[1] == self.n_y:
            return sol
        unseen = sol.y - basis @ (basis.T @ sol.y)
        y = sol.y - (unseen - basis @ (basis.T @ unseen))  # twice: the seen part moves by roundoff of the rest only
        return dataclasses.replace(sol, y=y, objective=float(self.evaluate(x, y)[0]),
                                   solver=f"{sol.solver} + minimum-norm selection")

    def jacobians(self, x: np.ndarray, sol: LowerSolution) -> tuple[np.ndarray, np.ndarray]:
        """(dr/dw, dr/dx) at a solution: the implicit-derivative system of y*(x)."""
        w = self.pack(sol)
        return np.asarray(self.conic_kkt.residual(x, w)[1]), np.asarray(self.conic_kkt.residual_x(x, w))

    def kkt_solve(self, x: np.ndarray, K: np.ndarray, rhs: np.ndarray) -> tuple[np.ndarray, int]:
        """Z with K' Z = rhs for K = dr/dw, by LU (nonsingular at a strictly complementary, nondegenerate
        solution), else the minimum-norm least-squares solution; and the rank used."""
        return solve_square(K.T, rhs)

    def adjoint(self, x: np.ndarray, sol: LowerSolution, grad_y: np.ndarray) -> tuple[np.ndarray, bool]:
        """(dr/dx)' Z with (dr/dw)' Z = (grad_y, 0), one column per column of grad_y: the derivative of functions
        of (x, y) through y*(x) is their x-gradient minus this (the adjoint method); and whether dr/dw was singular.
        Singular along the free directions (a non-unique solution), grad_y is first projected off them: the
        derivative of the minimum-norm selection, exact where the free directions do not move with x; otherwise
        one element of a generalized derivative."""
        K, R = self.jacobians(x, sol)
        rhs = np.vstack([grad_y, np.zeros((K.shape[0] - grad_y.shape[0], grad_y.shape[1]))])
        Z, rank = self.kkt_solve(x, K, rhs)
        if rank < K.shape[0]:
            basis = self.seen_directions(x)
            if basis.shape[1] < self.n_y:
                rhs[: self.n_y] = basis @ (basis.T @ grad_y)
                Z, rank = self.kkt_solve(x, K, rhs)
        return R.T @ Z, rank < K.shape[0]
