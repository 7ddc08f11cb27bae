"""Every tolerance, limit and count the methods and certificates read, in one registry (python-control's
`control.config.defaults`): `defaults["module.name"]` holds a value, `set_defaults("module", name=value)` changes it
for every later solve in the process, `reset_defaults()` restores the values below, and `param(key, given)` is the
one reader (an argument given by the caller, else the registry's value).

Each entry is (value, what it is and its unit). A method option whose default is None means "the registry's value":
`solve(p, method="hypergradient", max_iter=None)` runs `defaults["hypergradient.max_iter"]` steps.
"""

from __future__ import annotations

import math
from collections.abc import Iterator, MutableMapping
from dataclasses import dataclass
from numbers import Integral, Real
from typing import Any

import numpy as np

from .errors import ModelError, UnknownName, did_you_mean

ENTRIES: dict[str, tuple[Any, str]] = {
    # the certificate (bilevel.certificate)
    "certificate.tol": (1e-6, "tolerance of the certificate's scaled checks: lower KKT residuals, feasibility, gap to"
                              " the re-solve"),
    "certificate.nlp_starts": (8, "starts of the independent re-solve of a nonlinear lower level (count)"),
    "certificate.unique_rtol": (1e-9, "judging the re-solved lower solution unique, singular values of the active rows "
                                      "and eigenvalues of the reduced Hessian count as zero below this * max(1, the "
                                      "largest)"),
    # method hypergradient (and block-exact, the descent after differential-evolution)
    "hypergradient.starts": (4, "multistart starts of hypergradient and block-exact (count)"),
    "hypergradient.scale": (10.0, "half-width of the random starts' box where a bound is infinite (units of x)"),
    "hypergradient.gtol": (1e-7, "the descent stops when the projected step norm ||x - P(x - grad phi)|| is below "
                                 "this (units of x)"),
    "hypergradient.ftol": (1e-12, "the descent stops when one step decreases phi by less than this (relative)"),
    "hypergradient.max_iter": (500, "descent steps per start (count)"),
    "hypergradient.min_step": (2.0 ** -60, "the line search fails below this fraction of its trial step"),
    "hypergradient.auto_exact_dimension": (256, "exact_block='auto' takes an exact block whose trust-region "
                                                "subproblem has at most this dimension (count)"),
    "hypergradient.tie_rtol": (1e-6, "option prefer breaks ties among starts within this distance of the best "
                                     "objective (relative)"),
    "block_exact.gain_tol": (1e-5, "the exact-block ascent stops when its gain over ascent.window steps is below this "
                                   "(relative)"),
    "hypergradient.restoration_tol": (1e-12, "IPOPT's tol in the restoration NLP (the nearest upper point in the box "
                                             "where the lower level is feasible)"),
    "hypergradient.restoration_max_iter": (500, "IPOPT's iteration limit in that NLP (count)"),
    # the implicit-differentiation engine (bilevel.solvers.engine.implicit)
    "implicit.penalty": (1e4, "weight of the upper constraints' violation added to phi where they are penalized"),
    "implicit.active_tol": (1e-6, "a lower inequality is active where lam_i > this or |g_i| <= this (absolute)"),
    "implicit.kink_tol": (1e-9, "where some |G_i| or |H_j| <= this the penalty is not differentiable (least-norm "
                                "element used)"),
    # the engine's ascent loop (bilevel.solvers.engine.ascent)
    "ascent.armijo": (1e-4, "sufficient-increase constant of the Armijo backtracking (fraction)"),
    "ascent.window": (5, "the ascent's gain stop is measured over this many accepted steps (count)"),
    # the start sequence (bilevel.solvers.engine.starts)
    "starts.conditioning_steps": (10, "projected steps of the conditioning start, one budget radius or half-width "
                                      "each (count)"),
    # the KKT methods ipopt and relaxation (bilevel.solvers.ipopt)
    "ipopt.starts": (8, "multistart starts of ipopt and relaxation (count)"),
    "ipopt.scale": (10.0, "half-width of the random starts' box where a bound is infinite (units of x)"),
    "ipopt.nlp_tol": (1e-10, "IPOPT's tol on each NLP of ipopt and relaxation (its scaled KKT error)"),
    "ipopt.max_iter": (3000, "IPOPT iterations per NLP (count)"),
    "ipopt.acceptable_tol": (1e-7, "IPOPT's acceptable_tol: its 'solved to acceptable level' threshold"),
    "ipopt.max_wall_time": (300.0, "IPOPT max_wall_time per NLP solve (seconds)"),
    # method reduced (bilevel.solvers.reduced)
    "reduced.starts": (1, "starts of method reduced: the first of bilevel.solvers.engine.starts (a suggested start, "
                          "the conditioning start of a least-squares learner, else the declared start) (count)"),
    "reduced.scale": (10.0, "half-width of reduced's random starts where a bound is infinite (units of x)"),
    "reduced.nlp_tol": (1e-8, "IPOPT's tol on the reduced NLP (its scaled KKT error)"),
    "reduced.max_iter": (300, "IPOPT iterations of the reduced NLP per start (count)"),
    "ipopt.metis_from": (500, "KKT systems with at least this many variables plus constraints are ordered by METIS "
                              "(mumps_pivot_order 5) unless option ipopt chooses: MUMPS's automatic order factored "
                              "the DeePC learner's (920 rows) 5x slower; smaller ones keep MUMPS's choice (count)"),
    "ipopt.complementarity_t": (1e-9, "relaxation parameter t of the default complementarity mode Scholtes(t)"),
    "ipopt.polish_tie": (1e-6, "a further candidate is branch-polished only if it beats the polished one by more "
                               "than this (relative)"),
    "ipopt.warm_max_iter": (50, "IPOPT iterations of an NLP started from hypergradient's answer (count)"),
    "ipopt.warm_max_wall_time": (10.0, "IPOPT max_wall_time of an NLP started from hypergradient's answer "
                                       "(seconds)"),
    # method relaxation
    "relaxation.t0": (1.0, "first relaxation parameter t of the sequence"),
    "relaxation.factor": (0.1, "t is multiplied by this at each step (in (0, 1))"),
    "relaxation.t_min": (1e-12, "the sequence stops before t falls below this"),
    "relaxation.comp_tol": (1e-7, "the sequence stops when the complementarity residual is below this (absolute)"),
    # method differential-evolution (bilevel.solvers.evolution)
    "evolution.starts": (1, "multistart points seeded into the population (count)"),
    "evolution.pop_tol": (1e-8, "the search stops when std(population values) <= this * |mean| (relative)"),
    "evolution.members": (64, "cap on the default population size (count)"),
    "evolution.evaluations": (3000, "evaluations the default number of generations is sized to (count)"),
    # method global (bilevel.solvers.globalopt)
    "global.time_limit": (60.0, "wall-clock limit of method global (seconds)"),
    "global.node_limit": (100_000, "branch-and-bound nodes of method global (count)"),
    "global.gap": (1e-6, "method global stops when (upper - lower bound) / max(1, |best|) is below this"),
    "global.bigm_safety": (1e-6, "relative and absolute margin added to each LP maximum so that LP tolerances cannot "
                                 "make M too small"),
    "global.fix_tol": (1e-6, "a pair's side is fixed only if the other side's minimum exceeds this * max(1, its "
                             "maximum)"),
    "global.complementarity_tol": (1e-9, "branch-and-bound takes a node as complementary when its worst min(G_i, H_i)"
                                         " is below this * (1 + max |w|)"),
    "global.convexity_tol": (1e-9, "a Hessian counts as convex when its smallest eigenvalue >= -this * max(1, max "
                                   "|entry|)"),
    "global.max_box_vertices": (4096, "vertices of the upper box on which an x-dependent lower Hessian is checked, at"
                                      " most (count)"),
    "global.slater_tol": (1e-10, "IPOPT's tol in the Slater-point NLP that bounds the multipliers of a nonlinear lower "
                                 "level for SCIP"),
    "global.slater_max_iter": (500, "IPOPT's iteration limit in that NLP (count)"),
    "global.scip_feastol": (1e-9, "SCIP's feasibility tolerance (SCIP's own default is 1e-6; absolute)"),
    # multistart selection and dispatch (bilevel.solvers.engine.prepared, bilevel.solvers.registry)
    "solvers.feasibility_tol": (1e-6, "largest residual at which a start's end point counts as feasible"),
    "solvers.tie_rtol": (1e-9, "multistart: feasible end points whose objectives are within this of the best's tie, "
                               "and the first start among them wins (relative)"),
    "solvers.spread_rtol": (0.01, "a result's message reports its starts' spread when a feasible start ended this far "
                                  "(relative) from the best"),
    "solvers.small_lower": (256, "lower levels with at most this many variables run with one BLAS thread (count)"),
    "auto.min_upper": (20, "method auto takes hypergradient from this many upper entries on (count)"),
    "auto.global_time": (5.0, "method auto first tries global for at most this long on a problem in its class "
                              "(seconds)"),
    "auto.global_size": (60, "method auto tries global first on problems with at most this many upper plus lower "
                             "variables (count)"),
    # the local probe and the optimistic selection (bilevel.solvers.verdict.probe, bilevel.solvers.verdict.optimistic)
    "probe.directions": (4, "random directions the local probe tries at each radius (count)"),
    "probe.coordinates": (16, "up to this many upper variables the probe tries +/- each coordinate and the adjacent "
                              "pieces at a kink (count)"),
    "probe.rel_tol": (1e-8, "along random directions a neighbour is better only by more than this (relative)"),
    "probe.radius": (0.1, "largest radius of the local probe; it also probes at a tenth and a hundredth of it "
                          "(budget units)"),
    "probe.min_radius": (1e-9, "where no probe at radius probe.radius, a tenth or a hundredth of it is feasible, the "
                               "probe tries three decades smaller at a time down to this radius (probe.feas_tol "
                               "shrinks in proportion)"),
    "probe.feas_tol": (1e-9, "largest upper violation (G > 0, |H|) of a probed point that counts as feasible "
                             "(absolute)"),
    "probe.descent_rel_tol": (1e-5, "along first-order directions a neighbour is better only by more than this "
                                    "(relative)"),
    "optimistic.nlp_tol": (1e-10, "IPOPT's tol and constr_viol_tol in the optimistic selection's NLP over y"),
    "optimistic.max_iter": (500, "IPOPT's iteration limit in that NLP (count)"),
    "optimistic.slack": (1e-9, "slack of the optimistic selection's lower optimality row, f <= f* + slack (1 + |f*|) "
                               "(relative)"),
    "optimistic.row_tol": (1e-8, "largest row violation, relative to 1 + max |y|, at which a selection counts as "
                                 "feasible"),
    "optimistic.improve_rel_tol": (1e-5, "F must drop by more than this (relative to max(1, |F|)) for a better "
                                         "selection"),
    # box methods (bilevel.attacks.willems_methods)
    "destabilize.starts": (64, "points ascending together in method destabilize (count)"),
    "destabilize.max_iter": (100, "ascent steps of method destabilize (count)"),
    "destabilize.pool": (512, "random points screened for destabilize's starts (count)"),
    # the structured VRFT attacks alternating and joint (bilevel.attacks.vrft_methods)
    "vrft.starts": (1, "multistart starts of the alternating and joint VRFT attacks (count)"),
    "vrft.max_iter.maxmin": (60, "ascent steps per start of a VRFT max-min attack (count; the committed Table 1's)"),
    "vrft.max_iter.targeted": (500, "ascent steps per start of a VRFT targeted attack (count; it converges in "
                                    "118-195)"),
    "vrft.max_iter.destabilize": (200, "ascent steps per start of a VRFT destabilize attack (count)"),
    "vrft.gain_tol": (1e-4, "a VRFT attack's ascent stops when its gain over ascent.window steps is below this "
                            "(relative)"),
    "vrft.batch_sims": (16, "data sets per task of the VRFT reproduction's sweeps, their attacks solved together "
                            "(bilevel.attacks.vrft_batch; count)"),
    # many instances at once (bilevel.solvers.batch)
    "batch.min_size": (4, "solve_many runs a method's batched form on at least this many instances, below it one at "
                          "a time (count)"),
    "batch.max_rows": (256, "instances one batched ascent carries; more run in consecutive batches of this size "
                            "(count; the per-instance arrays stay in cache: 5.6 ms per VRFT attack at 256, 6.8 at "
                            "4,096)"),
    "batch.chunk": (32, "rows a batched evaluation computes in one stacked call (count; a few dozen keep the working "
                        "set of N = 512 signals in cache: 30 us per row at 32, 176 us at 2048)"),
    # the Willems attacks (bilevel.attacks.willems; WillemsAttack.shared_problem reads willems.shared_kept,
    # destabilize_attack destabilize.*, de_attack evolution.pop_tol)
    "willems.shared_kept": (4, "attack shapes (learner, criterion, sizes; the data are parameters) whose prepared "
                               "problems a process keeps (count)"),
    "willems.hypergradient.starts": (8, "multistart starts of hypergradient_attack (count)"),
    "willems.hypergradient.max_iter": (300, "descent steps per start of hypergradient_attack (count)"),
    "willems.hypergradient.ftol": (1e-10, "hypergradient_attack's descent stops when one step decreases phi by less "
                                          "than this (relative)"),
    "willems.evolution.max_iter": (300, "generations of de_attack (count)"),
    "willems.evolution.popsize": (5, "de_attack's population is this many members per poisoned entry (scipy's "
                                     "popsize)"),
    # the robust De Persis-Tesi learner (bilevel.ddc.robust_depersis_tesi)
    "robust_willems.lmi_margin": (1e-5, "the robust SDP's LMI is >= this * I (strict, so that numpy's re-check has room;"
                                        " absolute)"),
    "robust_willems.margin_steps": (3, "solves of the robust SDP, tau growing by margin_factor, until numpy's re-check "
                                       "passes (count)"),
    "robust_willems.margin_factor": (100.0, "growth of tau between the robust SDP's solves"),
    "robust_willems.check_margin": (1e-10, "verify_gain passes where G's and P's smallest eigenvalues are >= this "
                                           "times the scale of G's terms (relative; rounding is ~1e-16)"),
    # lower levels (bilevel.lower)
    "classify.y_probes": (16, "lower points drawn per upper sample when a lower Hessian depends on y (count)"),
    "classify.matrix_entries": (25_000_000, "a lower level declared by expressions is recognized as a matrix QP "
                                            "(lower_qp's form) when its constraint matrix has at most this many "
                                            "entries, stored dense (count)"),
    "classify.matrix_min_entries": (5_000, "... and at least this many: smaller lower levels keep the expression "
                                           "kinds, whose symbolic Jacobians cost little there and whose Clarabel "
                                           "solves (central on a degenerate face, where HiGHS gives a vertex) the "
                                           "textbook problems' multistart results hold with (count)"),
    "classify.matrix_rtol": (1e-9, "the recognized matrix QP must reproduce the expressions' values to this times "
                                   "each entry's scale (the sum of its terms' magnitudes)"),
    "matrix.feas_tol": (1e-12, "a matrix LP's HiGHS solution, or the previous solve's active set, is kept where it "
                               "violates no row by more than this * (1 + |b| + |A| |y|); else Clarabel solves (and "
                               "finds an LP infeasible that HiGHS, at its tolerance 1e-7, solved: Bard's 5.1.1, x > 4)"),
    "convexity.psd_tol": (1e-9, "a Hessian counts as PSD when its smallest eigenvalue >= -this * max(1, its largest "
                                "entry)"),
    "sdp.psd_tol": (1e-9, "relative PSD violation of M_k and Z_k tolerated in a polished SDP iterate"),
    "sdp.polished_tol": (1e-6, "largest KKT residual of a polished solution of an SDP that moves with x (its "
                               "derivative needs it)"),
    "sdp.free_rtol": (1e-10, "singular values below this times the largest count as zero (the directions an SDP sees)"),
    "sdp.continuation_tol": (1e-9, "KKT residual a Newton continuation from a nearby SDP solution must reach (no worse "
                                   "than a polished conic solve)"),
    "sdp.continuation_steps": (6, "Newton steps of the continuation from a nearby SDP solution (count)"),
    "lower.clarabel_tol": (1e-10, "Clarabel's tol_gap_abs, tol_gap_rel and tol_feas in every lower-level solve and the "
                                  "certificate's LP/QP/SDP re-solve (tighter than its 1e-8: certificates compare "
                                  "against these solutions)"),
    "lower.clarabel_ktratio": (1e-8, "Clarabel's tol_ktratio in the same solves"),
    "lower.nlp_tol": (1e-12, "IPOPT's tol in the solves of a convex NLP lower level (the certificate's re-solves)"),
    "lower.nlp_acceptable_tol": (1e-9, "IPOPT's acceptable_tol in the same solves"),
    "lower.nlp_max_iter": (3000, "IPOPT's iteration limit in the same solves (count)"),
    "lower.unique_rtol": (1e-10, "a QP lower level's solution counts as unique (method reduced applies) when the "
                                 "smallest eigenvalue of its Hessian at the start exceeds this * max(1, max |P|)"),
    "mpcc.tau": (1e-8, "relaxation parameter of a complementarity mode built without one (Scholtes(), Product(), "
                       "KanzowSchwartz(), FischerBurmeister()); method ipopt's own mode takes ipopt.complementarity_t"),
    "polish.active_tol": (1e-6, "a row or LMI eigenvalue is active when within this * (1 + its scale) of zero"),
    "polish.flip_tol": (1e-13, "a face's solution violating a sign condition by more than this * (1 + scale) moves "
                               "that constraint"),
    "polish.max_steps": (8, "Newton steps per face of the lower polish (count)"),
    "polish.max_faces": (4, "faces the lower polish tries: the first guess and active-set corrections (count)"),
    "residual.form_size": (10_000, "least squares whose symbolic Hessian would have more than rows x n_y^2 = this "
                                   "many terms use the residual form (count)"),
    "residual.affine_fill": (4, "residual data are a sparse product when its matrix has at most this many nonzeros "
                                "per operation of their expressions (count)"),
    "residual.numeric_squares_size": (1_000, "a sum of squares of y with at least this many nonzero coefficients is "
                                             "evaluated by BLAS (count)"),
    "residual.sparse_squares": (0.25, "below this fraction of nonzero coefficients a sum of squares' matrix is kept "
                                      "sparse"),
    "linear_maps.dense_limit": (25_000_000, "entries up to which an operator given only by its products is formed as "
                                            "a matrix (count)"),
    "spectral_radius.defective_cond": (1e12, "eigenvector matrices with a larger condition number are treated as "
                                             "singular (a defective top eigenvalue)"),
    # certified robustness (bilevel.robust)
    "robust.margin_rel_tol": (0.05, "certified_margin bisects delta_lb to a bracket of this times its top (relative)"),
    "robust.attack_rel_tol": (0.05, "the attack's budget search for delta_ub stops at this bracket (relative)"),
    "robust.smallest_delta": (1e-4, "certified_margin gives up below this fraction of delta_ub (delta_lb = 0)"),
    "robust.deepc_cost_factor": (2.0, "DeePC certificates prove the true tracking cost stays below this times the "
                                      "clean plan's (the defenses sweep's degradation goal; ratio)"),
    "robust.soundness_samples": (10_000, "random poisonings on the budget sphere of the sampling check (count)"),
    "robust.check_margin": (1e-9, "an independent re-check passes only with this margin above zero, relative to the "
                                  "size of the numbers it compares (rounding cannot make it pass)"),
}
"""The registry's entries: key -> (default value, what it is and its unit)."""

