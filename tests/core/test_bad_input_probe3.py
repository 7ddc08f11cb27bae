"""A probe of the surfaces issue "Honest answers III" (44) named, with bad input: linear maps, lower_qp, the residual
tests, identification and DeePC instances, the defended learners, the defaults registry, the methods' limits, resumed
rows and the CLI. Each case ends in exactly one outcome, checked: a named `bilevel.errors` error of the given type
whose message names the problem, a result whose status is not SOLVED, or a value equal to one computed here
independently. Never a raw numpy/scipy/cvxpy/CasADi error, a NaN p-value, a silent truncation or a misread value.
The cases are new (test_bad_input_probe.py and test_bad_input.py hold the earlier probes)."""

from __future__ import annotations

import os
import re
from collections import Counter
from functools import lru_cache
from typing import Any, Callable

import casadi as ca
import numpy as np
import pytest
import scipy.sparse as sp
from scipy import stats
from scipy.sparse.linalg import LinearOperator, aslinearoperator

import bilevel as bl
from bilevel.cli import main
from bilevel.ddc.residual_tests import input_test, regression_tests, variance_test, whiteness_test
from bilevel.errors import BilevelError, InvalidData, ModelError, UnknownName
from bilevel.experiments.identification import ROW_SCHEMA
from bilevel.experiments.sweep import check_fields
from bilevel.files import atomic_open
from bilevel.linear_maps import Operator
from bilevel.problems import registry
from bilevel.problems.deepc_instance import DeePCAttack
from bilevel.problems.deepc_instance import attack_instance as deepc_instance
from bilevel.problems.defended_identification import DefendedIdentification, defended_instance
from bilevel.problems.identification_instance import IdentificationAttack
from bilevel.problems.identification_instance import attack_instance as ident_instance
from tests.conftest import bard_511

STATUS = "status"
"""A case that returns a result whose status is not SOLVED, its message matching."""
VALUE = "value"
"""A case that returns True where its value equals the one computed independently (the match names the check)."""


# -- builders --------------------------------------------------------------------------------------------------------
def _declared(matrix: Any) -> bl.linear_maps.LinearMap:
    p = bl.BilevelProblem("probe3")
    p.upper_variable("x", 2)
    return p.linear_map(matrix)


def _operator(matvec: Callable[[np.ndarray], Any], rmatvec: Callable[[np.ndarray], Any] | None = None,
              dtype: Any = float) -> LinearOperator:
    return LinearOperator((3, 2), matvec=matvec, rmatvec=rmatvec or (lambda v: np.ones(2)), dtype=dtype)


def _lazy_nan_solve() -> bl.BilevelResult:
    """A LinearOperator whose products are fine at the declaration's probe (ones) and NaN once x moves off it."""
    A = np.array([[1.0, 0.5], [0.0, 1.0], [1.0, 1.0]])
    op = LinearOperator((3, 2), matvec=lambda v: A @ v if np.allclose(v, 1.0) else np.full(3, np.nan),
                        rmatvec=lambda v: A.T @ v, dtype=float)
    p = bl.BilevelProblem("nan-operator")
    x = p.upper_variable("x", 2, lb=-1, ub=1)
    y = p.lower_variable("y", 3)
    T = p.linear_map(op)
    p.minimize_upper(ca.sumsqr(y - 1))
    p.minimize_lower(ca.sumsqr(y - T @ x))
    return p.solve("hypergradient", starts=1)


def _qp(**mats: Any) -> bl.BilevelProblem:
    p = bl.BilevelProblem("qp")
    x = p.upper_variable("x", 2, lb=0, ub=1)
    y = p.lower_variable("y", 2)
    p.minimize_upper(ca.sumsqr(y - x))
    p.lower_qp(y, **{"C": np.eye(2), **mats})
    return p


def _expression(fn: Callable[[bl.BilevelProblem, ca.SX, ca.SX], Any]) -> Callable[[], Any]:
    def run() -> Any:
        p = bl.BilevelProblem("expr")
        x = p.upper_variable("x", 2, lb=0, ub=1)
        y = p.lower_variable("y", 2)
        return fn(p, x, y)
    return run


RNG = np.random.default_rng(44)
E1 = RNG.standard_normal((1, 120))
E2 = RNG.standard_normal((2, 120))
Z = RNG.standard_normal((4, 120))
THETA = np.array([[0.8, -0.3, 0.5, 0.2]])
Y = THETA @ Z + 0.1 * RNG.standard_normal((1, 120))
THETA_LS = np.linalg.lstsq(Z.T, Y.T, rcond=None)[0].T


def _variance_reference(E: np.ndarray, sigma: float, k: int) -> float:
    """The two-sided chi-square p-value of ||E||^2 / sigma^2 by the regularized incomplete gamma function."""
    dof = E.size - E.shape[0] * k
    cdf = stats.chi2.cdf(float(np.sum((E / sigma) ** 2)), dof)
    return float(min(1.0, 2 * min(cdf, 1 - cdf)))


def _f_reference(Y: np.ndarray, Z: np.ndarray, Theta: np.ndarray, rows: list[int]) -> float:
    """The input F statistic by normal equations on the restricted regressor."""
    rest = np.delete(Z, rows, axis=0)
    theta0 = np.linalg.solve(rest @ rest.T, rest @ Y.T).T
    rss, rss0 = np.sum((Y - Theta @ Z) ** 2), np.sum((Y - theta0 @ rest) ** 2)
    n, N, k = Y.shape[0], Y.shape[1], Z.shape[0]
    return float(((rss0 - rss) / (n * len(rows))) / (rss / (n * (N - k))))


