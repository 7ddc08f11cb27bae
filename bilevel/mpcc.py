"""The MPCC produced by the single-level reduction, and the complementarity modes that make it an NLP.

A mode is one mechanism with options (as BilevelJuMP's modes): each says how a pair 0 <= G ⟂ H >= 0
(or S >= 0 ⟂ L >= 0 for PSD matrices) becomes NLP constraints, with a relaxation parameter tau that
is an NLP *parameter*, so a relaxation sequence re-solves one NLP for decreasing tau.
"""

from __future__ import annotations

from abc import ABC
from dataclasses import dataclass, field, replace
from typing import Any, Callable

import casadi as ca
import numpy as np

from . import sparse_jacobian
from .defaults import param
from .errors import ModelError, UnsupportedPair
from .parameters import ParameterSet, scalar
from .vech import lower_triangular, vech_sx

Row = tuple[ca.SX, float, float]


@dataclass(frozen=True)
class ScalarPair:
    """Elementwise complementarity 0 <= G ⟂ H >= 0 (e.g. G = -g lower slack, H = its multiplier)."""

    name: str
    G: ca.SX
    H: ca.SX
    labels: tuple[str, ...] = ()


@dataclass(frozen=True)
class PSDPair:
    """Matrix complementarity S >= 0 ⟂ L >= 0 (PSD), i.e. <S, L> = 0 (an LMI and its multiplier)."""

    name: str
    S: ca.SX
    L: ca.SX


def psd_factor(m: np.ndarray, jitter: float = 1e-8) -> np.ndarray:
    """Lower-triangular P with P P' ~ the PSD part of m (eigenvalues clipped at jitter), in vech order.

    P is the Cholesky factor of the rebuilt matrix; where rounding makes that matrix numerically
    indefinite (an ill-conditioned m), P is R' from the QR factorization of diag(sqrt(lambda)) V'
    (P P' = V diag(lambda) V' as well), which cannot fail.
    """
    if not np.all(np.isfinite(m)):
        raise ModelError("a PSD start matrix contains NaN or inf; the warm start cannot be factored")
    vals, vecs = np.linalg.eigh(0.5 * (m + m.T))
    vals = np.maximum(vals, jitter)
    try:
        p = np.linalg.cholesky((vecs * vals) @ vecs.T)
    except np.linalg.LinAlgError:
        r = np.linalg.qr(np.sqrt(vals)[:, None] * vecs.T, mode="r")
        p = (np.sign(np.diag(r))[:, None] * r).T  # positive diagonal, as Cholesky's
    n = m.shape[0]
    return np.concatenate([p[j:, j] for j in range(n)])


@dataclass(frozen=True)
class PSDFactors:
    """Auxiliary factor variables (vech P, vech W) a mode introduced for one PSD pair."""

    pair: PSDPair
    symbols: ca.SX


class ComplementarityMode(ABC):
    """How complementarity pairs become NLP rows; `tau` is the (symbolic) relaxation parameter."""

    tau: float = 0.0

    def __post_init__(self) -> None:
        """A relaxation parameter is a finite number >= 0 (a negative one makes the relaxed set empty); None takes
        defaults["mpcc.tau"]."""
        if getattr(self, "tau", 0.0) is None:
            self.tau = param("mpcc.tau")
        tau = getattr(self, "tau", 0.0)
        if isinstance(tau, bool) or not isinstance(tau, (int, float, np.integer, np.floating)) \
                or not np.isfinite(tau) or tau < 0:
            raise ModelError(f"{type(self).__name__}(tau={tau!r}) is invalid: tau must be a finite number >= 0")

    def scalar_pair(self, pair: ScalarPair, tau: ca.SX) -> list[Row]:
        raise UnsupportedPair(self, "scalar")

    def psd_pair(self, pair: PSDPair, tau: ca.SX) -> tuple[list[Row], PSDFactors]:
        raise UnsupportedPair(self, "PSD")

    def scalar_upper(self, pair: ScalarPair) -> np.ndarray | None:
        """Upper bounds of a scalar pair's rows where they are solve-time data (one compiled NLP serves every value),
        None where the structure fixes them."""
        return None

    @staticmethod
    def _psd_factored(pair: PSDPair, bound: ca.SX | float) -> tuple[list[Row], PSDFactors]:
        """S = P P', L = W W' (P, W lower triangular, new variables) and ||P' W||_F^2 <= bound."""
        n = int(pair.S.size1())
        P, p_sym = lower_triangular(f"P_{pair.name}", n)
        W, w_sym = lower_triangular(f"W_{pair.name}", n)
        m = n * (n + 1) // 2
        rows: list[Row] = [(vech_sx(pair.S - P @ P.T), np.zeros(m), np.zeros(m)),
                           (vech_sx(pair.L - W @ W.T), np.zeros(m), np.zeros(m)),
                           (ca.sumsqr(P.T @ W) - bound, -np.inf, 0.0)]
        return rows, PSDFactors(pair, ca.vertcat(p_sym, w_sym))

    @staticmethod
    def _nonneg(pair: ScalarPair) -> list[Row]:
        n = int(pair.G.numel())
        return [(pair.G, np.zeros(n), np.full(n, np.inf)), (pair.H, np.zeros(n), np.full(n, np.inf))]

    def structure_key(self) -> tuple:
        """What the transcribed NLP's structure depends on (tau is its parameter, not part of it)."""
        return (type(self).__name__,)

    def __repr__(self) -> str:
        return f"{type(self).__name__}(tau={self.tau:g})"


