"""The affine least squares of bilevel.lower.affine_least_squares on a batch of instances that share their linear
maps (one learner design, many data sets and budgets), and the exact target block of bilevel.solvers.engine.affine_ls
on it: the fits, the target block in closed form and the implicit gradient, as stacked array operations (batched
filter products, thin QRs, triangular solves, eigenvalues). Per instance the arithmetic is that of AffineLeastSquares
and TargetBlock up to rounding; the rows of every call are a subset of the batch (`rows`), so finished instances drop
out.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Callable

import numpy as np

from ...defaults import param
from .batch_ascent import Points
from .batch_linalg import maximize_quadratics_on_balls, project_l2_balls, r_factor_batch, solve_upper


@dataclass(frozen=True)
class BatchMaps:
    """The shared maps on stacked signals: regressors (m, n_b) -> (m, rows, k) and its adjoint (m, rows, k) -> (m, n_b);
    targets (m, n_a) -> (m, rows) and its adjoint (m, rows, p) -> (m, n_a, p), both None where T a = a[:rows];
    regressor_adjoints_outer (us, vs) -> the adjoint of sum_l us[l] vs[l]' (us: L x m x rows, vs: L x m x k) without
    forming it, where given; signals (m, n_b) -> (n, m) and lags (n, m) -> (m, rows, k), where given, with
    regressors(B) = lags(signals(B)) and the regressors of a sum of signals equal to the sum of theirs bit for bit
    (AffineLSBatch.S0)."""

    regressors: Callable[[np.ndarray], np.ndarray]
    regressor_adjoints: Callable[[np.ndarray], np.ndarray]
    targets: Callable[[np.ndarray], np.ndarray] | None = None
    target_adjoints: Callable[[np.ndarray], np.ndarray] | None = None
    regressor_adjoints_outer: Callable[[np.ndarray, np.ndarray], np.ndarray] | None = None
    signals: Callable[[np.ndarray], np.ndarray] | None = None
    lags: Callable[[np.ndarray], np.ndarray] | None = None


@dataclass
class BatchFit:
    """Fits of some rows: a (m, n_a), regressor C, target d, theta, the R of C's thin QR (C = Q R; Q = C R^{-1} is not
    kept), R^{-1}, and whether C had full rank (theta and the rest are meaningless where not)."""

    a: np.ndarray
    C: np.ndarray
    d: np.ndarray
    theta: np.ndarray
    R: np.ndarray
    R_inv: np.ndarray
    ok: np.ndarray


@dataclass
class UpperBatch:
    """J(theta) to maximize per instance: value(rows, thetas) -> (m,), gradient(rows, thetas) -> (m, k), and its
    constant Hessians (instances, k, k) where J is quadratic."""

    value: Callable[[np.ndarray, np.ndarray], np.ndarray]
    gradient: Callable[[np.ndarray, np.ndarray], np.ndarray]
    hessian: np.ndarray | None = None


@dataclass
class AffineLSBatch:
    """theta*(a, b) = argmin ||d0_i + T a - (C0_i + R(b)) theta||^2 for each instance i, the maps shared; S0 (n, m),
    where given, the signals with C0_i = maps.lags(S0[:, [i]]), so that a fit forms C0_i + R(b) as the lags of one
    sum of signals (the same numbers, without gathering C0)."""

    C0: np.ndarray
    d0: np.ndarray
    maps: BatchMaps
    n_a: int
    n_b: int
    S0: np.ndarray | None = None

    def target(self, A: np.ndarray) -> np.ndarray:
        """T a of each row of A."""
        return A[:, : self.d0.shape[1]] if self.maps.targets is None else self.maps.targets(A)

    def fit(self, rows: np.ndarray, A: np.ndarray | None, B: np.ndarray) -> BatchFit:
        """The fits at (a, b) of the given rows (a, b the rows of A and B; A None: a = 0, the target d0):
        AffineLeastSquares.fit each (Householder's R and Q'd of [C d], r_factor_batch)."""
        if self.S0 is not None:
            C = self.maps.lags(self.S0[:, rows] + self.maps.signals(B))
        else:
            C = self.C0[rows] + self.maps.regressors(B)
        d = self.d0[rows] if A is None else self.d0[rows] + self.target(A)
        R, R_inv, Qd = r_factor_batch(C, d)
        diag = np.diagonal(R, axis1=1, axis2=2)
        ok = np.all(diag != 0, axis=1) & np.all(np.isfinite(R.reshape(len(rows), -1)), axis=1)
        R_safe = np.where(ok[:, None, None], R, np.eye(R.shape[-1]))
        theta = solve_upper(R_safe, Qd)
        a = np.zeros((len(rows), self.n_a)) if A is None else A
        return BatchFit(a, C, d, theta, R_safe, R_inv, ok)

    def target_block(self, rows: np.ndarray, B: np.ndarray) -> tuple[BatchFit, np.ndarray, np.ndarray | None]:
        """(fits at (0, b), S, W) per row as AffineLeastSquares.target_block: theta*(W v, b) = theta_c + S v with
        ||W v|| = ||v||; W None where T is a slice (S = R^{-1}, a = [Q v; 0])."""
        s0 = self.fit(rows, None, B)
        if self.maps.targets is None:
            return s0, s0.R_inv, None
        W = self.maps.target_adjoints(s0.C @ s0.R_inv)  # T'Q
        lam, V = np.linalg.eigh(np.swapaxes(W, 1, 2) @ W)
        lam = np.maximum(lam, 1e-14 * lam.max(axis=1, keepdims=True))
        root = np.sqrt(lam)
        S = s0.R_inv @ ((V * root[:, None, :]) @ np.swapaxes(V, 1, 2))
        return s0, S, W @ ((V / root[:, None, :]) @ np.swapaxes(V, 1, 2))

    def moved(self, s0: BatchFit, S: np.ndarray, W: np.ndarray | None, v: np.ndarray) -> BatchFit:
        """The fits at a = W v of the target blocks (AffineLeastSquares.moved)."""
        if W is None:
            qv = (s0.C @ (s0.R_inv @ v[:, :, None]))[:, :, 0]  # Q v
            a = np.zeros((v.shape[0], self.n_a))
            a[:, : qv.shape[1]] = qv
            d = s0.d + qv
        else:
            a = np.einsum("mnk,mk->mn", W, v)
            d = s0.d + self.target(a)
        return BatchFit(a, s0.C, d, s0.theta + np.einsum("mij,mj->mi", S, v), s0.R, s0.R_inv, s0.ok)

    def gradient(self, s: BatchFit, g_theta: np.ndarray, target: bool = True) -> tuple[np.ndarray | None, np.ndarray]:
        """(dJ/da, dJ/db) at the fits for dJ/dtheta = g_theta (AffineLeastSquares.gradient): with
        w = (C'C)^{-1} g_theta and r = d - C theta, dJ/da = T'(C w), dJ/db = R'(r w' - (C w) theta'); dJ/da None
        unless `target`."""
        w = np.einsum("mij,mj->mi", s.R_inv, np.einsum("mji,mj->mi", s.R_inv, g_theta))
        both = s.C @ np.stack([w, s.theta], axis=2)  # C w and C theta: one pass over C
        cw, residual = both[:, :, 0], s.d - both[:, :, 1]
        if self.maps.regressor_adjoints_outer is not None:
            g_b = self.maps.regressor_adjoints_outer(np.stack([residual, -cw]), np.stack([w, s.theta]))
        else:
            g_b = self.maps.regressor_adjoints(residual[:, :, None] * w[:, None, :] - cw[:, :, None] * s.theta[:, None, :])
        if not target:
            return None, g_b
        if self.maps.target_adjoints is None:
            g_a = np.zeros((cw.shape[0], self.n_a))
            g_a[:, : cw.shape[1]] = cw
        else:
            g_a = self.maps.target_adjoints(cw[:, :, None])[:, :, 0]
        return g_a, g_b


@dataclass
class TargetBlockBatch:
    """The exact target block (affine_ls.TargetBlock) of every instance: a at its global optimum on its ball (radius
    per instance) for the given b, J quadratic (upper.hessian)."""

    learner: AffineLSBatch
    upper: UpperBatch
    radius: np.ndarray

    def solve(self, rows: np.ndarray, B: np.ndarray) -> BatchFit:
        """The fits with a at its best value for each row's b (radius 0: a = 0; where every row's radius is 0, the fits
        at (0, b) without the block's step, as TargetBlock skips it)."""
        if not np.any(self.radius[rows]):
            return self.learner.fit(rows, None, B)
        s0, S, W = self.learner.target_block(rows, B)
        St = np.swapaxes(S, 1, 2)
        grad = self.upper.gradient(rows, s0.theta)
        A = 0.5 * (St @ self.upper.hessian[rows] @ S)
        v = maximize_quadratics_on_balls(A, 0.5 * np.einsum("mij,mj->mi", St, grad), self.radius[rows])
        return self.learner.moved(s0, S, W, v)


@dataclass
class BatchOracle:
    """The batched twin of affine_ls.Oracle with its TargetBlock (the exact block a at its optimum for each b) for
    bilevel.solvers.engine.block_exact_batch: J at the best a for each row's b, with its gradient in b (Danskin), and
    the fits and canonical hypergradients (grad of -J in x = (a, b)) the verdict's probe reads."""

    block: TargetBlockBatch

    @property
    def learner(self) -> AffineLSBatch:
        return self.block.learner

    @property
    def upper(self) -> UpperBatch:
        return self.block.upper

    def evaluate(self, inst: np.ndarray, B: np.ndarray) -> tuple[np.ndarray, Points]:
        """J at each row's b with a at its optimum (-inf where the learner has no unique fit), and the points' theta,
        a and gradient g of J in b (most trial points are accepted: computed while the fit's arrays are at hand)."""
        with np.errstate(all="ignore"):
            fit = self.block.solve(inst, B)
            f = self.upper.value(inst, fit.theta)
            g = self.learner.gradient(fit, self.upper.gradient(inst, fit.theta), target=False)[1]
        f = np.where(fit.ok & np.isfinite(f), f, -np.inf)
        return f, {"theta": fit.theta, "a": fit.a, "g": g}

    def fits(self, inst: np.ndarray, X: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """theta*(x) at each row x = (a, b) of X, and whether the fit is unique."""
        n = self.learner.n_a
        with np.errstate(all="ignore"):
            fit = self.learner.fit(inst, X[:, :n], X[:, n:])
        return fit.theta, fit.ok

    def hypergradients(self, inst: np.ndarray, X: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """The canonical gradient of -J(theta*(x)) in x = (a, b) at each row of X, and whether the fit is unique."""
        n = self.learner.n_a
        with np.errstate(all="ignore"):
            fit = self.learner.fit(inst, X[:, :n], X[:, n:])
            g_a, g_b = self.learner.gradient(fit, self.upper.gradient(inst, fit.theta))
        return -np.concatenate([g_a, g_b], axis=1), fit.ok


def conditioning_descent(learner: AffineLSBatch, rows: np.ndarray, radius: np.ndarray) -> np.ndarray:
    """The conditioning start (bilevel.solvers.engine.starts) of each row's learner from zero poisoning: b after
    defaults["starts.conditioning_steps"] projected steps of one radius down the gradient of the smallest eigenvalue
    of C'C (C = C0 + R(b); a, on which C'C does not depend, stays at zero), b on the l2 ball of its radius; a row
    whose step vanishes stops there. Computed defaults["batch.chunk"] rows at a time."""
    B = np.zeros((len(rows), learner.n_b))
    size, steps = int(param("batch.chunk")), int(param("starts.conditioning_steps"))
    for s in range(0, len(rows), size):
        part = np.arange(s, min(s + size, len(rows)))
        for _ in range(steps):
            C = learner.C0[rows[part]] + learner.maps.regressors(B[part])
            P = np.swapaxes(C, 1, 2) @ C
            v = np.linalg.eigh(0.5 * (P + np.swapaxes(P, 1, 2)))[1][:, :, 0]
            cv = np.einsum("mrk,mk->mr", C, v)
            if learner.maps.regressor_adjoints_outer is not None:
                g = 2.0 * learner.maps.regressor_adjoints_outer(cv[None], v[None])
            else:
                g = 2.0 * learner.maps.regressor_adjoints(cv[:, :, None] * v[:, None, :])
            unit = np.sqrt(np.sum((g * radius[part, None]) ** 2, axis=1))
            ok = (unit > 0) & np.isfinite(unit)
            part, g, unit = part[ok], g[ok], unit[ok]
            if part.size == 0:
                break
            B[part] = project_l2_balls(B[part] - g * (radius[part] ** 2 / unit)[:, None], radius[part])
    return B
