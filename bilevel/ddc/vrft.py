"""Virtual Reference Feedback Tuning (Campi, Lecchini & Savaresi 2002) as a structured least-squares learner.

Regression (the paper's lemma): target u (or L u), regressor Phi(y) with column
i = T_{beta_i} T_L (T_{M_r^{-1}} - I) y, applied as filters in O(N nk), never as N x N matrices.
Phi is linear in y, so Phi(y + a) = Phi(y) + Phi(a).

Conventions.
``prefilter=None`` (or ``"none"``): the data are already filtered by L, as in the paper, and
the learner regresses u on Phi(y). A transfer function L: the learner regresses L u on
T_{beta_i} T_L (T_{M_r^{-1}} - I) y.
``boundary="zero-final"`` (paper): r_t = M_r^{-1} y with y_t = 0 for t >= N, all N rows used.
``boundary="drop"``: the last d = reldeg(M_r) rows, whose virtual reference would need unseen
samples y_N.., are dropped from the regression (as common VRFT toolboxes do).
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import cached_property
from typing import Literal

import control
import numpy as np
import scipy.linalg
from numpy.typing import ArrayLike

from bilevel.errors import InvalidData, RankDeficientRegressor, UnknownOption
from bilevel.ddc.bases import Basis, basis_polynomials, controller_tf
from bilevel.ddc.operators import LTIOperator, filter_columns, virtual_error_operator
from bilevel.ddc.systems import SystemLike, as_tf
from bilevel.lower.least_squares import thin_qr

Boundary = Literal["zero-final", "drop"]
BOUNDARIES: tuple[str, ...] = ("zero-final", "drop")


def _frozen(x: np.ndarray) -> np.ndarray:
    x = np.array(x, dtype=float)
    x.flags.writeable = False
    return x


def _signal(name: str, x: ArrayLike) -> np.ndarray:
    x = np.asarray(x, dtype=float)
    if x.ndim != 1:
        raise InvalidData(f"{name} must be a 1-D signal, got shape {x.shape}")
    if not np.all(np.isfinite(x)):
        bad = np.flatnonzero(~np.isfinite(x))
        raise InvalidData(
            f"{name} contains {bad.size} NaN/inf samples (first at t = {bad[0]}); "
            "remove or interpolate them before fitting"
        )
    return x


def _pair(u: ArrayLike, y: ArrayLike, suffix: str = "") -> tuple[np.ndarray, np.ndarray]:
    u, y = _signal("u" + suffix, u), _signal("y" + suffix, y)
    if u.size != y.size:
        raise InvalidData(f"u{suffix} and y{suffix} must have equal length, got {u.size} and {y.size}")
    return u, y


_ONE = np.ones(1)  # the numerator of the basis's common all-pole filter 1/D


@dataclass(frozen=True)
class VRFTRegressor:
    """The linear maps of the VRFT regression: y -> Phi(y), u -> targets, and Phi's adjoint.

    The basis is applied over its common denominator D: one all-pole filter 1/D, then each
    numerator as a short FIR on the same signal (a lag matrix times the numerator coefficients).
    """

    error: LTIOperator
    prefilter: LTIOperator | None
    basis: tuple[LTIOperator, ...]
    drop: int
    basis_num: np.ndarray
    basis_den: np.ndarray

    @cached_property
    def _delays(self) -> bool:
        """Whether the numerators over the common denominator are the delays 1, q^-1, ... in order (basis_num the
        identity, as for the PID-like bases): Phi is then the lag matrix itself, no product."""
        return self.basis_num.shape[0] == self.basis_num.shape[1] and np.array_equal(
            self.basis_num, np.eye(self.basis_num.shape[0]))

    def _lags(self, w: np.ndarray) -> np.ndarray:
        """The lag matrix (n, width) of a signal w (n,), or one per column of w (n, m): shape (m, n, width)."""
        n, width = w.shape[0], self.basis_num.shape[1]
        padded = np.zeros((n + width - 1,) + w.shape[1:])
        padded[width - 1:] = w
        windows = np.lib.stride_tricks.sliding_window_view(padded, width, axis=0)[..., ::-1]  # (n, [m,] width)
        return np.ascontiguousarray(windows if w.ndim == 1 else np.moveaxis(windows, 1, 0))  # one copy

    @property
    def n_params(self) -> int:
        """Number of controller parameters nk."""
        return len(self.basis)

    def rows(self, n: int) -> int:
        """Number of regression rows for a record of n samples."""
        return n - self.drop

    def error_signal(self, y: ArrayLike) -> np.ndarray:
        """Virtual error (T_{M_r^{-1}} - I) y, filtered by L when the learner owns the prefilter (y a signal, or signals
        as columns)."""
        e = self.error.apply(y)
        return e if self.prefilter is None else self.prefilter.apply(e)

    def __call__(self, y: ArrayLike) -> np.ndarray:
        """Phi(y), shape (rows, nk); linear in y."""
        y = _signal("y", y)
        w = filter_columns(_ONE, self.basis_den, self.error_signal(y))
        lag = self._lags(w)
        return (lag if self._delays else lag @ self.basis_num.T)[: self.rows(y.size)]

    def stack(self, ys: ArrayLike) -> np.ndarray:
        """Phi of each row of ys (m x n), shape (m, rows, nk): the filters run on all rows in one call each."""
        return self.stack_lags(self.stack_signals(ys))

    def stack_signals(self, ys: ArrayLike) -> np.ndarray:
        """The signal of each row of ys (m x n) whose lags make up its Phi (1/D of the virtual error), as columns
        (n, m)."""
        ys = np.asarray(ys, dtype=float)
        if ys.ndim != 2 or not np.all(np.isfinite(ys)):
            raise InvalidData(f"ys must be a 2-D array of finite signals (one per row), got shape {ys.shape}")
        return filter_columns(_ONE, self.basis_den, self.error_signal(ys.T))

    def stack_lags(self, w: np.ndarray) -> np.ndarray:
        """Phi from stack_signals' columns w (n, m), shape (m, rows, nk)."""
        lag = self._lags(w)
        return (lag if self._delays else lag @ self.basis_num.T)[:, : self.rows(w.shape[0])]

    @property
    def lags_are_regressors(self) -> bool:
        """Whether Phi(y) is the lag matrix of its signal itself (a basis of delays): then Phi(y) + Phi(y') equals the
        lags of the two signals' sum bit for bit (each entry the same one addition)."""
        return self._delays

    def targets(self, u: ArrayLike) -> np.ndarray:
        """The regressed targets: u (or L u) on the regression rows."""
        u = _signal("u", u)
        target = u if self.prefilter is None else self.prefilter.apply(u)
        return target[: self.rows(u.size)]

    def stack_targets(self, us: ArrayLike) -> np.ndarray:
        """targets of each row of us (m x n), shape (m, rows): the prefilter runs on all rows in one call."""
        us = np.asarray(us, dtype=float)
        rows = self.rows(us.shape[1])
        return (us if self.prefilter is None else self.prefilter.apply(us.T).T)[:, :rows]

    def targets_adjoint(self, g: np.ndarray, n: int) -> np.ndarray:
        """Adjoint of u -> targets(u) for records of n samples (g a vector or columns): pad the dropped rows, then
        L^T."""
        padded = np.concatenate([g, np.zeros((n - g.shape[0],) + g.shape[1:])])
        return padded if self.prefilter is None else self.prefilter.adjoint(padded)

    def adjoint(self, g: ArrayLike) -> np.ndarray:
        """Gradient in y of <g, Phi(y)>: sum_i T_i^T g_i for g of shape (rows, nk), returned with length N."""
        g = np.asarray(g, dtype=float)
        if g.ndim != 2 or g.shape[1] != self.n_params:
            raise InvalidData(f"g must have shape (rows, {self.n_params}), got {g.shape}")
        return self._adjoints(g[None])[:, 0]

    def stack_adjoint(self, gs: ArrayLike) -> np.ndarray:
        """adjoint of each gs[i] (m x rows x nk), shape (m, N): the filters run on all of them in one call each."""
        gs = np.asarray(gs, dtype=float)
        if gs.ndim != 3 or gs.shape[2] != self.n_params:
            raise InvalidData(f"gs must have shape (m, rows, {self.n_params}), got {gs.shape}")
        return self._adjoints(gs).T

    def stack_adjoint_outer(self, us: ArrayLike, vs: ArrayLike) -> np.ndarray:
        """stack_adjoint of G_i = sum_l us[l, i] vs[l, i]' (us: L x m x rows, vs: L x m x nk), shape (m, N), without
        forming the G_i (a sum of outer products: the adjoint's taps read the factors)."""
        us, vs = np.asarray(us, dtype=float), np.asarray(vs, dtype=float)
        if us.ndim != 3 or vs.shape != us.shape[:2] + (self.n_params,):
            raise InvalidData(f"us must have shape (L, m, rows) and vs (L, m, {self.n_params}), got {us.shape} and "
                              f"{vs.shape}")
        if self.drop:
            us = np.concatenate([us, np.zeros(us.shape[:2] + (self.drop,))], axis=2)
        vs = vs if self._delays else vs @ self.basis_num
        n = us.shape[2]
        fir = np.zeros((n, us.shape[1]))
        for j in range(vs.shape[2]):  # sum_j b_j g_{t+j} with g = sum_l u_l v_l'
            fir[: n - j] += np.einsum("lmt,lm->tm", us[:, :, j:], vs[:, :, j])
        return self._back(fir).T

    def _adjoints(self, gs: np.ndarray) -> np.ndarray:
        """sum_i T_i^T g_i for each g of gs (m, rows, nk), as columns (N, m)."""
        if self.drop:
            gs = np.concatenate([gs, np.zeros((gs.shape[0], self.drop, gs.shape[2]))], axis=1)
        h = gs if self._delays else gs @ self.basis_num
        n = h.shape[1]
        fir = np.zeros((n, h.shape[0]))
        for j in range(h.shape[2]):  # adjoint of the FIR part: sum_j b_j g_{t+j}
            fir[: n - j] += h[:, j:, j].T
        return self._back(fir)

    def _back(self, fir: np.ndarray) -> np.ndarray:
        """The adjoint's filters after its FIR taps, on columns: 1/D reversed, L^T, the virtual error's adjoint."""
        back = filter_columns(_ONE, self.basis_den, fir[::-1])[::-1]
        if self.prefilter is not None:
            back = self.prefilter.adjoint(back)
        return self.error.adjoint(back)

    def dense(self, n: int) -> np.ndarray:
        """Stack of the matrices T_i with Phi(y)[:, i] = T_i y, shape (nk, rows, n); small n only."""
        error = self.error.dense(n)
        if self.prefilter is not None:
            error = self.prefilter.dense(n) @ error
        return np.stack([(beta.dense(n) @ error)[: self.rows(n)] for beta in self.basis])