class Exact(ComplementarityMode):
    """G >= 0, H >= 0, G_i H_i <= 0: the unrelaxed MPCC (degenerate for NLP solvers; use for polishing)."""

    def scalar_pair(self, pair: ScalarPair, tau: ca.SX) -> list[Row]:
        n = int(pair.G.numel())
        return self._nonneg(pair) + [(pair.G * pair.H, np.full(n, -np.inf), np.zeros(n))]

    def psd_pair(self, pair: PSDPair, tau: ca.SX) -> tuple[list[Row], PSDFactors]:
        return self._psd_factored(pair, 0.0)


@dataclass(repr=False)
class Scholtes(ComplementarityMode):
    """G >= 0, H >= 0, G_i H_i <= t (Scholtes 2001); t -> 0 recovers the MPCC."""

    tau: float | None = None

    def scalar_pair(self, pair: ScalarPair, tau: ca.SX) -> list[Row]:
        n = int(pair.G.numel())
        return self._nonneg(pair) + [(pair.G * pair.H - tau, np.full(n, -np.inf), np.zeros(n))]

    def psd_pair(self, pair: PSDPair, tau: ca.SX) -> tuple[list[Row], PSDFactors]:
        """S = P P', L = W W', <S, L> = ||P' W||_F^2 <= t."""
        return self._psd_factored(pair, tau)


@dataclass(repr=False)
class Product(ComplementarityMode):
    """G >= 0, H >= 0, sum_i G_i H_i <= eps: one aggregated product constraint per pair."""

    tau: float | None = None

    def scalar_pair(self, pair: ScalarPair, tau: ca.SX) -> list[Row]:
        return self._nonneg(pair) + [(ca.dot(pair.G, pair.H) - tau, -np.inf, 0.0)]

    def psd_pair(self, pair: PSDPair, tau: ca.SX) -> tuple[list[Row], PSDFactors]:
        return self._psd_factored(pair, tau)


@dataclass(repr=False)
class KanzowSchwartz(ComplementarityMode):
    """G >= 0, H >= 0, phi_t(G_i, H_i) <= 0 with the Kanzow–Schwartz (2013) piecewise function."""

    tau: float | None = None

    def scalar_pair(self, pair: ScalarPair, tau: ca.SX) -> list[Row]:
        a, b = pair.G - tau, pair.H - tau
        phi = ca.if_else(a + b >= 0, a * b, -0.5 * (a * a + b * b))
        n = int(pair.G.numel())
        return self._nonneg(pair) + [(phi, np.full(n, -np.inf), np.zeros(n))]


@dataclass(repr=False)
class FischerBurmeister(ComplementarityMode):
    """G + H - sqrt(G^2 + H^2 + 2 mu) = 0: smoothed Fischer–Burmeister (G, H > 0, G H = mu)."""

    tau: float | None = None

    def scalar_pair(self, pair: ScalarPair, tau: ca.SX) -> list[Row]:
        n = int(pair.G.numel())
        phi = pair.G + pair.H - ca.sqrt(pair.G ** 2 + pair.H ** 2 + 2 * tau)
        return [(phi, np.zeros(n), np.zeros(n))]


