"""The defaults registry (bilevel.defaults): one documented entry per tolerance, limit and count, read at call time;
set_defaults / reset_defaults; methods' explicit keyword options, listed by show_options and checked against their
signatures; renamed options answer with their new names."""

from __future__ import annotations

import inspect

import pytest

import bilevel as bl
from bilevel.defaults import ENTRIES, param
from bilevel.errors import ModelError, UnknownOption
from bilevel.attacks.vrft_methods import METHODS as VRFT_METHODS
from bilevel.attacks.willems import de_attack, destabilize_attack, hypergradient_attack
from bilevel.solvers.engine.prepared import options_of
from bilevel.attacks.willems_methods import destabilize, random_signs
from tests.docs_pages import run_page


def bard() -> bl.BilevelProblem:
    """Bard (1998) Example 5.1.1 with the upper variable boxed: optimum F = -12 at x = y = 4."""
    p = bl.BilevelProblem("bard-boxed")
    x = p.upper_variable("x", lb=0, ub=10)
    y = p.lower_variable("y", lb=0)
    p.minimize_upper(x - 4 * y)
    p.minimize_lower(y)
    for c in (-x - y <= -3, -2 * x + y <= 0, 2 * x + y <= 12, 3 * x - 2 * y <= 4):
        p.lower_constraint(c)
    return p


BEFORE = {  # the module constants and option defaults the registry replaced, as they were
    "certificate.tol": 1e-6, "certificate.nlp_starts": 8, "hypergradient.starts": 4, "hypergradient.scale": 10.0,
    "hypergradient.gtol": 1e-7, "hypergradient.ftol": 1e-12, "hypergradient.max_iter": 500,
    "hypergradient.min_step": 2.0 ** -60, "hypergradient.auto_exact_dimension": 256, "hypergradient.tie_rtol": 1e-6,
    "block_exact.gain_tol": 1e-5, "implicit.penalty": 1e4, "implicit.active_tol": 1e-6, "implicit.kink_tol": 1e-9,
    "ascent.armijo": 1e-4, "ascent.window": 5, "starts.conditioning_steps": 10, "ipopt.starts": 8,
    "reduced.starts": 1, "reduced.scale": 10.0, "reduced.nlp_tol": 1e-8, "reduced.max_iter": 300,
    "ipopt.metis_from": 500, "ipopt.scale": 10.0, "ipopt.nlp_tol": 1e-10, "ipopt.max_iter": 3000, "ipopt.acceptable_tol": 1e-7,
    "ipopt.max_wall_time": 300.0, "ipopt.complementarity_t": 1e-9, "ipopt.polish_tie": 1e-6,
    "ipopt.warm_max_iter": 50, "ipopt.warm_max_wall_time": 10.0, "relaxation.t0": 1.0, "relaxation.factor": 0.1,
    "relaxation.t_min": 1e-12, "relaxation.comp_tol": 1e-7, "evolution.starts": 1, "evolution.pop_tol": 1e-8,
    "evolution.members": 64, "evolution.evaluations": 3000, "global.time_limit": 60.0, "global.node_limit": 100_000,
    "global.gap": 1e-6, "global.bigm_safety": 1e-6, "global.fix_tol": 1e-6, "global.complementarity_tol": 1e-9,
    "global.convexity_tol": 1e-9, "global.max_box_vertices": 4096, "global.scip_feastol": 1e-9,
    "solvers.feasibility_tol": 1e-6, "solvers.tie_rtol": 1e-9, "solvers.spread_rtol": 0.01,
    "solvers.small_lower": 256, "auto.min_upper": 20,
    "auto.global_time": 5.0, "auto.global_size": 60, "probe.directions": 4, "probe.coordinates": 16,
    "probe.rel_tol": 1e-8, "probe.min_radius": 1e-9, "probe.feas_tol": 1e-9, "probe.descent_rel_tol": 1e-5,
    "optimistic.slack": 1e-9, "optimistic.row_tol": 1e-8, "optimistic.improve_rel_tol": 1e-5,
    "destabilize.starts": 64, "destabilize.max_iter": 100, "destabilize.pool": 512, "classify.y_probes": 16,
    "classify.matrix_entries": 25_000_000, "classify.matrix_min_entries": 5_000, "classify.matrix_rtol": 1e-9, "matrix.feas_tol": 1e-12,
    "convexity.psd_tol": 1e-9, "sdp.psd_tol": 1e-9, "sdp.polished_tol": 1e-6, "sdp.free_rtol": 1e-10,
    "sdp.continuation_tol": 1e-9, "sdp.continuation_steps": 6,
    "polish.active_tol": 1e-6, "polish.flip_tol": 1e-13, "polish.max_steps": 8, "polish.max_faces": 4,
    "residual.form_size": 10_000, "residual.affine_fill": 4, "residual.numeric_squares_size": 1_000,
    "residual.sparse_squares": 0.25, "linear_maps.dense_limit": 25_000_000, "spectral_radius.defective_cond": 1e12,
    "vrft.starts": 1, "vrft.max_iter.maxmin": 60, "vrft.max_iter.targeted": 500, "vrft.max_iter.destabilize": 200,
    "vrft.gain_tol": 1e-4, "vrft.batch_sims": 16, "batch.min_size": 4, "batch.chunk": 32, "batch.max_rows": 256,
    "willems.shared_kept": 4, "willems.hypergradient.starts": 8,
    "willems.hypergradient.max_iter": 300, "willems.hypergradient.ftol": 1e-10, "willems.evolution.max_iter": 300,
    "willems.evolution.popsize": 5,
    "robust.margin_rel_tol": 0.05, "robust.attack_rel_tol": 0.05, "robust.smallest_delta": 1e-4,
    "robust.deepc_cost_factor": 2.0, "robust.soundness_samples": 10_000, "robust.check_margin": 1e-9,
    "robust_willems.lmi_margin": 1e-5,
    "robust_willems.margin_steps": 3, "robust_willems.margin_factor": 100.0, "robust_willems.check_margin": 1e-10,
    "certificate.unique_rtol": 1e-9, "probe.radius": 0.1, "lower.clarabel_tol": 1e-10, "lower.clarabel_ktratio": 1e-8,
    "lower.nlp_tol": 1e-12, "lower.nlp_acceptable_tol": 1e-9, "mpcc.tau": 1e-8,
    "lower.nlp_max_iter": 3000, "lower.unique_rtol": 1e-10, "global.slater_tol": 1e-10, "global.slater_max_iter": 500,
    "optimistic.nlp_tol": 1e-10, "optimistic.max_iter": 500, "hypergradient.restoration_tol": 1e-12,
    "hypergradient.restoration_max_iter": 500,
}

