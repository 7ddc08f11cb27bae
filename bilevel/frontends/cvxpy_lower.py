"""A lower level written as a cvxpy Problem, translated into the framework's own lower-level declarations.

cvxpy's parametrized conic form (frontends/conic.py) becomes: one lower variable (the conic variables,
less the auxiliaries that an equality row defines, which are substituted out so that a least-squares
learner stays least squares), zero-cone rows as equalities, nonnegative rows as inequalities,
second-order cones as arrow LMIs [[t I, u], [u', t]] >= 0 (exact: PSD iff ||u|| <= t) and PSD cones
as LMIs. Every method and the certificate then see an ordinary lower level; the certificate's
independent re-solve is the user's own cvxpy problem (`CvxpyLower.reference`).
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Any

import casadi as ca
import cvxpy as cp
import numpy as np
import scipy.sparse as sp

from ..errors import InvalidData, ModelError
from ..lower.base import LowerSolution
from ..lower.quadratic import solve_clarabel
from .conic import ConicForm, conic_form
from .cvxpy_domains import constrain_domain, in_domain

if TYPE_CHECKING:  # pragma: no cover
    from ..model import BilevelProblem


def _label(param: cp.Parameter) -> str:
    return f"Parameter {param.name()!r} (shape {param.shape})"


def _shape(leaf: cp.Parameter | cp.Variable) -> tuple[int, int]:
    """A cvxpy shape as CasADi's (rows, cols): () -> (1, 1), (n,) -> (n, 1)."""
    return (leaf.shape + (1, 1))[:2] if len(leaf.shape) < 2 else leaf.shape


def _bind(problem: BilevelProblem, learner: cp.Problem, parameters: dict[Any, Any],
          name: str) -> tuple[dict[int, ca.SX], dict[int, str]]:
    """Parameter id -> its CasADi value: the bound expression, or else a model parameter declared with the current
    .value (re-set later without rebuilding); also the model parameter names of the unbound Parameters."""
    own = {p.id: p for p in learner.parameters()}
    known = ca.vertcat(*[ca.vec(v.sym) for v in problem.upper_variables], problem.parameters.sym)
    allowed = {s.element_hash() for s in ca.symvar(known)}
    values: dict[int, ca.SX] = {}
    for param, expr in parameters.items():
        if not isinstance(param, cp.Parameter) or param.id not in own:
            raise ModelError(f"lower_cvxpy: the key {param!r} of parameters= is not a cvxpy Parameter of this "
                             "problem; bind the Parameters that appear in the cvxpy problem")
        value = expr if isinstance(expr, ca.SX) else ca.SX(ca.DM(np.asarray(expr, dtype=float)))
        rows, cols = _shape(param)
        if value.shape != (rows, cols) and not (len(param.shape) == 1 and value.shape == (1, rows)):
            raise ModelError(f"lower_cvxpy: {_label(param)} is bound to an expression of shape {value.shape}; "
                             f"bind it to a {rows} x {cols} CasADi expression (a vector Parameter takes a column)")
        free = [s for s in ca.symvar(value) if s.element_hash() not in allowed]
        if free:
            raise ModelError(f"lower_cvxpy: {_label(param)} is bound to an expression of {free[0]}, which is not an "
                             "upper variable or parameter of this problem; declare it with upper_variable first")
        values[param.id] = ca.reshape(value, rows, cols)
    names: dict[int, str] = {}
    for param in learner.parameters():
        if param.id not in values:
            if param.value is None:
                raise ModelError(f"lower_cvxpy: {_label(param)} is not bound in parameters= and has no value; bind "
                                 "it to an upper-level expression or set param.value before declaring")
            label = f"{name}_{param.name()}"
            names[param.id] = label if label.isidentifier() else f"{name}_parameter{param.id}"
            values[param.id] = problem.parameter(names[param.id], _shape(param), param.value)
    return values, names


def _check_convex(learner: cp.Problem) -> None:
    if learner.is_mixed_integer():
        raise ModelError("lower_cvxpy: the cvxpy problem has integer or boolean variables; a lower level must be "
                         "convex (relax them, or solve the integer bilevel problem elsewhere)")
    if not learner.is_dcp():
        raise ModelError("lower_cvxpy: the cvxpy problem is not DCP (learner.is_dcp() is False); rewrite it "
                         "following cvxpy's disciplined convex programming rules")
    if not learner.is_dcp(dpp=True):
        raise ModelError("lower_cvxpy: the cvxpy problem is DCP but not DPP in its Parameters (e.g. a product of two "
                         "Parameters, or a Parameter inside a nonlinear atom), so its conic data are not affine in "
                         "them; introduce one Parameter for the product or nonlinear term and bind it instead")


