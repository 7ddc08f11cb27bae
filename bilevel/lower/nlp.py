"""Smooth convex NLP lower level, solved independently by IPOPT on the plain lower problem."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import casadi as ca
import numpy as np

from ..defaults import param
from ..errors import LowerLevelInfeasible, LowerLevelUnbounded, SolverFailed
from .base import ExpressionLower, LowerSolution


NLPSOL_QUIET = {"print_time": False, "show_eval_warnings": False}
"""CasADi nlpsol options of every IPOPT solve: no timing report, and no console warning when a function evaluation
gives NaN or inf (outside its domain). IPOPT handles such a point (it shortens the step) or stops with status
Invalid_Number_Detected, which the caller's status and message carry."""


def ipopt_options(tol: float, max_iter: int, settings: dict[str, Any] | None = None) -> dict[str, Any]:
    """CasADi nlpsol options of a quiet IPOPT (NLPSOL_QUIET, print_level 0, no banner) with tolerance `tol`, iteration
    limit `max_iter` and further IPOPT `settings` (which may override these): the one builder of every IPOPT solve."""
    return {**NLPSOL_QUIET, "ipopt": {"print_level": 0, "sb": "yes", "tol": tol, "max_iter": max_iter,
                                      **(settings or {})}}


@dataclass
class ConvexNLPLower(ExpressionLower):
    """Convex f and g in y, affine h in y; any local solution is global."""

    kind = "nlp"

    def __post_init__(self) -> None:
        super().__post_init__()
        nlp = {"x": self.y, "p": ca.vertcat(self.x, self.params.sym), "f": self.f, "g": ca.vertcat(self.g, self.h)}
        opts = ipopt_options(param("lower.nlp_tol"), param("lower.nlp_max_iter"), {"acceptable_tol": param("lower.nlp_acceptable_tol")})
        self._solver = ca.nlpsol("lower_nlp", "ipopt", nlp, opts)
        self._ng = int(self.g.numel())

    def solve(self, x: np.ndarray, y0: np.ndarray | None = None) -> LowerSolution:
        """Solve the plain lower problem at x by IPOPT (tight tolerance), from y0 or zero."""
        x = self.check_point(x)
        lbg = np.concatenate([np.full(self._ng, -np.inf), np.zeros(self.h.numel())])
        ubg = np.zeros(self._ng + int(self.h.numel()))
        sol = self._solver(x0=np.zeros(self.n_y) if y0 is None else y0, p=np.concatenate([x, self.params.value]),
                           lbg=lbg, ubg=ubg)
        status = self._solver.stats()["return_status"]
        if status == "Infeasible_Problem_Detected":
            raise LowerLevelInfeasible(f"the lower level is infeasible at x = {x}")
        if status == "Diverging_Iterates":
            raise LowerLevelUnbounded(f"the lower level is unbounded below at x = {x} (IPOPT: Diverging_Iterates)")
        if status not in ("Solve_Succeeded", "Solved_To_Acceptable_Level"):
            raise SolverFailed(f"IPOPT did not solve the lower level at x = {x}: {status}")
        lam_g = np.asarray(sol["lam_g"]).ravel()
        return LowerSolution(np.asarray(sol["x"]).ravel(), float(sol["f"]), np.maximum(lam_g[: self._ng], 0.0),
                             lam_g[self._ng:], [], status, "ipopt (plain lower problem)")