def _same(a: float, b: float, rel: float = 1e-9) -> bool:
    return bool(np.isfinite(a) and abs(a - b) <= rel * max(abs(b), 1e-300))


@lru_cache(maxsize=1)
def _ss() -> IdentificationAttack:
    return ident_instance("ss", T=40)


@lru_cache(maxsize=1)
def _arx() -> IdentificationAttack:
    return ident_instance("arx", T=60, na=2, nb=2)


def _ss_with(**signals: Any) -> Callable[[], Any]:
    def run() -> Any:
        atk = _ss()
        return IdentificationAttack(atk.setting, "ss", {**atk.signals, **signals}, dict(atk.eps))
    return run


def _arx_with(**signals: Any) -> Callable[[], Any]:
    def run() -> Any:
        atk = _arx()
        return IdentificationAttack(atk.setting, "arx", {"u": atk.signals["u"].ravel(), "y": atk.signals["y"].ravel(),
                                                         **signals}, dict(atk.eps), orders=(2, 2))
    return run


@lru_cache(maxsize=1)
def _deepc() -> DeePCAttack:
    return deepc_instance(T=120)


def _deepc_with(**settings: Any) -> Callable[[], Any]:
    def run() -> Any:
        d = _deepc()
        return DeePCAttack(d.plant, d.u, d.y, d.past_u, d.past_y, d.budget, **settings)
    return run


def _plan(u: Any = None, y: Any = None) -> Callable[[], Any]:
    return lambda: _deepc().plan(_deepc().u if u is None else u, _deepc().y if y is None else y)


def _steps(steps: Any) -> Callable[[], Any]:
    return lambda: _deepc().closed_loop(_deepc().u, _deepc().y, steps)


def _huber(**kw: Any) -> Callable[[], Any]:
    def run() -> Any:
        atk = ident_instance("ss", T=25)
        if "noise_std" in kw:
            from dataclasses import replace
            atk = IdentificationAttack(replace(atk.setting, noise_std=kw.pop("noise_std")), "ss", dict(atk.signals),
                                       dict(atk.eps))
        return DefendedIdentification(atk, "huber", **kw)
    return run


def _set(module: str, **values: Any) -> Callable[[], Any]:
    def run() -> Any:
        try:
            bl.set_defaults(module, **values)
        finally:
            bl.reset_defaults()
    return run


def _item(key: str, value: Any) -> Callable[[], Any]:
    def run() -> Any:
        try:
            bl.defaults[key] = value
        finally:
            bl.reset_defaults()
    return run


def _solve(method: str = "global", problem: Callable[[], bl.BilevelProblem] = bard_511, **options: Any
           ) -> Callable[[], Any]:
    return lambda: bl.solve(problem(), method=method, **options)


def _row(**fields: Any) -> Callable[[], Any]:
    """A resumed identification row with `fields` changed: check_fields names what is wrong (else returns "")."""
    row = {"norm2": 0.5, "frobenius": 0.7, "stealthy": True, "max_relative_change": 0.01, "budget_used": {},
           "residual_norm": {}, "before": {}, "after": {}, "wall_time": 1.0, "cpu_time": 1.0, "status": "solved",
           "certified": True, "warm_up_cpu_time": 0.0, **fields}

    def run() -> Any:
        why = check_fields(row, ROW_SCHEMA)
        if why:
            raise InvalidData(f"resumed row refused: {why}")
        return True
    return run


def _fifo(name: str = "pipe") -> str:
    """A named pipe in a fresh temporary directory (a stand-in for /dev/full: a special file that a rename would
    replace; the probe never names a real device, so a regression cannot replace one)."""
    import tempfile
    path = os.path.join(tempfile.mkdtemp(), name)
    os.mkfifo(path)
    return path


def _link_to_fifo() -> str:
    target = _fifo()
    link = target + ".json"
    os.symlink(target, link)
    return link


def _fifo_write() -> None:
    with atomic_open(_fifo()) as fh:
        fh.write("x")


def _cli(*argv: str) -> Callable[[], Any]:
    """`bilevel ...`: a named error is one line on stderr and exit 2 (raised here as the InvalidData it reports)."""
    def run() -> Any:
        import contextlib
        import io
        err = io.StringIO()
        with contextlib.redirect_stderr(err), contextlib.redirect_stdout(io.StringIO()):
            code = main(list(argv))
        text = err.getvalue()
        assert "Traceback" not in text and text.count("\n") <= 1, text
        if code == 2 and text.startswith("bilevel solve: error: "):
            raise ModelError(text)
        return f"exit {code}: {text}"
    return run


def _toeplitz(t: np.ndarray, m: int, n: int) -> np.ndarray:
    return np.array([[t[i - j + n - 1] for j in range(n)] for i in range(m)])


def _operator_reproduces(A: np.ndarray) -> Callable[[], bool]:
    """The operator of A (Toeplitz recognized or dense) reproduces each entry of A to 1e-9 of its scale."""
    def run() -> bool:
        op = Operator(A, "A")
        magnitude = np.abs(A)
        scale = np.minimum(magnitude.max(axis=1)[:, None], magnitude.max(axis=0)[None, :])
        return bool(np.all(np.abs(op.apply(np.eye(A.shape[1])) - A) <= 1e-9 * scale + 2.0 ** -48 * magnitude.max()))
    return run


def _near_toeplitz(kind: str) -> np.ndarray:
    rng = np.random.default_rng(len(kind))
    m, n = 300, 256
    A = _toeplitz(rng.standard_normal(m + n - 1), m, n)
    if kind == "outlier":
        A[7, 9] = 1e15
    elif kind == "column":
        A[:, 5] *= 1e-4
    elif kind == "relative":
        A[100, 100] *= 1 + 1e-12
    elif kind == "corner":
        A[m - 1, 0] = 1e12
    elif kind == "random":
        A = rng.standard_normal((m, n))
        A[0, 0] = 1e15
    return A