def vrft_regressor(
    reference: SystemLike,
    basis: Basis,
    prefilter: SystemLike | Literal["none"] | None = None,
    boundary: Boundary = "zero-final",
) -> VRFTRegressor:
    """Build the VRFT regressor for reference model M_r, controller basis beta and prefilter L."""
    if boundary not in BOUNDARIES:
        raise UnknownOption(f"boundary={boundary!r} is not understood; use one of {BOUNDARIES}")
    if len(basis) == 0:
        raise InvalidData("the controller basis is empty; pass at least one transfer function")
    error = virtual_error_operator(reference)
    if isinstance(prefilter, str):
        if prefilter != "none":
            raise UnknownOption(f"prefilter={prefilter!r} is not understood; use None, 'none' or a transfer function")
        prefilter = None
    pre = None if prefilter is None else LTIOperator(prefilter)
    drop = error.advance if boundary == "drop" else 0
    nums, den = basis_polynomials(basis)
    if nums.shape[1] > den.size:
        raise InvalidData("a basis function is improper (numerator degree above denominator degree); "
                          "only proper controller basis functions can be applied causally")
    nums = np.hstack([np.zeros((nums.shape[0], den.size - nums.shape[1])), nums])
    return VRFTRegressor(error, pre, tuple(LTIOperator(beta) for beta in basis), drop, nums / den[0], den / den[0])