class CvxpyLower:
    """The lower level of a BilevelProblem declared from a cvxpy Problem (BilevelProblem.lower_cvxpy).

    `ll[v]` is the user's cvxpy Variable v as a CasADi expression (its shape; a vector is a column);
    `ll.set_value(param, value)` gives an unbound Parameter new data without rebuilding.
    """

    def __init__(self, problem: BilevelProblem, learner: cp.Problem, parameters: dict[Any, Any], name: str) -> None:
        _check_convex(learner)
        self.learner = learner
        self._problem = problem
        self._bound = {p.id: (p, parameters[p]) for p in parameters}
        values, self._model_names = _bind(problem, learner, parameters, name)
        for param, _ in self._bound.values():
            constrain_domain(problem, param, values[param.id], _label(param), name)
        self._unbound = {p.id: p for p in learner.parameters() if p.id in self._model_names}
        form = conic_form(learner, values)
        keep, E, e, used_rows = self._eliminate(form)
        self.y = problem.lower_variable(name, len(keep), lb=form.lb[keep], ub=form.ub[keep])
        z = ca.mtimes(E, self.y) + e
        objective = 0.5 * ca.bilin(form.P, z, z) + ca.dot(form.q, z) + form.d
        if form.minimize:
            problem.minimize_lower(objective)
        else:
            problem.maximize_lower(-objective)
        self._declare(problem, form, E, e, name, used_rows)
        self._user = {vid: ca.mtimes(ca.DM(mat.tocsc()), z) for vid, mat in form.user.items()}
        self._variables = {v.id: v for v in learner.variables()}
        self._ref_cache: tuple[tuple[int, ...], Any, Any] | None = None

    def __getitem__(self, variable: cp.Variable) -> ca.SX:
        """The cvxpy Variable's value as a CasADi expression of the lower variables (its shape, column-major)."""
        if not isinstance(variable, cp.Variable) or variable.id not in self._user:
            raise ModelError(f"{variable!r} is not a Variable of this cvxpy lower level")
        return ca.reshape(self._user[variable.id], *_shape(variable))

    def parameter_name(self, param: cp.Parameter) -> str:
        """The model parameter (BilevelProblem.parameter) that an unbound cvxpy Parameter was declared as."""
        if not isinstance(param, cp.Parameter) or param.id not in self._model_names:
            raise ModelError(f"{param!r} is not an unbound Parameter of this cvxpy lower level (bound Parameters "
                             "follow their upper-level expressions)")
        return self._model_names[param.id]

    def set_value(self, param: cp.Parameter, value: Any) -> None:
        """Give an unbound cvxpy Parameter new data: its .value and its model parameter; the next solve reuses the
        declared problem (no re-canonicalization)."""
        name = self.parameter_name(param)
        param.value = value
        self._problem.set_value(name, param.value)

    # -- translation -------------------------------------------------------------------------------
    @staticmethod
    def _eliminate(form: ConicForm) -> tuple[np.ndarray, ca.SX, ca.SX, set[int]]:
        """Auxiliary conic variables that occur in one zero-cone row only, with a constant coefficient, unbounded and
        not part of a user Variable, are solved from that row. Returns the kept indices, z = E y + e in the kept
        variables y, and the rows used up (numbered across all blocks)."""
        n = form.n
        A = ca.vertcat(*[blk.A for blk in form.blocks]) if form.blocks else ca.SX(0, n)
        b = ca.vertcat(*[blk.b for blk in form.blocks]) if form.blocks else ca.SX(0, 1)
        rows_of, cols_of = (np.asarray(v, dtype=int) for v in A.sparsity().get_triplet())
        count = np.bincount(cols_of, minlength=n)
        used = np.zeros(n, dtype=bool)
        for mat in form.user.values():
            used |= np.asarray(abs(mat).sum(axis=0)).ravel() > 0
        free = (count == 1) & ~used & ~np.isfinite(form.lb) & ~np.isfinite(form.ub)
        zero_row = np.concatenate([np.full(int(blk.b.numel()), blk.kind == "zero") for blk in form.blocks] or [[]])
        solved: dict[int, tuple[int, float]] = {}
        taken: set[int] = set()
        for i, k in zip(rows_of, cols_of):
            if free[k] and zero_row[i] and i not in taken:
                coef = A[int(i), int(k)]
                if coef.is_constant() and float(coef) != 0.0:
                    solved[int(k)] = (int(i), float(coef))
                    taken.add(int(i))
        keep = np.array([k for k in range(n) if k not in solved], dtype=int)
        gone = sorted(solved)
        rows = [solved[k][0] for k in gone]
        scale = ca.DM(sp.diags([-1.0 / solved[k][1] for k in gone]).tocsc()) if gone else ca.DM(0, 0)
        solved_rows = ca.mtimes(scale, A[rows, keep.tolist()]) if gone else ca.SX(0, len(keep))
        stacked = ca.vertcat(ca.SX.eye(len(keep)), solved_rows)
        offsets = ca.vertcat(ca.SX(len(keep), 1), ca.mtimes(scale, b[rows]) if gone else ca.SX(0, 1))
        order = np.argsort(np.concatenate([keep, gone])).tolist()  # back to the conic variables' order
        return keep, stacked[order, :], offsets[order], taken

    def _declare(self, problem: BilevelProblem, form: ConicForm, E: ca.SX, e: ca.SX, name: str,
                 used_rows: set[int]) -> None:
        """Declare the cone rows, A (E y + e) + b, less those used up by elimination, as constraints and LMIs."""
        offset = 0
        for b, blk in enumerate(form.blocks):
            size = int(blk.b.numel())
            rest = [i for i in range(size) if offset + i not in used_rows]
            offset += size
            if not rest:
                continue
            A_y, b_y = ca.mtimes(blk.A, E)[rest, :], (ca.mtimes(blk.A, e) + blk.b)[rest]
            rows = ca.mtimes(A_y, self.y) + b_y
            if blk.kind in ("zero", "nonneg"):
                live = np.diff(np.asarray(A_y.T.sparsity().colind())) > 0
                rows = self._live_rows(rows, live, blk.kind, f"{name}.{blk.kind}{b}")
                if rows.numel():
                    comparison = rows == 0 if blk.kind == "zero" else rows >= 0
                    problem.lower_constraint(comparison, name=f"{name}.{blk.kind}{b}")
                continue
            start = 0
            for c, side in enumerate(blk.sizes):
                if blk.kind == "soc":
                    t, u = rows[start], rows[start + 1:start + side]
                    start += side
                    mat = ca.blockcat([[t * ca.SX.eye(side - 1), u], [u.T, t]]) if side > 1 else t
                else:
                    mat = ca.reshape(rows[start:start + side * side], side, side)
                    start += side * side
                problem.lower_psd_constraint(mat, name=f"{name}.{blk.kind}{b}_{c}")

    @staticmethod
    def _live_rows(rows: ca.SX, live: np.ndarray, kind: str, where: str) -> ca.SX:
        """Rows that involve the lower variables (`live`); the others must hold as constants (else ModelError)."""
        for i in np.flatnonzero(~live):
            row = rows[int(i)]
            if not row.is_constant():
                raise ModelError(f"lower_cvxpy: constraint row {where}[{i}] involves only Parameters, so it "
                                 "constrains the upper level; state it with upper_constraint instead")
            value = float(row)
            if (kind == "zero" and value != 0.0) or (kind == "nonneg" and value < 0.0):
                raise ModelError(f"lower_cvxpy: constraint row {where}[{i}] is the constant {value:g}, which is "
                                 "infeasible; check the cvxpy problem")
        return rows[np.flatnonzero(live).tolist()] if live.any() else ca.SX(0, 1)

    # -- the certificate's independent re-solve ---------------------------------------------------
    def _reference_functions(self, x_sym: ca.SX) -> tuple[Any, Any]:
        """x -> the bound Parameters' values, and (x, y) -> (user Variables, their Jacobian in y); built once per
        upper symbol vector (the canonical form's), reading the model parameters' current values."""
        key = tuple(s.element_hash() for s in ca.symvar(x_sym))
        if self._ref_cache is None or self._ref_cache[0] != key:
            model = self._problem.parameters
            users = ca.vertcat(*self._user.values())
            self._ref_cache = (key, model.function("bind", [x_sym], [ca.SX(e) for _, e in self._bound.values()]),
                               model.function("users", [x_sym, self.y], [users, ca.jacobian(users, self.y)]))
        return self._ref_cache[1], self._ref_cache[2]

    def reference(self, x_sym: ca.SX, x: np.ndarray, y: np.ndarray) -> LowerSolution:
        """Solve the user's cvxpy problem with Clarabel at upper point x: bound Parameters at their expressions there,
        unbound ones at their model parameters' values (all restored after).

        The returned y is the lower vector nearest to `y` that reproduces the re-solved user Variables
        (auxiliary conic entries are not the user's), so F(x, y_ref) is the upper objective at the re-solve.
        """
        model = self._problem.parameters
        bind, users = self._reference_functions(x_sym)
        bound = [p for p, _ in self._bound.values()]
        values = list(bind(x)) if len(bound) > 1 else [bind(x)] if bound else []
        current = {p.name: p.value for p in model.items}
        values += [current[self._model_names[p.id]] for p in self._unbound.values()]
        params = bound + list(self._unbound.values())
        old = [p.value for p in params]
        try:
            for p, value in zip(params, values):
                v = in_domain(p, np.asarray(value, dtype=float).reshape(p.shape, order="F"), _label(p))
                try:
                    p.value = v
                except ValueError as exc:  # e.g. 0 for a pos Parameter: outside the domain cvxpy accepts
                    raise InvalidData(f"{_label(p)} cannot take its value here: {exc}") from exc
            solve_clarabel(self.learner, "the cvxpy lower level (independent re-solve)")
            w_ref = np.concatenate([np.asarray(self._variables[vid].value, dtype=float).reshape(-1, order="F")
                                    for vid in self._user])
            value = float(self.learner.value)
            status = str(self.learner.status)
        finally:
            for p, v in zip(params, old):
                p.value = v
        w, jac = users(x, y)
        y_ref = y + np.linalg.lstsq(jac, w_ref - w.ravel(), rcond=None)[0]
        f_ref = value if isinstance(self.learner.objective, cp.Minimize) else -value
        return LowerSolution(y_ref, f_ref, np.zeros(0), np.zeros(0), [], status, "cvxpy+clarabel (user's problem)")