# -- the cases -------------------------------------------------------------------------------------------------------
CASES: dict[str, tuple[Callable[[], Any], Any, str]] = {
    # -- linear maps: complex, broken operators, shapes ----------------------------------------------------------------
    "linear_map complex dense": (lambda: _declared(np.eye(2) * (1 + 1j)), InvalidData, "the matrix is complex"),
    "linear_map complex with zero imaginary part": (lambda: _declared(np.eye(2, dtype=complex)), InvalidData,
                                                    "is complex"),
    "linear_map complex sparse": (lambda: _declared(sp.eye(2, dtype=complex) * 1j), InvalidData, "is complex"),
    "linear_map complex LinearOperator": (lambda: _declared(aslinearoperator(np.eye(2) * 1j)), InvalidData,
                                          "is complex"),
    "linear_map complex list": (lambda: _declared([[1j, 0], [0, 1]]), InvalidData, "is complex"),
    "LinearOperator matvec wrong length": (lambda: _declared(_operator(lambda v: np.ones(5))), InvalidData,
                                           "matvec failed.*shape \\(3,\\)"),
    "LinearOperator matvec NaN": (lambda: _declared(_operator(lambda v: np.full(3, np.nan))), InvalidData,
                                  "matvec returned NaN or inf"),
    "LinearOperator matvec inf": (lambda: _declared(_operator(lambda v: np.full(3, np.inf))), InvalidData,
                                  "matvec returned NaN or inf"),
    "LinearOperator matvec complex": (lambda: _declared(_operator(lambda v: np.ones(3) * 1j)), InvalidData,
                                      "matvec output is complex"),
    "LinearOperator rmatvec wrong length": (lambda: _declared(_operator(lambda v: np.ones(3), lambda v: np.ones(4))),
                                            InvalidData, "rmatvec"),
    "LinearOperator rmatvec NaN": (lambda: _declared(_operator(lambda v: np.ones(3), lambda v: np.full(2, np.nan))),
                                   InvalidData, "rmatvec returned NaN"),
    "LinearOperator NaN off its probe point": (_lazy_nan_solve, InvalidData, "matvec returned NaN or inf"),
    "linear_map 3-D array": (lambda: _declared(np.ones((2, 2, 2))), ModelError, "expected a 2-D matrix"),
    "linear_map of strings": (lambda: _declared([["a", "b"]]), ModelError, "expected a numeric matrix"),
    "linear_map with NaN": (lambda: _declared(np.array([[np.nan, 1.0]])), InvalidData, "NaN or inf"),
    # -- structure recognition: reproduced entry by entry, or dense ----------------------------------------------------
    "Toeplitz recognition: random matrix with a 1e15 entry": (_operator_reproduces(_near_toeplitz("random")), VALUE,
                                                              "reproduces"),
    "Toeplitz recognition: outlier 1e15": (_operator_reproduces(_near_toeplitz("outlier")), VALUE, "reproduces"),
    "Toeplitz recognition: a column scaled 1e-4": (_operator_reproduces(_near_toeplitz("column")), VALUE,
                                                   "reproduces"),
    "Toeplitz recognition: one entry moved 1e-12": (_operator_reproduces(_near_toeplitz("relative")), VALUE,
                                                    "reproduces"),
    "Toeplitz recognition: huge corner 1e12": (_operator_reproduces(_near_toeplitz("corner")), VALUE, "reproduces"),
    # -- lower_qp and expressions: complex data ---------------------------------------------------------------------
    "lower_qp complex P": (lambda: _qp(P=np.eye(2) * (1 + 1j)), InvalidData, "lower_qp: P is complex"),
    "lower_qp complex C": (lambda: _qp(C=np.eye(2) * 1j), InvalidData, "lower_qp: C is complex"),
    "lower_qp complex A": (lambda: _qp(A=np.ones((1, 2)) * 1j, b=[1.0]), InvalidData, "lower_qp: A is complex"),
    "lower_qp complex E": (lambda: _qp(E=sp.csr_matrix(np.ones((1, 2)) * 1j), e=[1.0]), InvalidData,
                           "lower_qp: E is complex"),
    "lower_qp complex d": (lambda: _qp(d=np.array([1j, 0])), InvalidData, "lower_qp: d is complex"),
    "lower_qp complex q": (lambda: _qp(q=[1 + 0j, 2]), InvalidData, "lower_qp: q is complex"),
    "lower_qp complex b": (lambda: _qp(A=np.ones((1, 2)), b=[1j]), InvalidData, "lower_qp: b is complex"),
    "lower_qp complex e": (lambda: _qp(E=np.ones((1, 2)), e=np.array([2j])), InvalidData, "lower_qp: e is complex"),
    "upper objective of a complex array": (_expression(lambda p, x, y: p.minimize_upper(np.array([1j]))), InvalidData,
                                           "is complex"),
    "definition of a complex number": (_expression(lambda p, x, y: p.define("z", 1 + 2j)), InvalidData, "is complex"),
    # -- the variance test ---------------------------------------------------------------------------------------------
    "variance: zero residuals (limit p = 0)": (lambda: variance_test(np.zeros((1, 50)), 0.1, 3).p_value == 0.0, VALUE,
                                               "p = 0"),
    "variance: residuals at 1e-200": (lambda: _same(variance_test(1e-200 * E1, 1e-200, 3).p_value,
                                                    _variance_reference(E1, 1.0, 3)), VALUE, "reference"),
    "variance: residuals at 1e200": (lambda: _same(variance_test(1e200 * E1, 1e200, 3).p_value,
                                                   _variance_reference(E1, 1.0, 3)), VALUE, "reference"),
    "variance: two outputs at 1e150": (lambda: _same(variance_test(1e150 * E2, 1e150, 2).p_value,
                                                     _variance_reference(E2, 1.0, 2)), VALUE, "reference"),
    "variance: infinite noise": (lambda: variance_test(E1, np.inf, 3), InvalidData, "noise_std=inf is invalid"),
    "variance: NaN noise": (lambda: variance_test(E1, np.nan, 3), InvalidData, "noise_std=nan is invalid"),
    "variance: zero noise": (lambda: variance_test(E1, 0.0, 3), InvalidData, "noise_std=0.0 is invalid"),
    "variance: negative noise": (lambda: variance_test(E1, -1.0, 3), InvalidData, "noise_std=-1.0 is invalid"),
    "variance: string noise": (lambda: variance_test(E1, "0.1", 3), InvalidData, "noise_std='0.1' is invalid"),
    "variance: bool noise": (lambda: variance_test(E1, True, 3), InvalidData, "noise_std=True is invalid"),
    "variance: negative regressor count": (lambda: variance_test(E1, 1.0, -3), ModelError,
                                           "n_regressors=-3 is invalid"),
    "variance: float regressor count": (lambda: variance_test(E1, 1.0, 2.5), ModelError, "n_regressors=2.5"),
    "variance: bool regressor count": (lambda: variance_test(E1, 1.0, True), ModelError, "n_regressors=True"),
    "variance: as many regressors as samples": (lambda: variance_test(E1, 1.0, 120), InvalidData, "needs N > k"),
    "variance: complex residuals": (lambda: variance_test(E1 * 1j, 1.0, 3), InvalidData, "residuals is complex"),
    "variance: NaN residuals": (lambda: variance_test(np.full((1, 10), np.nan), 1.0, 3), InvalidData, "finite"),
    "variance: 3-D residuals": (lambda: variance_test(np.ones((2, 2, 10)), 1.0, 1), InvalidData, "shape"),
    # -- the whiteness test --------------------------------------------------------------------------------------------
    "whiteness: zero residuals": (lambda: whiteness_test(np.zeros((1, 50)), 3), InvalidData, "all zero"),
    "whiteness: one zero output": (lambda: whiteness_test(np.vstack([E1, 0 * E1]), 3), InvalidData,
                                   "output\\(s\\) \\[1\\] are all zero"),
    "whiteness: duplicated output (singular R_0)": (lambda: whiteness_test(np.vstack([E1, E1]), 3), InvalidData,
                                                    "R_0.*singular"),
    "whiteness: dependent outputs (singular R_0)": (lambda: whiteness_test(np.vstack([E1, -2 * E1]), 3), InvalidData,
                                                    "singular"),
    "whiteness: residuals at 1e-200": (lambda: _same(whiteness_test(1e-200 * E2, 4).statistic,
                                                     whiteness_test(E2, 4).statistic), VALUE, "scale invariant"),
    "whiteness: residuals at 1e200": (lambda: _same(whiteness_test(1e200 * E2, 4).statistic,
                                                    whiteness_test(E2, 4).statistic), VALUE, "scale invariant"),
    "whiteness: outputs at 1e-150 and 1e150": (lambda: _same(whiteness_test(np.array([[1e-150], [1e150]]) * E2,
                                                                            4).statistic,
                                                             whiteness_test(E2, 4).statistic), VALUE, "invariant"),
    "whiteness: lags 0": (lambda: whiteness_test(E1, 0), ModelError, "lags=0 is invalid"),
    "whiteness: lags negative": (lambda: whiteness_test(E1, -2), ModelError, "lags=-2 is invalid"),
    "whiteness: lags float": (lambda: whiteness_test(E1, 2.5), ModelError, "lags=2.5 is invalid"),
    "whiteness: lags bool": (lambda: whiteness_test(E1, True), ModelError, "lags=True is invalid"),
    "whiteness: lags N": (lambda: whiteness_test(E1, 120), InvalidData, "0 < lags < N"),
    "whiteness: complex residuals": (lambda: whiteness_test(E1 + 1j, 3), InvalidData, "is complex"),
    "whiteness: inf residuals": (lambda: whiteness_test(np.full((1, 20), np.inf), 3), InvalidData, "finite"),
    # -- the input F-test ----------------------------------------------------------------------------------------------
    "input: the F statistic by normal equations": (lambda: _same(input_test(Y, Z, THETA_LS, [2, 3]).statistic,
                                                                 _f_reference(Y, Z, THETA_LS, [2, 3]), 1e-8), VALUE,
                                                   "normal equations"),
    "input: data at 1e-200": (lambda: _same(input_test(1e-200 * Y, Z, 1e-200 * THETA_LS, [2, 3]).statistic,
                                            _f_reference(Y, Z, THETA_LS, [2, 3]), 1e-8), VALUE, "invariant"),
    "input: data at 1e200": (lambda: _same(input_test(1e200 * Y, Z, 1e200 * THETA_LS, [2, 3]).statistic,
                                           _f_reference(Y, Z, THETA_LS, [2, 3]), 1e-8), VALUE, "invariant"),
    "input: exact fit (limit F = inf)": (lambda: input_test(THETA @ Z, Z, THETA, [3]).p_value == 0.0, VALUE,
                                         "p = 0"),
    "input: both models exact": (lambda: input_test(THETA[:, :2] @ Z[:2], Z, np.array([[0.8, -0.3, 0.0, 0.0]]),
                                                    [3]), InvalidData, "0 / 0"),
    "input: duplicate input rows": (lambda: input_test(Y, Z, THETA_LS, [3, 3]), InvalidData, "distinct rows"),
    "input: row out of range": (lambda: input_test(Y, Z, THETA_LS, [4]), InvalidData, "each in 0 .. 3"),
    "input: negative row": (lambda: input_test(Y, Z, THETA_LS, [-1]), ModelError, "input row=-1 is invalid"),
    "input: float row": (lambda: input_test(Y, Z, THETA_LS, [2.0]), ModelError, "input row=2.0 is invalid"),
    "input: bool row": (lambda: input_test(Y, Z, THETA_LS, [True]), ModelError, "input row=True is invalid"),
    "input: string row": (lambda: input_test(Y, Z, THETA_LS, ["2"]), ModelError, "input row='2' is invalid"),
    "input: no rows": (lambda: input_test(Y, Z, THETA_LS, []), InvalidData, "0 < q < k"),
    "input: every row": (lambda: input_test(Y, Z, THETA_LS, [0, 1, 2, 3]), InvalidData, "0 < q < k"),
    "input: Theta of the wrong shape": (lambda: input_test(Y, Z, THETA_LS[:, :3], [2]), InvalidData, "do not fit"),
    "input: complex Z": (lambda: input_test(Y, Z * 1j, THETA_LS, [2]), InvalidData, "Z is complex"),
    "residual tests: Y and Z of other lengths": (lambda: regression_tests(Y, Z[:, :100], THETA_LS, [2], 0.1, 3),
                                                 InvalidData, "do not fit"),
    # -- identification instances --------------------------------------------------------------------------------------
    "ident ARX na negative": (lambda: ident_instance("arx", T=50, na=-1), ModelError, "na=-1 is invalid"),
    "ident ARX nb 0": (lambda: ident_instance("arx", T=50, nb=0), ModelError, "nb=0 is invalid"),
    "ident ARX na float": (lambda: ident_instance("arx", T=50, na=2.5), ModelError, "na=2.5 is invalid"),
    "ident ARX na bool": (lambda: ident_instance("arx", T=50, na=True), ModelError, "na=True is invalid"),
    "ident ARX nb string": (lambda: ident_instance("arx", T=50, nb="2"), ModelError, "nb='2' is invalid"),
    "ident lags negative": (lambda: ident_instance("ss", T=50, lags=-3), ModelError, "lags.*=-3 is invalid"),
    "ident lags 0": (lambda: ident_instance("ss", T=50, lags=0), ModelError, "=0 is invalid"),
    "ident lags float": (lambda: ident_instance("ss", T=50, lags=2.5), ModelError, "=2.5 is invalid"),
    "ident stealth string": (lambda: ident_instance("ss", T=50, stealth="0.05"), ModelError, "stealth='0.05'"),
    "ident stealth 0": (lambda: ident_instance("ss", T=50, stealth=0.0), ModelError, "in \\(0, 1\\)"),
    "ident stealth 1": (lambda: ident_instance("ss", T=50, stealth=1.0), ModelError, "in \\(0, 1\\)"),
    "ident stealth NaN": (lambda: ident_instance("ss", T=50, stealth=np.nan), ModelError, "stealth=nan"),
    "ident stealth bool": (lambda: ident_instance("ss", T=50, stealth=True), ModelError, "stealth=True"),
    "ident eps string": (lambda: ident_instance("ss", T=50, eps="0.05"), ModelError, "eps_X='0.05'"),
    "ident eps bool": (lambda: ident_instance("ss", T=50, eps=True), ModelError, "eps_X=True"),
    "ident eps inf": (lambda: ident_instance("ss", T=50, eps=np.inf), ModelError, "eps_X=inf"),
    "ident eps negative": (lambda: ident_instance("ss", T=50, eps=-0.1), ModelError, "finite and >= 0"),
    "ident T 0": (lambda: ident_instance("ss", T=0), InvalidData, "T=0"),
    "ident T bool": (lambda: ident_instance("ss", T=True), InvalidData, "T=True"),
    "ident unknown learner": (lambda: IdentificationAttack(_ss().setting, "pem", dict(_ss().signals),
                                                           dict(_ss().eps)), ModelError, "'pem' is not"),
    "ident h2 on ARX": (lambda: ident_instance("arx", T=50, objective="h2"), ModelError, "state-space model"),
    "ident lqr weight string": (lambda: ident_instance("ss", T=50, lqr_weights=("1", 1.0)), ModelError,
                                "lqr weight='1'"),
    "ident X 3-D": (_ss_with(X=np.ones((1, 4, 41))), InvalidData, "signal X has shape \\(1, 4, 41\\)"),
    "ident X transposed": (_ss_with(X=np.ones((41, 4))), InvalidData, "needs T \\+ 1 = 41 columns.*transposed"),
    "ident X short": (_ss_with(X=np.ones((4, 20))), InvalidData, "needs T \\+ 1 = 41 columns"),
    "ident X longer than U (was cut)": (_ss_with(X=np.ones((4, 60))), InvalidData, "needs T \\+ 1 = 41 columns"),
    "ident U longer than X": (_ss_with(U=np.ones((1, 50))), InvalidData, "needs T \\+ 1 = 51 columns"),
    "ident X complex": (_ss_with(X=np.ones((4, 41)) * 1j), InvalidData, "signal X is complex"),
    "ident U complex, zero imaginary part": (_ss_with(U=np.ones((1, 40), dtype=complex)), InvalidData,
                                             "signal U is complex"),
    "ident X of strings": (_ss_with(X=[["a"] * 41] * 4), InvalidData, "signal X must be real numbers"),
    "ident X with NaN": (_ss_with(X=np.full((4, 41), np.nan)), InvalidData, "NaN or inf"),
    "ident ARX y longer than u (was cut)": (_arx_with(y=np.ones(70)), InvalidData, "60 and 70 samples"),
    "ident ARX u shorter": (_arx_with(u=np.ones(30)), InvalidData, "30 and 60 samples"),
    "ident ARX u a matrix": (_arx_with(u=np.ones((2, 60))), InvalidData, "a 1-D signal"),
    "ident ARX y complex": (_arx_with(y=np.ones(60) * 1j), InvalidData, "signal y is complex"),
    "ident-arx problem with na 0 and nb 0": (lambda: registry.get("ident-arx", na=0, nb=0, T=50), ModelError,
                                             "nb=0 is invalid"),
    # -- DeePC instances -----------------------------------------------------------------------------------------------
    "DeePC horizon bool": (lambda: deepc_instance(T=120, horizon=True), ModelError, "horizon=True is invalid"),
    "DeePC horizon 0": (lambda: deepc_instance(T=120, horizon=0), ModelError, "horizon=0 is invalid"),
    "DeePC horizon float": (lambda: deepc_instance(T=120, horizon=10.0), ModelError, "horizon=10.0 is invalid"),
    "DeePC t_ini bool": (lambda: deepc_instance(T=120, t_ini=True), ModelError, "t_ini=True is invalid"),
    "DeePC t_ini string": (lambda: deepc_instance(T=120, t_ini="4"), ModelError, "t_ini='4' is invalid"),
    "DeePC eps string": (lambda: deepc_instance(T=120, eps="0.1"), ModelError, "eps='0.1' is invalid"),
    "DeePC eps NaN": (lambda: deepc_instance(T=120, eps=np.nan), ModelError, "eps=nan is invalid"),
    "DeePC noise_std string": (lambda: deepc_instance(T=120, noise_std="0.1"), ModelError, "noise_std='0.1'"),
    "DeePC past_std inf": (lambda: deepc_instance(T=120, past_std=np.inf), ModelError, "past_std=inf"),
    "DeePC lambda_g string": (lambda: deepc_instance(T=120, lambda_g="big"), ModelError, "lambda_g='big'"),
    "DeePC lambda_y negative": (lambda: deepc_instance(T=120, lambda_y=-1.0), ModelError, "finite and >= 0"),
    "DeePC u_max 0": (lambda: deepc_instance(T=120, u_max=0.0), ModelError, "u_max"),
    "DeePC u_max string": (lambda: deepc_instance(T=120, u_max="1"), ModelError, "u_max='1'"),
    "DeePC reference of the wrong length": (_deepc_with(reference=np.ones(3)), InvalidData,
                                            "setpoint r is one finite number"),
    "DeePC reference NaN": (_deepc_with(reference=np.nan), ModelError, "reference=nan is invalid"),
    "DeePC reference inf": (_deepc_with(reference=np.inf), ModelError, "reference=inf is invalid"),
    "DeePC reference string": (_deepc_with(reference="one"), InvalidData, "reference must be real numbers"),
    "DeePC reference complex": (_deepc_with(reference=1j), InvalidData, "reference is complex"),
    "DeePC recorded u complex": (lambda: DeePCAttack(_deepc().plant, _deepc().u * 1j, _deepc().y, _deepc().past_u,
                                                     _deepc().past_y, _deepc().budget), InvalidData,
                                 "signal u is complex"),
    "DeePC plan on NaN data": (_plan(u=np.full(120, np.nan)), InvalidData, "NaN or inf"),
    "DeePC plan on shorter data": (_plan(u=np.ones(50), y=np.ones(50)), InvalidData, "50 and 50 samples"),
    "DeePC plan on longer data (was an error deep in cvxpy)": (_plan(u=np.ones(240), y=np.ones(240)), InvalidData,
                                                               "240 and 240 samples"),
    "DeePC plan on u and y of other lengths": (_plan(y=np.ones(117)), InvalidData, "120 and 117 samples"),
    "DeePC plan on complex data": (_plan(y=np.ones(120) * 1j), InvalidData, "recorded y is complex"),
    "DeePC closed_loop steps -1 (was an empty loop)": (_steps(-1), ModelError, "steps=-1 is invalid"),
    "DeePC closed_loop steps float": (_steps(1.5), ModelError, "steps=1.5 is invalid"),
    "DeePC closed_loop steps bool": (_steps(True), ModelError, "steps=True is invalid"),
    "DeePC closed_loop steps string": (_steps("2"), ModelError, "steps='2' is invalid"),
    "DeePC tracking cost of a long plan": (lambda: _deepc().tracking_cost(np.zeros(15)), InvalidData,
                                           "a plan has 10 inputs"),
    "DeePC tracking cost of a complex plan": (lambda: _deepc().tracking_cost(np.zeros(10) * 1j), InvalidData,
                                              "plan is complex"),
    # -- defended learners -------------------------------------------------------------------------------------------
    "Huber threshold 1e-12 (was another learner)": (_huber(k=1e-12), ModelError, "below 0.001.*use loss 'lad'"),
    "Huber threshold 0": (_huber(k=0.0), ModelError, "k=0.0 noise stds is below"),
    "Huber threshold negative": (_huber(k=-1.0), ModelError, "is below"),
    "Huber threshold string": (_huber(k="1.3"), ModelError, "='1.3' is invalid"),
    "Huber with noise_std 0": (_huber(noise_std=0.0), ModelError, "noise_std 0.0 must be > 0"),
    "defended identification k inf": (lambda: defended_instance("huber", T=25, k=np.inf), ModelError, "k.*=inf"),
    "IV trusted_instrument 'no' (was True)": (lambda: registry.get("defense-vrft-iv", trusted_instrument="no"),
                                              ModelError, "trusted_instrument='no' is invalid: it must be True or"),
    "IV trusted_instrument 1": (lambda: registry.get("defense-vrft-iv", trusted_instrument=1), ModelError,
                                "trusted_instrument=1 is invalid"),
    "IV trusted_instrument None": (lambda: registry.get("defense-vrft-iv", trusted_instrument=None), ModelError,
                                   "trusted_instrument=None"),
    # -- the defaults registry -----------------------------------------------------------------------------------------
    "'name' in defaults": (lambda: ("name" in bl.defaults) is False, VALUE, "False"),
    "defaults.get of an unknown key": (lambda: bl.defaults.get("hypergradient.maxiter", 7) == 7, VALUE, "default"),
    "defaults[unknown]": (lambda: bl.defaults["nope"], UnknownName, "unknown default 'nope'"),
    "defaults[unknown] = 1": (_item("nope.x", 1), UnknownName, "unknown default"),
    "set_defaults starts 0": (_set("hypergradient", starts=0), ModelError, "starts=0 is invalid: it must be an "
                                                                           "integer >= 1"),
    "set_defaults ipopt starts 0": (_set("ipopt", starts=0), ModelError, "ipopt.starts=0 is invalid"),
    "set_defaults reduced starts -1": (_set("reduced", starts=-1), ModelError, "reduced.starts=-1"),
    "set_defaults certificate tol 0": (_set("certificate", tol=0), ModelError, "certificate.tol=0 is invalid"),
    "set_defaults certificate tol 1e-300": (_set("certificate", tol=1e-300), ModelError, "tol=1e-300 is invalid"),
    "set_defaults certificate tol NaN": (_set("certificate", tol=np.nan), ModelError, "tol=nan is invalid"),
    "set_defaults SCIP feastol 0": (_set("global", scip_feastol=0.0), ModelError, "\\[1e-17, 0.001\\]"),
    "set_defaults SCIP feastol 1": (_set("global", scip_feastol=1.0), ModelError, "scip_feastol=1.0 is invalid"),
    "set_defaults node_limit 2**70": (_set("global", node_limit=2 ** 70), ModelError, "node_limit="),
    "set_defaults node_limit 0": (_set("global", node_limit=0), ModelError, "node_limit=0 is invalid"),
    "set_defaults node_limit float": (_set("global", node_limit=10.0), ModelError, "node_limit=10.0 is invalid"),
    "set_defaults time_limit 0": (_set("global", time_limit=0.0), ModelError, "time_limit=0.0 is invalid"),
    "set_defaults time_limit inf": (_set("global", time_limit=np.inf), ModelError, "time_limit=inf is invalid"),
    "set_defaults gap 1": (_set("global", gap=1.0), ModelError, "gap=1.0 is invalid.*in \\(0, 1\\)"),
    "set_defaults relaxation factor 1": (_set("relaxation", factor=1.0), ModelError, "factor=1.0 is invalid"),
    "set_defaults armijo 0": (_set("ascent", armijo=0.0), ModelError, "armijo=0.0 is invalid"),
    "set_defaults window 0": (_set("ascent", window=0), ModelError, "window=0 is invalid"),
    "set_defaults sparse_squares 2": (_set("residual", sparse_squares=2.0), ModelError, "in \\[0, 1\\]"),
    "set_defaults defective_cond 0.5": (_set("spectral_radius", defective_cond=0.5), ModelError, ">= 1"),
    "set_defaults max_iter -1": (_set("hypergradient", max_iter=-1), ModelError, "max_iter=-1 is invalid"),
    "set_defaults max_iter True": (_set("hypergradient", max_iter=True), ModelError, "max_iter=True is invalid"),
    "set_defaults nlp_tol string": (_set("ipopt", nlp_tol="1e-8"), ModelError, "nlp_tol='1e-8' is invalid"),
    "set_defaults gtol 0": (_set("hypergradient", gtol=0.0), ModelError, "gtol=0.0 is invalid"),
    "defaults[popsize] = 0": (_item("willems.evolution.popsize", 0), ModelError,
                                "popsize=0 is invalid"),
    # -- options at solve: the registry's ranges ---------------------------------------------------------------------
    "global node_limit '5' (was int('5'))": (_solve(node_limit="5"), ModelError, "node_limit='5' is invalid"),
    "global node_limit 1e30": (_solve(node_limit=1e30), ModelError, "node_limit=1e\\+30 is invalid"),
    "global node_limit 2.5": (_solve(node_limit=2.5), ModelError, "node_limit=2.5 is invalid"),
    "global node_limit True": (_solve(node_limit=True), ModelError, "node_limit=True is invalid"),
    "global node_limit 0": (_solve(node_limit=0), ModelError, "node_limit=0 is invalid"),
    "global gap 0": (_solve(gap=0.0), ModelError, "gap=0.0 is invalid"),
    "global node_limit 1 (honest stop)": (_solve(node_limit=1), STATUS, "stopped \\(node_limit\\) before the gap"),
    "hypergradient max_iter 0 (honest stop)": (_solve("hypergradient", starts=1, max_iter=0), STATUS,
                                               "max_iter = 0 reached"),
    "global time_limit string": (_solve(time_limit="60"), ModelError, "time_limit='60' is invalid"),
    "scip time_limit 1e30 (SCIP's no limit)": (lambda: _solve(algorithm="scip", time_limit=1e30)().status
                                               is bl.Status.SOLVED, VALUE, "solved as without a limit"),
    "scip node_limit 1e30": (_solve(algorithm="scip", node_limit=1e30), ModelError, "node_limit=1e\\+30"),
    "certificate_tol 0": (_solve("ipopt", starts=1, certificate_tol=0.0), ModelError, "certificate_tol=0.0 is inv"),
    "certificate_tol 1e-300": (_solve("ipopt", starts=1, certificate_tol=1e-300), ModelError,
                               "certificate_tol=1e-300 is invalid"),
    "certificate_tol string": (_solve("ipopt", starts=1, certificate_tol="1e-6"), ModelError,
                               "certificate_tol='1e-6' is invalid"),
    "relaxation factor 1": (_solve("relaxation", starts=1, factor=1.0), ModelError, "factor=1.0 is invalid"),
    "relaxation t0 string": (_solve("relaxation", starts=1, t0="1"), ModelError, "t0='1' is invalid"),
    "ipopt nlp_tol 0": (_solve("ipopt", starts=1, nlp_tol=0.0), ModelError, "nlp_tol=0.0 is invalid"),
    "hypergradient penalty 0": (_solve("hypergradient", starts=1, penalty=0.0), ModelError,
                                "penalty=0.0 is invalid"),
    # -- resumed rows ------------------------------------------------------------------------------------------------
    "resumed row with norm2 inf": (_row(norm2=float("inf")), InvalidData, "norm2: inf is not finite number >= 0"),
    "resumed row with norm2 negative": (_row(norm2=-0.5), InvalidData, "norm2: -0.5 is not"),
    "resumed row with norm2 NaN": (_row(norm2=float("nan")), InvalidData, "norm2: nan is not"),
    "resumed row with frobenius negative": (_row(frobenius=-1.0), InvalidData, "frobenius: -1.0 is not"),
    "resumed row with norm2 a string": (_row(norm2="0.5"), InvalidData, "norm2: '0.5' is not"),
    "resumed row that is whole": (_row(), VALUE, "accepted"),
    # -- files and the CLI -------------------------------------------------------------------------------------------
    "write over a pipe": (_fifo_write, OSError, "not a regular file"),
    "CLI --option starts=2 --starts 3": (_cli("solve", "bard1998-ex5.1.1", "--option", "starts=2", "--starts", "3"),
                                         ModelError, "give option starts twice"),
    "CLI --option seed=2 --seed 3": (_cli("solve", "bard1998-ex5.1.1", "--option", "seed=2", "--seed", "3"),
                                     ModelError, "give option seed twice"),
    "CLI --json to a pipe (as /dev/full: was replaced by a file)": (lambda: _cli("solve", "bard1998-ex5.1.1",
                                                                                 "--json", _fifo())(),
                                                                    ModelError, "not a regular file"),
    "CLI --json to a link to a pipe": (lambda: _cli("solve", "bard1998-ex5.1.1", "--json", _link_to_fifo())(),
                                       ModelError, "not a regular file"),
    "CLI ident-arx na=0 nb=0": (_cli("solve", "ident-arx", "--param", "na=0", "--param", "nb=0"), ModelError,
                                "nb=0 is invalid"),
    "CLI ident-ss lags=-3": (_cli("solve", "ident-ss", "--param", "lags=-3"), ModelError, "=-3 is invalid"),
    "CLI certificate_tol=1e-300": (_cli("solve", "bard1998-ex5.1.1", "--option", "certificate_tol=1e-300"),
                                   ModelError, "certificate_tol=1e-300 is invalid"),
    "CLI global node_limit=1e30": (_cli("solve", "bard1998-ex5.1.1", "--method", "global", "--option",
                                        "node_limit=1e30"), ModelError, "node_limit=1e\\+30 is invalid"),
    "CLI trusted_instrument=no": (_cli("solve", "defense-vrft-iv", "--param", "trusted_instrument=no"), ModelError,
                                  "trusted_instrument='no'"),
    "CLI ident-arx na=-1": (_cli("solve", "ident-arx", "--param", "na=-1"), ModelError, "na=-1 is invalid"),
    "CLI ident-ss stealth=2": (_cli("solve", "ident-ss", "--param", "stealth=2"), ModelError, "stealth"),
}