@dataclass(frozen=True)
class Range:
    """The values an entry takes: low <= value <= high (strict where open), integers for an integer default."""

    low: float = 0.0
    high: float = math.inf
    open_low: bool = False
    open_high: bool = False

    def holds(self, value: float) -> bool:
        above = value > self.low if self.open_low else value >= self.low
        below = value < self.high if self.open_high else value <= self.high
        return above and below

    def __str__(self) -> str:
        text = lambda v: f"{v:g}" if isinstance(v, float) else str(v)  # noqa: E731
        if self.high == math.inf:
            return f"{'>' if self.open_low else '>='} {text(self.low)}"
        return (f"in {'(' if self.open_low else '['}{text(self.low)}, {text(self.high)}"
                f"{')' if self.open_high else ']'}")


COUNT, POSITIVE, FRACTION = Range(1), Range(0.0, open_low=True), Range(0.0, 1.0, True, True)
RANGES: dict[str, Range] = {
    **{key: COUNT for key in ENTRIES if key.endswith((".starts", ".nlp_starts", ".popsize", ".members", ".evaluations",
                                                        ".pool", ".window", ".shared_kept", ".max_faces", ".y_probes",
                                                        ".max_box_vertices", ".batch_sims", ".min_size", ".chunk",
                                                        ".max_rows"))},
    **{key: POSITIVE for key in ENTRIES if key.endswith(("scale", "_tol", ".t0", ".t_min", "max_wall_time", ".penalty",
                                                         ".gtol"))
       and key not in ("ipopt.polish_tie",)},
    **{key: Range() for key in ("probe.rel_tol", "probe.descent_rel_tol", "probe.feas_tol", "optimistic.row_tol",
                                "optimistic.improve_rel_tol", "polish.active_tol", "polish.flip_tol", "sdp.psd_tol",
                                "convexity.psd_tol", "global.convexity_tol", "global.complementarity_tol",
                                "global.fix_tol", "hypergradient.tie_rtol", "implicit.kink_tol", "mpcc.tau")},
    "certificate.tol": Range(2.0 ** -52),  # a scaled residual is no smaller than the rounding of its evaluation
    "global.node_limit": Range(1, 2 ** 63 - 1),  # SCIP's node limit is a 64-bit integer
    "global.time_limit": POSITIVE, "probe.radius": POSITIVE, "lower.clarabel_ktratio": POSITIVE,
    "global.gap": FRACTION, "relaxation.factor": FRACTION, "hypergradient.min_step": FRACTION,
    "ascent.armijo": FRACTION,
    "global.scip_feastol": Range(1e-17, 1e-3),  # SCIP's own range for numerics/feastol
    "residual.sparse_squares": Range(0.0, 1.0),
    "spectral_radius.defective_cond": Range(1.0),
    "robust.deepc_cost_factor": Range(1.0, open_low=True),  # a level above the clean plan's own cost
}
"""Each entry's valid values where they are narrower than the default's, an integer >= 0 or a finite number >= 0:
counts are >= 1, step sizes and most tolerances > 0, fractions in (0, 1), and SCIP's limits SCIP's ranges."""