METHOD_FUNCTIONS = {**{name: fn for name, fn in bl.METHODS.items()}, "destabilize": destabilize,
                    "random-signs": random_signs, **{f"vrft-{name}": fn for name, fn in VRFT_METHODS.items()},
                    "hypergradient_attack": hypergradient_attack, "de_attack": de_attack,
                    "destabilize_attack": destabilize_attack}


def test_every_entry_keeps_its_former_value_and_is_documented() -> None:
    assert set(ENTRIES) == set(BEFORE)
    for key, (value, doc) in ENTRIES.items():
        assert value == BEFORE[key] and type(value) is type(BEFORE[key]), key
        assert bl.defaults[key] == value and len(doc) > 20, key
    assert len(bl.defaults.describe().splitlines()) == len(ENTRIES)


def test_set_defaults_changes_later_solves_and_reset_restores() -> None:
    first = bard().solve("hypergradient", starts=1, seed=0)
    try:
        bl.set_defaults("hypergradient", max_iter=1)
        assert bl.defaults["hypergradient.max_iter"] == 1 and param("hypergradient.max_iter", 7) == 7
        short = bard().solve("hypergradient", starts=1, seed=0)
        assert short.nit <= 1 < first.nit
    finally:
        bl.reset_defaults()
    assert bl.defaults["hypergradient.max_iter"] == 500
    again = bard().solve("hypergradient", starts=1, seed=0)
    assert again.upper_objective == first.upper_objective and again.nit == first.nit


@pytest.mark.parametrize("call, match", [
    (lambda: bl.set_defaults("hypergrad", max_iter=3), "did you mean 'hypergradient'"),
    (lambda: bl.set_defaults("certificate", tol=-1.0), "certificate.tol=-1.0 is invalid"),
    (lambda: bl.set_defaults("ipopt", starts=2.5), "ipopt.starts=2.5 is invalid"),
    (lambda: bl.defaults.pop("certificate.tol"), "cannot be removed"),
])
def test_unknown_keys_and_bad_values_are_model_errors(call, match) -> None:
    with pytest.raises(ModelError, match=match):
        call()
    assert bl.defaults == {key: value for key, (value, _) in ENTRIES.items()}


@pytest.mark.parametrize("call", [lambda: bl.defaults["hypergradient.maxiter"],
                                  lambda: bl.set_defaults("hypergradient", maxiter=3)])
def test_an_unknown_key_is_an_unknown_name_and_the_registry_a_mapping(call) -> None:
    """A misspelt key names the closest keys, as an UnknownName: a KeyError, so the registry keeps the Mapping
    protocol ('name' in bl.defaults was a ModelError traceback, bl.defaults.get(key, default) too)."""
    with pytest.raises(bl.UnknownName, match="did you mean 'hypergradient.max_iter'"):
        call()
    assert "name" not in bl.defaults and "certificate.tol" in bl.defaults
    assert bl.defaults.get("hypergradient.maxiter", 7) == 7 and bl.defaults.get("ipopt.starts") == 8