def _outcome(case: str) -> str:
    expected = CASES[case][1]
    return {STATUS: "honest status", VALUE: "correct value"}.get(expected, "named error")


@pytest.mark.parametrize("case", sorted(CASES))
def test_bad_input_has_one_checked_outcome(case: str) -> None:
    run, expected, match = CASES[case]
    if expected == VALUE:
        assert run() is True, f"{case}: the value differs from the independent one ({match})"
        return
    if expected == STATUS:
        res = run()
        assert isinstance(res, bl.BilevelResult) and res.status is not bl.Status.SOLVED and not res.success
        assert re.search(match, res.message), res.message
        return
    with pytest.raises(BilevelError if expected is not OSError else OSError, match=match) as info:
        run()
    assert isinstance(info.value, expected), f"{type(info.value).__name__}: {info.value}"
    if expected is not OSError:
        assert type(info.value) in (expected, *expected.__subclasses__()), type(info.value)


def test_the_probe_covers_150_new_inputs() -> None:
    counts = Counter(_outcome(case) for case in CASES)
    assert sum(counts.values()) >= 150, counts
    assert counts["named error"] >= 100 and counts["correct value"] >= 15 and counts["honest status"] >= 1, counts


@pytest.mark.parametrize("method, starts", [("reduced", 1), ("hypergradient", 4)])
def test_flags_not_given_leave_the_registrys_defaults(method: str, starts: int, tmp_path, capsys) -> None:
    """`bilevel solve` without --starts runs the method's registry default (it sent starts=8 to every method)."""
    import json

    path = str(tmp_path / "r.json")
    assert main(["solve", "bolib-hendersonquandt1958", "--method", method, "--json", path]) == 0
    assert len(json.load(open(path))["start_records"]) == starts == bl.defaults[f"{method}.starts"]
    capsys.readouterr()