def _check_key(key: str) -> None:
    if key not in ENTRIES:
        raise UnknownName(f"unknown default {key!r}; {did_you_mean(key, ENTRIES)}the keys are listed by "
                          "bilevel.defaults.describe()")


def check(key: str, value: Any, name: str | None = None) -> None:
    """ModelError unless `value` is a valid value of entry `key` (its default's type, integer or finite number, in
    RANGES[key]); `name`: the option it was given as (None: set as the default itself)."""
    default, allowed = ENTRIES[key][0], RANGES.get(key, Range())
    integer = isinstance(default, int)
    ok = (isinstance(value, Integral) if integer else isinstance(value, Real) and math.isfinite(value)) \
        and not isinstance(value, (bool, np.bool_)) and allowed.holds(value)
    if not ok:
        want = f"{'an integer' if integer else 'a finite number'} {allowed}"
        what = f"default {key}" if name is None else f"option {name}"
        raise ModelError(f"{what}={value!r} is invalid: it must be {want} ({ENTRIES[key][1]})")


class Defaults(MutableMapping):
    """The registry: a dict of the ENTRIES' keys whose keys cannot be added or removed, only set (checked)."""

    def __init__(self) -> None:
        self._values = {key: value for key, (value, _) in ENTRIES.items()}

    def __getitem__(self, key: str) -> Any:
        try:
            return self._values[key]
        except KeyError:
            _check_key(key)
            raise

    def __setitem__(self, key: str, value: Any) -> None:
        _check_key(key)
        check(key, value)
        self._values[key] = value

    def __delitem__(self, key: str) -> None:
        raise ModelError(f"defaults cannot be removed ({key!r}); reset_defaults() restores them")

    def __iter__(self) -> Iterator[str]:
        return iter(self._values)

    def __len__(self) -> int:
        return len(self._values)

    def __repr__(self) -> str:
        return f"Defaults({self._values!r})"

    def describe(self, prefix: str = "") -> str:
        """One line per default whose key starts with `prefix`: key = current value: what it is and its unit."""
        return "\n".join(f"{key} = {self._values[key]!r}: {doc}" for key, (_, doc) in ENTRIES.items()
                         if key.startswith(prefix))