def normal_equations(phi: ArrayLike, target: ArrayLike) -> tuple[np.ndarray, np.ndarray]:
    """(Phi^T Phi, Phi^T u): the nk x nk Gram matrix and right-hand side of the least-squares fit."""
    phi = np.asarray(phi, dtype=float)
    return phi.T @ phi, phi.T @ np.asarray(target, dtype=float)


def vrft_loss(phi: ArrayLike, target: ArrayLike, theta: ArrayLike) -> float:
    """Learner's loss (1/N) ||u - Phi theta||^2 over the N regression rows."""
    residual = np.asarray(target, dtype=float) - np.asarray(phi, dtype=float) @ np.asarray(theta, dtype=float)
    return float(residual @ residual / residual.size)


def _rank_check(what: str, singular_values: np.ndarray, rows: int, rcond: float | None) -> float:
    cols = singular_values.size
    top = singular_values[0]
    cond = float(top / singular_values[-1]) if singular_values[-1] > 0 else float("inf")
    tol = top * (max(rows, cols) * np.finfo(float).eps if rcond is None else rcond)
    rank = int(np.sum(singular_values > tol))
    if top == 0 or rank < cols:
        raise RankDeficientRegressor(
            f"{what} ({rows} x {cols}) is rank deficient: numerical rank {rank} < {cols}, condition "
            f"number {cond:.3g}; the data do not excite all {cols} basis functions: use a richer or "
            "longer input, or fewer / linearly independent basis functions"
        )
    return cond