@dataclass(repr=False)
class Branch(ComplementarityMode):
    """One piece of the MPCC: G_i = 0, H_i >= 0 where side_i is True, else H_i = 0, G_i >= 0 (a regular NLP).

    The sides are row bounds, not structure: every branch of an MPCC is solved by one compiled NLP."""

    sides: dict[str, np.ndarray] = field(default_factory=dict)
    psd_tol: float = 1e-14

    def structure_key(self) -> tuple:
        return ("Branch", self.psd_tol)

    def scalar_pair(self, pair: ScalarPair, tau: ca.SX) -> list[Row]:
        n = int(pair.G.numel())
        upper = self.scalar_upper(pair)
        return [(pair.G, np.zeros(n), upper[:n]), (pair.H, np.zeros(n), upper[n:])]

    def scalar_upper(self, pair: ScalarPair) -> np.ndarray:
        """[ub of G; ub of H]: 0 on the side held at zero, inf on the free one."""
        side = np.asarray(self.sides.get(pair.name, ()), dtype=bool)
        n = int(pair.G.numel())
        if side.shape != (n,):
            raise ModelError(f"Branch: pair {pair.name!r} has {n} entries, got {side.size} sides")
        return np.concatenate([np.where(side, 0.0, np.inf), np.where(side, np.inf, 0.0)])

    def psd_pair(self, pair: PSDPair, tau: ca.SX) -> tuple[list[Row], PSDFactors]:
        """PSD pairs have no finite branch structure: polish them with <S, L> <= psd_tol in factored form
        (a tiny positive bound keeps an interior for the NLP solver; 0 would make the row degenerate)."""
        return self._psd_factored(pair, self.psd_tol)

    def __repr__(self) -> str:
        return f"Branch({ {k: int(np.sum(v)) for k, v in self.sides.items()} } G-active)"


@dataclass
class NLPForm:
    """An NLP min f(x; p) s.t. lbg <= g(x; p) <= ubg, lbx <= x <= ubx; the first n_w entries of x are w,
    the rest are auxiliary variables of the modes (PSD factors), initialized by `start`."""

    x: ca.SX
    f: ca.SX
    g: ca.SX
    p: ca.SX
    lbx: np.ndarray
    ubx: np.ndarray
    lbg: np.ndarray
    ubg: np.ndarray
    p_value: np.ndarray
    n_w: int
    psd_values: Callable | None = None
    params: ParameterSet = field(default_factory=ParameterSet)
    _solvers: dict[str, ca.Function] = field(default_factory=dict, repr=False)
    common_rows: int = 0
    """The first rows of g, which with f every transcription of the MPCC shares (its equalities and inequalities)."""
    _derivatives: dict[str, ca.Function] = field(default_factory=dict, repr=False)
    _shared: dict[str, ca.Function] = field(default_factory=dict, repr=False)
    """Derivative functions of f and the common rows, one dict for every transcription of the MPCC."""

    def start(self, w: np.ndarray) -> np.ndarray:
        """Full NLP start from an MPCC point: w followed by PSD factors of each pair's (S, L) at w."""
        if self.psd_values is None or self.psd_values.n_out() == 0:
            return np.asarray(w, dtype=float)
        mats = [np.asarray(m) for m in self.psd_values(w)]
        return np.concatenate([np.asarray(w, dtype=float)] + [psd_factor(m) for m in mats])

    def solver(self, plugin: str = "ipopt", options: dict[str, Any] | None = None) -> ca.Function:
        """A CasADi nlpsol for this NLP, cached per (plugin, options); IPOPT gets the derivative functions built once
        (derivatives), so another options dict costs no differentiation."""
        key = f"{plugin}:{sorted((options or {}).items())!r}"
        if key not in self._solvers:
            nlp = {"x": self.x, "f": self.f, "g": self.g, "p": ca.vertcat(self.p, self.params.sym)}
            given = dict(options or {})
            if plugin == "ipopt":
                exact = (given.get("ipopt") or {}).get("hessian_approximation", "exact") == "exact"
                given.update(self.derivatives(exact))
            self._solvers[key] = ca.nlpsol("mpcc_nlp", plugin, nlp, given)
        return self._solvers[key]

    def derivatives(self, hessian: bool = True) -> dict[str, ca.Function]:
        """nlpsol's grad_f, jac_g and (if `hessian`) hess_lag functions of this NLP (the upper triangle of the
        Lagrangian's Hessian), built once per transcription, their part from f and the first common_rows rows of g
        once per MPCC (shared)."""
        d, p = self._derivatives, ca.vertcat(self.p, self.params.sym)
        if "jac_g" not in d:
            d["grad_f"] = ca.Function("nlp_grad_f", [self.x, p], [self.f, ca.gradient(self.f, self.x)],
                                      ["x", "p"], ["f", "grad_f_x"])
            d["jac_g"] = ca.Function("nlp_jac_g", [self.x, p], [self.g, self._jacobian()], ["x", "p"],
                                     ["g", "jac_g_x"])
        if hessian and "hess_lag" not in d:
            sigma, lam = ca.SX.sym("lam_f"), ca.SX.sym("lam_g", int(self.g.numel()))
            d["hess_lag"] = ca.Function("nlp_hess_l", [self.x, p, sigma, lam], [ca.triu(self._hessian(sigma, lam))],
                                        ["x", "p", "lam_f", "lam_g"], ["hess_gamma_x_x"])
        return {k: v for k, v in d.items() if hessian or k != "hess_lag"}

    def _jacobian(self) -> ca.SX:
        """dg/dx: the common rows' (functions of w alone) from the shared cache, the mode's rows by sparse_jacobian,
        which differentiates dense rows and columns apart."""
        n, c, params = self.n_w, self.common_rows, self.params.sym
        w, n_aux = self.x[:n], int(self.x.numel()) - n
        if "jacobian" not in self._shared:
            self._shared["jacobian"] = ca.Function("common_jac_g", [w, params],
                                                   [sparse_jacobian.jacobian(self.g[:c], w)])
        common = ca.horzcat(self._shared["jacobian"](w, params), ca.SX(c, n_aux))
        return ca.vertcat(common, sparse_jacobian.jacobian(self.g[c:], self.x))

    def _hessian(self, sigma: ca.SX, lam: ca.SX) -> ca.SX:
        """The Hessian in x of sigma f + lam' g: of f and the common rows from the shared cache, of the mode's rows
        here."""
        n, c, params = self.n_w, self.common_rows, self.params.sym
        w, n_aux = self.x[:n], int(self.x.numel()) - n
        if "hessian" not in self._shared:
            s, l_c = ca.SX.sym("lam_f"), ca.SX.sym("lam_g", c)
            self._shared["hessian"] = ca.Function("common_hess_l", [w, params, s, l_c],
                                                  [ca.hessian(s * self.f + ca.dot(l_c, self.g[:c]), w)[0]])
        common = ca.diagcat(self._shared["hessian"](w, params, sigma, lam[:c]), ca.SX(n_aux, n_aux))
        return common + ca.hessian(ca.dot(lam[c:], self.g[c:]), self.x)[0]