defaults = Defaults()
"""The one registry every method and certificate reads (through param); `bilevel.defaults` is this object (the
package exports it under the module's name), so `bilevel.defaults.describe("probe")` lists the probe's entries."""


def param(key: str, given: Any = None) -> Any:
    """The value to use: `given` where the caller passed one (not None; checked against the entry's type and range,
    the one check of every option the registry holds), else defaults[key] (read directly: this runs inside the
    methods' loops)."""
    if given is not None:
        check(key, given, key.split(".")[1] if key.startswith("vrft.max_iter.") else key.rsplit(".", 1)[1])
        return given
    try:
        return defaults._values[key]
    except KeyError:
        _check_key(key)
        raise


def set_defaults(module: str, **values: Any) -> None:
    """Set defaults["module.name"] = value for each name=value (e.g. set_defaults("hypergradient", max_iter=100))."""
    modules = {key.split(".")[0] for key in ENTRIES}
    if module not in modules:
        raise ModelError(f"set_defaults: unknown module {module!r}; {did_you_mean(module, modules)}"
                         f"the modules are {', '.join(sorted(modules))}")
    for name in values:
        _check_key(f"{module}.{name}")
    for name, value in values.items():
        defaults[f"{module}.{name}"] = value


def reset_defaults() -> None:
    """Restore every default to the value it has in ENTRIES."""
    for key, (value, _) in ENTRIES.items():
        defaults._values[key] = value