@pytest.mark.parametrize("module, values, match", [
    ("hypergradient", {"starts": 0}, "hypergradient.starts=0 is invalid: it must be an integer >= 1"),
    ("certificate", {"tol": 0}, "certificate.tol=0 is invalid: it must be a finite number >= 2.22045e-16"),
    ("certificate", {"tol": 1e-300}, "certificate.tol=1e-300 is invalid"),
    ("global", {"scip_feastol": 0.0}, "global.scip_feastol=0.0 is invalid: it must be a finite number in "
                                      "\\[1e-17, 0.001\\]"),
    ("global", {"node_limit": 2 ** 70}, "global.node_limit=1180591620717411303424 is invalid"),
    ("relaxation", {"factor": 1.0}, "relaxation.factor=1.0 is invalid: it must be a finite number in \\(0, 1\\)"),
    ("ipopt", {"starts": True}, "ipopt.starts=True is invalid"),
])
def test_the_registry_checks_each_entry_against_its_range(module: str, values: dict, match: str) -> None:
    """Values the methods cannot use are refused when set, not accepted and then a traceback at the next solve
    (set_defaults(method, starts=0), certificate_tol=0, SCIP's feastol 0)."""
    with pytest.raises(ModelError, match=match):
        bl.set_defaults(module, **values)
    assert bl.defaults == {key: value for key, (value, _) in ENTRIES.items()}


@pytest.mark.parametrize("name", sorted(METHOD_FUNCTIONS))
def test_help_lists_every_option_of_every_method(name: str) -> None:
    """Each method's options are keyword-only parameters (scipy's _minimize_* style), each named in its docstring,
    listed by show_options; an option with a registry default defaults to None."""
    fn = METHOD_FUNCTIONS[name]
    doc = inspect.getdoc(fn)
    assert options_of(fn), name
    for option in options_of(fn):
        assert option in doc, (name, option)
    shown = bl.show_options(name if name in bl.METHODS else fn)
    assert all(f"\n{option}: " in "\n" + shown for option in options_of(fn)), shown


def test_the_solve_docstring_names_every_method_and_where_options_are_listed() -> None:
    doc = inspect.getdoc(bl.BilevelProblem.solve)
    assert all(f'"{name}"' in doc for name in bl.METHODS) and "show_options" in doc


@pytest.mark.parametrize("method, option, new", [
    ("hypergradient", "tol", "gtol"), ("block-exact", "tol", "gain_tol"), ("ipopt", "tol", "nlp_tol"),
    ("ipopt", "polish", "branch_polish"), ("relaxation", "tol", "nlp_tol"),
    ("relaxation", "polish", "branch_polish"), ("differential-evolution", "tol", "pop_tol"),
])
def test_renamed_options_name_their_new_name(method: str, option: str, new: str) -> None:
    value = True if option == "polish" else 1e-8
    with pytest.raises(UnknownOption, match=f"{option} was renamed: use {new}"):
        bard().solve(method, **{option: value})


def test_a_misspelt_option_is_rejected_with_the_accepted_ones() -> None:
    with pytest.raises(UnknownOption, match="did you mean 'max_iter'.*it accepts: .*gtol"):
        bard().solve("hypergradient", maxiter=3)


def test_renamed_attributes_and_keywords_name_their_new_names() -> None:
    p = bard()
    p.suggest_start(x=4.0)
    res = p.solve("hypergradient", starts=2)
    assert len(p.suggested_starts) == 1 and len(res.start_records) == 2
    with pytest.raises(AttributeError, match="use suggested_starts"):
        _ = p.starts
    with pytest.raises(AttributeError, match="use start_records"):
        _ = res.starts
    old = {k: v for k, v in res.to_dict().items() if k != "start_records"} | {"starts": list(res.start_records)}
    assert bl.BilevelResult.from_dict(old).start_records == bl.BilevelResult.from_dict(res.to_dict()).start_records
    for old_name, new in (("maxiter", "max_iter"), ("tol", "pop_tol")):
        with pytest.raises(UnknownOption, match=f"{old_name} was renamed: use {new}"):
            de_attack(None, **{old_name: 3})


def test_options_page_runs_as_printed() -> None:
    try:
        run_page("options.md")
    finally:
        bl.reset_defaults()


def test_the_attacks_read_their_registry_defaults_and_check_their_options() -> None:
    """None options of the VRFT and Willems attacks read "vrft.*" and "willems.hypergradient.*": an attack under a
    changed registry value equals the one given that value; a misspelt option names the closest accepted one."""
    from bilevel.attacks import attack_alternating, attack_instance
    from bilevel.problems.willems import build_attack

    atk, willems = attack_instance("maxmin", N=64, seed=1), build_attack(horizon=10, seed=0, delta_u=0.3)
    given = attack_alternating(atk, max_iter=3, gain_tol=1e-3)
    given_w = hypergradient_attack(willems, starts=1, max_iter=4, stop_when_unstable=False)
    try:
        bl.set_defaults("vrft", **{"max_iter.maxmin": 3, "gain_tol": 1e-3})
        bl.set_defaults("willems", **{"hypergradient.starts": 1, "hypergradient.max_iter": 4})
        read = attack_alternating(atk)
        read_w = hypergradient_attack(willems, stop_when_unstable=False)
    finally:
        bl.reset_defaults()
    assert read.upper_objective == given.upper_objective and read.nit == given.nit <= 3
    assert read_w.upper_objective == given_w.upper_objective and len(read_w.start_records) == 1
    for call in (lambda: attack_alternating(atk, maxiter=3), lambda: hypergradient_attack(willems, maxiter=3)):
        with pytest.raises(UnknownOption, match="did you mean 'max_iter'"):
            call()