@dataclass
class MPCC:
    """min F(w) s.t. equalities(w) = 0, inequalities(w) <= 0, lbw <= w <= ubw, complementarity pairs.

    `blocks` names the slices of w (x, y, lam, mu, Z_k) so the MPCC can be inspected and inverted.
    """

    w: ca.SX
    lbw: np.ndarray
    ubw: np.ndarray
    objective: ca.SX
    equalities: ca.SX
    inequalities: ca.SX
    pairs: list[ScalarPair | PSDPair]
    blocks: dict[str, slice]
    params: ParameterSet = field(default_factory=ParameterSet)

    def __post_init__(self) -> None:
        scalar = [p for p in self.pairs if isinstance(p, ScalarPair)]
        psd = [p for p in self.pairs if isinstance(p, PSDPair)]
        outs = [self.objective, self.equalities, self.inequalities]
        outs += [ca.vertcat(*[p.G for p in scalar]) if scalar else ca.SX(0, 1),
                 ca.vertcat(*[p.H for p in scalar]) if scalar else ca.SX(0, 1)]
        outs += [m for p in psd for m in (p.S, p.L)]
        self._eval = self.params.function("mpcc_eval", [self.w], outs)
        self._n_psd = len(psd)
        self._nlps: dict[tuple, NLPForm] = {}
        self._shared_derivatives: dict[str, ca.Function] = {}
        self._pair_rows: dict[tuple, dict[str, int]] = {}
        """Per transcription (structure key): the offset in g of each scalar pair's rows."""

    @property
    def n_variables(self) -> int:
        return int(self.w.numel())

    def transcribe(self, mode: ComplementarityMode) -> NLPForm:
        """The NLP obtained by writing every pair with `mode` (tau becomes the NLP parameter); kept per structure, so
        its compiled solvers serve later solves (other tau, other parameter values, other branches)."""
        key = mode.structure_key() if self.pairs else ("no pairs",)
        if key not in self._nlps:
            self._pair_rows[key] = {}
            self._nlps[key] = self._transcribe(mode, self._pair_rows[key])
        form = replace(self._nlps[key], p_value=np.array([mode.tau]))
        ubg, start = form.ubg, self._pair_rows[key]
        for pair in self.pairs:
            if isinstance(pair, ScalarPair) and (upper := mode.scalar_upper(pair)) is not None:
                ubg = ubg.copy() if ubg is form.ubg else ubg
                ubg[start[pair.name]:start[pair.name] + upper.size] = upper
        return replace(form, ubg=ubg)

    def _transcribe(self, mode: ComplementarityMode, offsets: dict[str, int]) -> NLPForm:
        tau = ca.SX.sym("tau")
        n_eq, n_in = int(self.equalities.numel()), int(self.inequalities.numel())
        rows: list[Row] = [(self.equalities, np.zeros(n_eq), np.zeros(n_eq)),
                           (self.inequalities, np.full(n_in, -np.inf), np.zeros(n_in))]
        factors: list[PSDFactors] = []
        for pair in self.pairs:
            if isinstance(pair, ScalarPair):
                offsets[pair.name] = sum(int(r[0].numel()) for r in rows)
                rows += mode.scalar_pair(pair, tau)
            else:
                pair_rows, aux = mode.psd_pair(pair, tau)
                rows += pair_rows
                factors.append(aux)
        g = ca.vertcat(*[r[0] for r in rows])
        lbg = np.concatenate([np.broadcast_to(r[1], (int(r[0].numel()),)) for r in rows]) if rows else np.zeros(0)
        ubg = np.concatenate([np.broadcast_to(r[2], (int(r[0].numel()),)) for r in rows]) if rows else np.zeros(0)
        aux = ca.vertcat(*[f.symbols for f in factors]) if factors else ca.SX(0, 1)
        n_aux = int(aux.numel())
        init = self.params.function("psd_pairs", [self.w], [m for f in factors for m in (f.pair.S, f.pair.L)])
        return NLPForm(ca.vertcat(self.w, aux), self.objective, g, tau,
                       np.concatenate([self.lbw, np.full(n_aux, -np.inf)]),
                       np.concatenate([self.ubw, np.full(n_aux, np.inf)]), lbg.astype(float), ubg.astype(float),
                       np.array([mode.tau]), self.n_variables, init, self.params, common_rows=n_eq + n_in,
                       _shared=self._shared_derivatives)

    def residuals(self, w: np.ndarray) -> dict[str, float]:
        """Max violations at w: equality, inequality (incl. bounds), pair sign, complementarity; a NaN (a function
        outside its domain) is an infinite violation."""
        out = self._eval(np.asarray(w, dtype=float))
        eq = np.abs(np.asarray(out[1]).ravel())
        ineq = np.maximum(np.asarray(out[2]).ravel(), 0.0)
        bounds = np.maximum(np.maximum(self.lbw - w, w - self.ubw), 0.0)
        G, H = np.asarray(out[3]).ravel(), np.asarray(out[4]).ravel()
        sign = np.concatenate([np.maximum(-G, 0.0), np.maximum(-H, 0.0)])
        comp = np.abs(np.minimum(np.maximum(G, 0.0), np.maximum(H, 0.0)))
        for k in range(self._n_psd):
            S, L = np.asarray(out[5 + 2 * k]), np.asarray(out[6 + 2 * k])
            sign = np.concatenate([sign, [max(-np.linalg.eigvalsh(S).min(), 0.0),
                                          max(-np.linalg.eigvalsh(L).min(), 0.0)]])
            comp = np.concatenate([comp, [abs(float(np.sum(S * L)))]])
        top = lambda a: float(np.nan_to_num(a, nan=np.inf).max()) if a.size else 0.0  # noqa: E731
        return {"equality": top(eq), "inequality": max(top(ineq), top(bounds)), "pair_sign": top(sign),
                "complementarity": top(comp)}

    def pair_values(self, w: np.ndarray) -> dict[str, tuple[np.ndarray, np.ndarray]]:
        """(G, H) of every scalar pair at w, by pair name."""
        out = self._eval(np.asarray(w, dtype=float))
        G, H = np.asarray(out[3]).ravel(), np.asarray(out[4]).ravel()
        values, k = {}, 0
        for p in self.pairs:
            if isinstance(p, ScalarPair):
                n = int(p.G.numel())
                values[p.name] = (G[k:k + n], H[k:k + n])
                k += n
        return values

    def objective_value(self, w: np.ndarray) -> float:
        return scalar(self._eval(np.asarray(w, dtype=float))[0])

    def __repr__(self) -> str:
        n_scalar = sum(int(p.G.numel()) for p in self.pairs if isinstance(p, ScalarPair))
        n_psd = sum(1 for p in self.pairs if isinstance(p, PSDPair))
        return (f"MPCC({self.n_variables} variables {dict((k, v.stop - v.start) for k, v in self.blocks.items())}, "
                f"{int(self.equalities.numel())} equalities, {int(self.inequalities.numel())} inequalities, "
                f"{n_scalar} scalar and {n_psd} PSD complementarity pairs)")