def least_squares(
    phi: ArrayLike, target: ArrayLike, rcond: float | None = None
) -> tuple[np.ndarray, float]:
    """(theta, cond(Phi)): min ||target - Phi theta|| by QR; raises RankDeficientRegressor if rank < nk."""
    phi, target = np.asarray(phi, dtype=float), np.asarray(target, dtype=float)
    q, r = thin_qr(phi)
    cond = _rank_check("VRFT regressor Phi", np.linalg.svd(r, compute_uv=False), phi.shape[0], rcond)
    return scipy.linalg.solve_triangular(r, q.T @ target), cond


def instrumental_variables(
    phi: ArrayLike, instruments: ArrayLike, target: ArrayLike, rcond: float | None = None
) -> tuple[np.ndarray, float]:
    """(theta, cond(Z^T Phi)): the IV estimate solving Z^T Phi theta = Z^T u (Campi et al. 2002, Sec. 4)."""
    phi, z = np.asarray(phi, dtype=float), np.asarray(instruments, dtype=float)
    gram = z.T @ phi
    cond = _rank_check("instrument correlation Z^T Phi", np.linalg.svd(gram, compute_uv=False), phi.shape[0], rcond)
    return np.linalg.solve(gram, z.T @ np.asarray(target, dtype=float)), cond


@dataclass(frozen=True)
class VRFTFit:
    """A fitted VRFT controller with the regression it came from and the options used."""

    theta: np.ndarray
    loss: float
    phi: np.ndarray
    u_used: np.ndarray
    controller: control.TransferFunction
    condition_number: float
    boundary: Boundary
    prefilter: control.TransferFunction | None
    instrumental: bool


def fit_vrft(
    u: ArrayLike,
    y: ArrayLike,
    reference: SystemLike,
    basis: Basis,
    *,
    prefilter: SystemLike | Literal["none"] | None = None,
    boundary: Boundary = "zero-final",
    instruments: tuple[ArrayLike, ArrayLike] | None = None,
    dt: float | bool | None = None,
    rcond: float | None = None,
) -> VRFTFit:
    """Fit theta of K = beta^T theta by VRFT on data (u, y); instruments = (u, y2) of a repeated experiment."""
    u, y = _pair(u, y)
    regressor = vrft_regressor(reference, basis, prefilter, boundary)
    if regressor.rows(u.size) < regressor.n_params:
        raise InvalidData(
            f"{u.size} samples give {regressor.rows(u.size)} regression rows, fewer than the "
            f"{regressor.n_params} parameters; collect more data"
        )
    phi, target = regressor(y), regressor.targets(u)
    if instruments is None:
        theta, cond = least_squares(phi, target, rcond)
    else:
        u2, y2 = _pair(*instruments, suffix="2")
        if u2.size != u.size or not np.allclose(u2, u):
            raise InvalidData(
                "instrumental variables need a repeated experiment with the same input u "
                "(Campi et al. 2002); the second experiment's input differs"
            )
        theta, cond = instrumental_variables(phi, regressor(y2), target, rcond)
    if dt is None:
        dt = reference.dt if isinstance(reference, control.lti.LTI) else True
    return VRFTFit(
        theta=_frozen(theta),
        loss=vrft_loss(phi, target, theta),
        phi=_frozen(phi),
        u_used=_frozen(target),
        controller=controller_tf(basis, theta, dt),
        condition_number=cond,
        boundary=boundary,
        prefilter=None if regressor.prefilter is None else as_tf(prefilter, dt),
        instrumental=instruments is not None,
    )
