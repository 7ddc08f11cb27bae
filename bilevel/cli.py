"""Command line: `bilevel list | solve | compare | reproduce`."""

from __future__ import annotations

import argparse
import contextlib
import inspect
import json
import math
import os
import sys
import tempfile
import typing
from importlib import metadata
from types import UnionType
from typing import Any, Callable, Sequence

import numpy as np

from .errors import BilevelError, InvalidData, ModelError, UnknownName, UnknownOption, did_you_mean
from .files import atomic_open
from .problems import registry
from .result import SHOWN
from .solvers import METHODS, solve
from .solvers.registry import AUTO

WILLEMS_SELECTIONS = ("min-norm", "tikhonov", "clarabel", "scs")
"""bilevel.problems.willems_instance.SELECTIONS, spelled out so the parser does not import the Willems problems (~1 s)."""


def _cmd_list(args: argparse.Namespace) -> int:
    if args.params is not None:
        if args.tag is not None:
            raise ModelError("--params NAME lists one problem's parameters and --tag filters the list; give one")
        return _list_params(args.params)
    if args.tag is not None and args.tag not in (tags := {t for n in registry.names() for t in registry.spec(n).tags}):
        raise UnknownName(f"--tag {args.tag!r}: no problem carries it; {did_you_mean(args.tag, tags)}known tags: "
                          f"{', '.join(sorted(tags))}")
    rows = [registry.spec(n) for n in registry.names(args.tag)]
    width = max((len(s.name) for s in rows), default=4)
    for s in rows:
        opt = "-" if s.optimum is None else f"{s.optimum:.6g}"
        print(f"{s.name.ljust(width)}  optimum {opt:>10}  [{', '.join(s.tags)}]  {s.description}")
    print(f"{len(rows)} problems; methods: {', '.join(sorted(METHODS))}; `bilevel list --params NAME` lists a "
          "problem's parameters")
    return 0


def _type_name(kind: object) -> str:
    """A declared parameter type as the user writes its value: int, float, one of a, b, ... (optional: or none)."""
    args = typing.get_args(kind)
    if typing.get_origin(kind) in (typing.Union, UnionType) and type(None) in args:
        rest = [a for a in args if a is not type(None)]
        return (_type_name(rest[0]) if len(rest) == 1 else " | ".join(map(_type_name, rest))) + " or none"
    if typing.get_origin(kind) is typing.Literal:
        return "one of " + ", ".join(map(str, args))
    return getattr(kind, "__name__", None) or str(kind or "JSON")


def _list_params(name: str) -> int:
    """Print problem `name`'s parameters (--param NAME=VALUE): the registry's defaults and the builder's signature."""
    s = registry.spec(name)
    types = _declared_types(s.build, s.defaults)
    parameters = inspect.signature(s.build).parameters
    required = [k for k, p in parameters.items() if p.default is inspect.Parameter.empty
                and p.kind not in (inspect.Parameter.VAR_POSITIONAL, inspect.Parameter.VAR_KEYWORD)]
    print(f"{name}: {s.description}")
    text = lambda v: v if isinstance(v, str) else json.dumps(v)  # noqa: E731  (as --param takes it)
    rows = [(k, _type_name(types.get(k)), "(required)" if k in required else text(s.defaults[k]))
            for k in [*required, *s.defaults]]
    widths = [max((len(r[i]) for r in rows), default=0) for i in range(2)]
    for k, kind, default in rows:
        print(f"  {k.ljust(widths[0])}  {kind.ljust(widths[1])}  {default}")
    forwards = any(p.kind is inspect.Parameter.VAR_KEYWORD for p in parameters.values())
    if not rows:
        print("no parameters" + (" listed; its builder takes keyword parameters (see its documentation)" if forwards
                                 else ""))
    else:
        example = "VALUE" if rows[0][0] in required else rows[0][2]
        print(f"give them as --param NAME=VALUE, e.g. bilevel solve {name} --param {rows[0][0]}={example}"
              + ("; its builder may take further keyword parameters (see its documentation)" if forwards else ""))
    if _structured(name) is not None:
        _list_attack_options(name)
    return 0


def _list_attack_options(name: str) -> None:
    """Print the options of problem `name`'s structured attack (--option NAME=VALUE) from its signatures, and the
    registry's values their default None takes."""
    from .attacks.registry import attack_options
    from .defaults import defaults

    options, types = _attack_parameters(name)
    prefix = attack_options(name)[1]
    keys = [key for key in defaults if key.startswith(prefix)]
    registry = {k for k, p in options.items() if p.default is None and any(f".{k}" in key for key in keys)}
    rows = [(k, _type_name(types.get(k)), "registry (below)" if k in registry else p.default
             if isinstance(p.default, str) else json.dumps(p.default)) for k, p in options.items()]
    widths = [max(len(r[i]) for r in rows) for i in range(2)]
    print(f"structured attack (--method {STRUCTURED}, the default; --starts and --seed set its starts and seed), "
          "options given as --option NAME=VALUE:")
    for k, kind, default in rows:
        print(f"  {k.ljust(widths[0])}  {kind.ljust(widths[1])}  {default}")
    print("registry defaults (bilevel.defaults, bilevel.set_defaults):")
    print("\n".join("  " + line for line in defaults.describe(prefix).splitlines()))


def _parse_value(text: str) -> object:
    try:
        return json.loads(text)
    except json.JSONDecodeError:
        return text


def _pairs(items: list[str], flag: str) -> dict[str, str]:
    """NAME=VALUE strings to a dict of the raw VALUE texts (each NAME once)."""
    bad = [kv for kv in items if "=" not in kv or not kv.split("=", 1)[0]]
    if bad:
        raise ModelError(f"{flag} {bad[0]!r} is not NAME=VALUE; write e.g. {flag} starts=4")
    pairs = [kv.split("=", 1) for kv in items]
    if twice := sorted({k for k, _ in pairs if [n for n, _ in pairs].count(k) > 1}):
        raise ModelError(f"{flag} {', '.join(twice)} given more than once; give each NAME once")
    return dict(pairs)


EXAMPLES = {bool: ("true or false", "true"), int: ("an integer", "3"), float: ("a finite number", "0.1")}


def _convert(flag: str, name: str, text: str, kind: object) -> object:
    """The --param/--option value `text` as the declared type `kind` (JSON when nothing usable is declared)."""
    args = typing.get_args(kind)
    if typing.get_origin(kind) in (typing.Union, UnionType) and type(None) in args:
        if text.lower() in ("none", "null"):
            return None
        rest = [a for a in args if a is not type(None)]
        kind = rest[0] if len(rest) == 1 else None
    if typing.get_origin(kind) is typing.Literal:
        if text not in (allowed := [str(a) for a in typing.get_args(kind)]):
            raise ModelError(f"{flag} {name}={text!r}: expected one of {', '.join(allowed)}")
        return typing.get_args(kind)[allowed.index(text)]
    if kind is str:
        return text
    value = _parse_value(text)
    ok = {bool: isinstance(value, bool), int: isinstance(value, int) and not isinstance(value, bool),
          float: isinstance(value, (int, float)) and not isinstance(value, bool) and math.isfinite(value)}
    if kind in ok and not ok[kind]:
        what, example = EXAMPLES[kind]
        raise ModelError(f"{flag} {name}={text!r}: expected {what} ({kind.__name__}), e.g. {flag} {name}={example}")
    if isinstance(value, float) and math.isnan(value):
        raise ModelError(f"{flag} {name}={text!r}: NaN is not a value; give a number")
    return float(value) if kind is float else value


def _declared_types(build: Callable[..., object], defaults: dict[str, Any]) -> dict[str, object]:
    """Each parameter's declared type: the builder's annotation, else the type of its default."""
    types: dict[str, object] = {k: type(v) for k, v in defaults.items() if v is not None}
    try:
        hints = typing.get_type_hints(build)
        parameters = inspect.signature(build).parameters
    except Exception:  # annotations that do not resolve: the defaults' types are all there is
        return types
    for k, p in parameters.items():
        if k in hints:
            types[k] = hints[k]
        elif p.default is not inspect.Parameter.empty and p.default is not None:
            types[k] = type(p.default)
    return types


def _problem_params(name: str, raw: dict[str, str]) -> dict[str, object]:
    """The --param values problem `name` has, typed as its builder declares; a name that is neither in its builder's
    signature nor (for a builder taking **params) among the registry's listed parameters is refused before it runs."""
    s = registry.spec(name)
    types = _declared_types(s.build, s.defaults)
    parameters = inspect.signature(s.build).parameters.values()
    accepted = {p.name for p in parameters if p.kind not in (inspect.Parameter.VAR_POSITIONAL,
                                                             inspect.Parameter.VAR_KEYWORD)}
    if any(p.kind is inspect.Parameter.VAR_KEYWORD for p in parameters):
        accepted |= set(s.defaults)
    if unknown := sorted(set(raw) - accepted):
        raise ModelError(f"problem {name!r} rejected its parameters: --param {', '.join(unknown)} is not one of "
                         f"them ({', '.join(sorted(accepted)) or 'it has none'})")
    return {k: _convert("--param", k, v, types.get(k)) for k, v in raw.items()}


def _method_options(raw: dict[str, str]) -> dict[str, object]:
    """--option values (JSON where they are JSON); names that are solve()'s own arguments are refused."""
    if reserved := sorted(set(raw) & {"problem", "method"}):
        raise ModelError(f"--option {', '.join(reserved)}: a reserved argument, not a method option; name the "
                         "problem as PROBLEM and the method with --method")
    return {k: _convert("--option", k, v, None) for k, v in raw.items()}


OPTION_RULE = ("an explicit flag (--starts, --seed) > --option NAME=VALUE > the registry's default (bilevel.defaults: "
               "e.g. starts of reduced 1, hypergradient 4, ipopt 8); a flag and an --option for the same option is an "
               "error, and a flag not given sends nothing")
"""How `bilevel solve` resolves a method option given more than one way (docs/options.md, `bilevel solve --help`)."""


def _with_flags(options: dict[str, object], flags: dict[str, object]) -> dict[str, object]:
    """The method options with the flags given (not None) added; a flag also given as --option is refused."""
    if both := sorted(k for k, v in flags.items() if v is not None and k in options):
        name = both[0]
        raise ModelError(f"--{name} {flags[name]} and --option {name}={options[name]!r} give option {name} twice; "
                         f"give one ({OPTION_RULE})")
    return {**options, **{k: v for k, v in flags.items() if v is not None}}


STRUCTURED = "structured"
"""--method of a registered attack problem's own attack (bilevel.attacks.registry), its default."""


def _structured(name: str) -> Callable[..., Any] | None:
    """Problem `name`'s structured attack, or None."""
    from .attacks.registry import STRUCTURED as ATTACKS

    return ATTACKS.get(name)


def _attack_options(name: str, raw: dict[str, str]) -> dict[str, object]:
    """--option values of a structured attack, typed by its signatures (_attack_parameters)."""
    accepted, types = _attack_parameters(name)
    if unknown := sorted(set(raw) - set(accepted)):
        raise ModelError(f"--option {', '.join(unknown)}: the structured attack of {name} takes "
                         f"{', '.join(accepted)}; name a generic --method for method options")
    return {k: _convert("--option", k, v, types.get(k)) for k, v in raw.items()}


def _attack_parameters(name: str) -> tuple[dict[str, inspect.Parameter], dict[str, object]]:
    """A structured attack's options other than starts and seed (--starts, --seed), with their declared types: the
    named keywords of its run (bilevel.attacks.registry) and the keyword-only ones of its method (attack_options), with
    the run's defaults."""
    from .attacks.registry import attack_options

    method, _, defaults = attack_options(name)
    functions = (method, _structured(name))
    parameters = {k: p.replace(default=defaults.get(k, p.default)) for fn in functions
                  for k, p in inspect.signature(fn).parameters.items()
                  if k not in ("starts", "seed") and p.default is not inspect.Parameter.empty}
    return parameters, {k: v for fn in functions for k, v in typing.get_type_hints(fn).items()}


def _cmd_solve(args: argparse.Namespace) -> int:
    attack = _structured(args.problem)
    if args.method not in (None, AUTO, STRUCTURED, *METHODS):
        raise ModelError(f"unknown method {args.method!r}; choose {AUTO}, {STRUCTURED} (a problem's own attack: "
                         f"vrft-*, willems-*) or a registered method: {', '.join(sorted(METHODS))}")
    params = _problem_params(args.problem, _pairs(args.param, "--param"))
    raw_options = _pairs(args.option, "--option")
    structured = attack is not None and args.method in (None, STRUCTURED)
    if structured:
        options = _attack_options(args.problem, raw_options)
        starts = {} if args.starts is None else {"starts": args.starts}
        if args.verbose:
            if "verbose" not in _attack_parameters(args.problem)[0]:
                raise ModelError(f"--verbose: the structured attack of {args.problem} reports no progress; give a "
                                 f"generic --method (e.g. --method {AUTO}), whose methods all do")
            options = _with_flags(options, {"verbose": True})
        if "seed" in params and args.seed is not None and args.seed != params["seed"]:
            raise ModelError(f"--seed {args.seed} and --param seed={params['seed']}: a structured attack's seed is also "
                             "its data's; give one")
        seed = params.pop("seed", args.seed or 0)
        result = attack(seed=seed, **starts, **registry.params_for(args.problem, params), **options)
    else:
        if args.method == STRUCTURED:
            raise ModelError(f"{args.problem} has no structured attack; choose {AUTO} or a registered method: "
                             f"{', '.join(sorted(METHODS))}")
        problem = registry.get(args.problem, **params)
        options = _with_flags(_method_options(raw_options), {"starts": args.starts, "seed": args.seed,
                                                             "verbose": True if args.verbose else None})
        result = solve(problem, method=args.method or AUTO, **{"seed": 0, **options})
    print(result)
    if clean := {k: v for k, v in result.stats.items() if k.endswith("_clean") and np.ndim(v) == 0}:
        print("clean data (the scale of the attack's numbers): " + ", ".join(f"{k} {float(v):.6g}"
                                                                           for k, v in clean.items()))
    if "spectral_radius" in result.stats:  # an attack's outcome on the true closed loop
        from .attacks.outcome import unstable

        print(f"spectral radius of the true closed loop {result.stats['spectral_radius']:.6g} (unstable: "
              f"{unstable(result)})")
    if not args.json and any(np.size(v) > SHOWN for v in (*result.x.values(), *result.y.values())):
        print(f"(arrays of more than {SHOWN} entries are summarized; --json PATH writes every value)")
    known = registry.spec(args.problem).optimum
    if known is not None and result.upper_objective is not None:
        gap = abs(result.upper_objective - known) / max(1.0, abs(known))
        print(f"known optimum {known:.10g}; relative gap {gap:.2e}  ({registry.spec(args.problem).source})")
    if args.json:
        result.to_json(args.json)
        print(f"wrote {args.json}")
    certified = result.certificate is not None and result.certificate.passed
    return 0 if result.success or (structured and certified) else 1  # an attack's certified point is its answer


INTEGER_FLAGS = {"sims": (1, 10**6), "starts": (1, 10**6), "workers": (1, 1024), "seed": (0, 2**63 - 1)}
"""Integer flags -> (smallest, largest) accepted value: sane maxima, so that a typo is refused rather than run."""


def _check_numbers(args: argparse.Namespace) -> None:
    """Numeric and executor flags of every command, checked before any work."""
    for flag, (low, high) in INTEGER_FLAGS.items():
        value = getattr(args, flag, None)
        if value is not None and not low <= value <= high:
            raise ModelError(f"--{flag}: {flag}={value} is invalid; give an integer in [{low}, {high}]")
    if getattr(args, "dask", None) is not None:
        from .experiments.executor import check_dask_address

        if (why := check_dask_address(args.dask)) is not None:
            raise ModelError(f"--dask: {why}")
        if args.dask != "local" and args.workers is not None:
            raise ModelError("--workers sizes the local pool or --dask local; a scheduler's cluster has its own "
                             "workers")


def _run_sweeps(work: Callable[[], object]) -> int:
    """Run a sweep; an interrupted sweep exits 128 + signal number."""
    from .experiments.sweep import SweepInterrupted

    try:
        work()
    except SweepInterrupted as exc:
        return 128 + exc.signum
    return 0


def _names(text: str, flag: str) -> list[str]:
    """A comma-separated list of names, each once and none empty."""
    names = [n.strip() for n in text.split(",")]
    if "" in names:
        raise ModelError(f"{flag} {text!r} has an empty name; separate names by single commas")
    if twice := sorted({n for n in names if names.count(n) > 1}):
        raise ModelError(f"{flag}: {', '.join(twice)} given more than once; name each once")
    return names


def _cmd_compare(args: argparse.Namespace) -> int:
    from .experiments.compare import STRUCTURED, compare, markdown_table

    problems = _names(args.problems, "--problems") if args.problems else registry.names("textbook")
    methods = _names(args.methods, "--methods") if args.methods else sorted(METHODS)
    if unknown := sorted(set(methods) - set(METHODS) - {STRUCTURED}):
        raise ModelError(f"--methods {', '.join(unknown)}: unknown; choose from {', '.join(sorted(METHODS))} and "
                         f"{STRUCTURED} (an attack problem's own attack)")
    raw = _pairs(args.param, "--param")
    for name in problems:
        registry.spec(name)  # an unknown name or an undeclared builder fails here, before any work
    if unused := sorted(k for k in raw if not any(k in registry.spec(n).defaults for n in problems)):
        raise ModelError(f"--param {', '.join(unused)}: no selected problem has such a parameter")
    params: dict[str, object] = {}
    for name in problems:  # typed as the first problem that has the parameter declares it
        typed = _problem_params(name, {k: v for k, v in raw.items() if k in registry.spec(name).defaults})
        params = {**typed, **params}
    for name in problems:  # a user's builder is run once up front, so that a broken one fails before any work
        if ":" in name:
            registry.get(name, **registry.params_for(name, params))

    def work() -> None:
        rows = compare(problems, methods, os.path.join(args.out, "compare.csv"), starts=args.starts, seed=args.seed,
                       workers=args.workers, dask=args.dask, params=params)
        table = markdown_table(rows, params)
        with atomic_open(os.path.join(args.out, "compare.md")) as fh:
            fh.write(table)
        print(table)
        print(f"wrote {args.out}/compare.csv and {args.out}/compare.md")

    return _run_sweeps(work)


REPRODUCE_FLAGS = {"--quick": ("willems", "identification", "defenses", "certify", "robust-willems"),
                   "--selection": ("willems",), "--learners": ("defenses", "certify"), "--paper": ("identification",)}
"""The `reproduce` flags that only some targets take."""


def _cmd_reproduce(args: argparse.Namespace) -> int:
    given = {"--quick": args.quick, "--selection": args.selection is not None, "--learners": args.learners is not None,
             "--paper": args.paper is not None}
    unused = [flag for flag, takers in REPRODUCE_FLAGS.items() if given[flag] and args.target not in takers]
    if unused:
        flag = unused[0]
        takers = [f"`reproduce {t}`" for t in REPRODUCE_FLAGS[flag]]
        raise ModelError(f"{flag}: only " + " and ".join([", ".join(takers[:-1]), takers[-1]] if len(takers) > 1
                                                         else takers)
                         + f" take{'s' if len(REPRODUCE_FLAGS[flag]) == 1 else ''} it, not `reproduce {args.target}`"
                         + (" (which runs the selections min-norm, clarabel and scs)" if args.target == "willems-budget"
                            else ""))
    if args.paper is not None:
        if args.quick:
            raise ModelError("--paper runs the authors' own grid (T = 100 and 500, 10 data sets, 5 deltas); "
                             "drop --quick")
        from .experiments.identification_paper import run_paper

        paper_out = args.out or "out/identification-paper"
        _check_out(paper_out, "identification-paper", args.force)
        return _run_sweeps(lambda: run_paper(args.paper, paper_out, args.workers, dask=args.dask))
    out = args.out or f"out/{args.target}"
    _check_out(out, args.target, args.force)
    if args.target == "vrft":
        from .experiments.vrft import run_reproduction

        return _run_sweeps(lambda: run_reproduction(args.sims, out, args.seed, args.workers, dask=args.dask))
    if args.target == "identification":
        from .experiments.identification import run_reproduction as run_identification

        return _run_sweeps(lambda: run_identification(args.sims, out, args.quick, args.seed, args.workers,
                                                      dask=args.dask))
    if args.target == "defenses":
        from .experiments.defenses import run_defenses

        learners = None if args.learners is None else args.learners.split(",")
        return _run_sweeps(lambda: run_defenses(args.sims, out, args.quick, args.seed, args.workers, args.dask,
                                                learners=learners))
    if args.target == "certify":
        from .experiments.certify import run_certify

        families = None if args.learners is None else args.learners.split(",")
        return _run_sweeps(lambda: run_certify(args.sims, out, args.quick, args.seed, args.workers, args.dask,
                                               families))
    if args.target == "robust-willems":
        from .experiments.robust_willems import run_robust_willems

        return _run_sweeps(lambda: run_robust_willems(args.sims, out, args.quick, args.seed, args.workers, args.dask))
    if args.target == "willems-budget":
        from .experiments.willems_budget import run_budget

        return _run_sweeps(lambda: run_budget(args.sims, out, args.seed, args.workers, args.dask))
    from .experiments.willems import run_reproduction as run_willems

    return _run_sweeps(lambda: run_willems(args.sims, out, args.quick, args.seed,
                                           selection=args.selection or "min-norm", workers=args.workers,
                                           dask=args.dask))


USER_CODE = ("MODULE:FUNCTION runs your code: MODULE is imported (its top-level code runs), then FUNCTION is called "
             "only if decorated with @bilevel.problem_builder. MODULE is path/to/file.py (loaded from that file) or a "
             "dotted name (imported normally; the working directory is searched after the installed packages, so a "
             "file there never shadows one).")


def _version() -> str:
    """The installed package's version (package metadata)."""
    try:
        return metadata.version("bilevel")
    except metadata.PackageNotFoundError:
        return "(not installed: no package metadata)"


def build_parser() -> argparse.ArgumentParser:
    """The `bilevel` argument parser."""
    parser = argparse.ArgumentParser(prog="bilevel", description="Bilevel optimization with certified answers.",
                                     epilog=USER_CODE)
    parser.add_argument("--version", action="version", version=f"bilevel {_version()}")
    sub = parser.add_subparsers(dest="command", required=True)
    p_list = sub.add_parser("list", help="list registered problems")
    p_list.add_argument("--tag", default=None, help="only problems with this tag")
    p_list.add_argument("--params", default=None, metavar="NAME",
                        help="list problem NAME's parameters (--param NAME=VALUE), their types and defaults")
    p_list.set_defaults(run=_cmd_list)
    p_solve = sub.add_parser("solve", help="solve a registered problem and print its certificate", epilog=USER_CODE)
    p_solve.add_argument("problem", help="a registered name (bilevel list) or MODULE:FUNCTION, your own builder")
    p_solve.add_argument("--method", default=None,
                         help=f"{', '.join([AUTO, STRUCTURED, *sorted(METHODS)])} (default: {STRUCTURED} for a problem "
                              f"with a structured attack (vrft-*, willems-*), else {AUTO}: chosen by structure)")
    p_solve.add_argument("--verbose", action="store_true",
                         help="progress on stderr while the method works (a line per start, iteration or generation)")
    p_solve.add_argument("--starts", type=int, default=None,
                         help="multistart count (default: the method's registry default, bilevel.defaults, e.g. "
                              "reduced 1, hypergradient 4, ipopt 8; a structured attack: its own)")
    p_solve.add_argument("--seed", type=int, default=None, help="the method's random seed (default 0; a problem's "
                         "data seed is --param seed=S where it has one; a structured attack's seed is its data's too)")
    p_solve.add_argument("--param", action="append", default=[], metavar="NAME=VALUE",
                         help="problem parameter (bilevel list --params NAME lists them)")
    p_solve.add_argument("--option", action="append", default=[], metavar="NAME=VALUE",
                         help="method option, or the structured attack's (bilevel list --params NAME lists them); an "
                              f"option given several ways: {OPTION_RULE}")
    p_solve.add_argument("--json", default=None, metavar="PATH", help="write the result as JSON")
    p_solve.set_defaults(run=_cmd_solve)
    p_cmp = sub.add_parser("compare", help="run solvers on problems; write CSV and Markdown (resumable)",
                           epilog=USER_CODE)
    p_cmp.add_argument("--problems", default="", help="comma-separated registered names or MODULE:FUNCTION "
                       "builders of your own (default: all textbook problems)")
    p_cmp.add_argument("--methods", default="",
                       help="comma-separated methods (default: all registered); structured: an attack problem's own "
                            "attack")
    p_cmp.add_argument("--starts", type=int, default=8,
                       help="the one multistart count every compared method runs (default 8: methods compared at "
                            "equal starts, not at their registry defaults)")
    p_cmp.add_argument("--param", action="append", default=[], metavar="NAME=VALUE",
                       help="problem parameter, for every selected problem that has it (e.g. N=512)")
    p_cmp.add_argument("--seed", type=int, default=0)
    p_cmp.add_argument("--out", default="out/compare", help="output directory")
    p_cmp.add_argument("--workers", type=int, default=None, help="local processes (default: all cores)")
    p_cmp.add_argument("--dask", default=None, metavar="ADDRESS",
                       help="run on a Dask cluster: tcp://HOST:PORT of its scheduler, or 'local' (docs/clusters.md)")
    p_cmp.set_defaults(run=_cmd_compare)
    p_rep = sub.add_parser("reproduce", help="reproduce the paper's tables and figures (resumable)")
    p_rep.add_argument("target", choices=["vrft", "willems", "willems-budget", "identification", "defenses", "certify",
                                          "robust-willems"],
                       help="willems-budget: delta_u*, the smallest destabilizing input budget, per data set; "
                            "identification: stealthy poisoning of state-space least squares; defenses: the defended "
                            "learners' clean cost against delta* (docs/defenses.md); certify: the certified bracket "
                            "[delta_lb, delta_ub] per learner and data set (docs/certify.md); robust-willems: the "
                            "robust De Persis-Tesi learner under adaptive attack (docs/defenses.md)")
    p_rep.add_argument("--sims", type=int, default=32, help="simulations per cell (the paper: 512 vrft, 256 willems; "
                       "identification: 100)")
    p_rep.add_argument("--out", default=None, help="output directory (default out/<target>); one holding another "
                       "target's run is refused")
    p_rep.add_argument("--force", action="store_true",
                       help="write into an --out holding another target's run (its report.md is overwritten)")
    p_rep.add_argument("--seed", type=int, default=0)
    p_rep.add_argument("--workers", type=int, default=None, help="local processes (default: all cores)")
    p_rep.add_argument("--dask", default=None, metavar="ADDRESS",
                       help="run on a Dask cluster: tcp://HOST:PORT of its scheduler, or 'local' (docs/clusters.md)")
    p_rep.add_argument("--quick", action="store_true", help="willems: the small CI-sized grid (4 sims, 3 budgets); "
                       "identification: T = 100, delta 0.01 and 0.05, 2 sims; defenses: 8 sims, VRFT N = 128, "
                       "De Persis-Tesi T = 15, identification T = 25, DeePC T = 60; certify: 2 sims, VRFT N = 64, "
                       "De Persis-Tesi T = 15, DeePC T = 60, 200 samples; robust-willems: 2 sims, design 0.1 attacked "
                       "at its full budget")
    p_rep.add_argument("--selection", choices=WILLEMS_SELECTIONS, default=None,
                       help="willems: the learner's choice among its optimal Q (tikhonov: the session-1 sweep's; "
                            "clarabel, scs: the solver's own Q, input poisoning only; default min-norm)")
    p_rep.add_argument("--paper", default=None, metavar="DIR",
                       help="identification: Russo & Proutiere's own data sets (their data_{T}timesteps_{i}.pkl files "
                            "in DIR; docs/identification.md says how to get them) on their stealth constraints, with "
                            "their published medians beside")
    p_rep.add_argument("--learners", default=None, metavar="LIST",
                       help="defenses: a comma-separated subset of vrft,willems,ident,deepc to run; certify: a "
                            "subset of its families (vrft, ident, dpt-reactor-min-norm, dpt-reactor-clarabel, "
                            "dpt-n2-min-norm, dpt-n2-clarabel, deepc); default all")
    p_rep.set_defaults(run=_cmd_reproduce)
    return parser


TARGET_FILES = {"vrft": "maxmin-paper.jsonl", "willems": "paper.jsonl", "willems-budget": "budget.jsonl",
                "identification": "stealthy.jsonl", "defenses": "defenses.jsonl", "certify": "certify.jsonl",
                "robust-willems": "robust.jsonl", "identification-paper": "authors_terms.jsonl"}
"""The sweep file only `bilevel reproduce TARGET` writes: a directory holding another target's is that target's run."""


def _check_out(out: str, target: str, force: bool) -> None:
    """Refuse an --out directory holding another target's run (its report.md would be overwritten) unless --force."""
    if force:
        return
    for other, name in TARGET_FILES.items():
        if other != target and os.path.exists(os.path.join(out, name)):
            raise ModelError(f"--out {out!r} holds a `reproduce {other}` run ({name}), whose report.md `reproduce "
                             f"{target}` would overwrite; give another --out (default out/{target}) or add --force")


def _probe_directory(flag: str, path: str, directory: str) -> None:
    """Create and delete a file in `directory`, so an unwritable output path fails before any work."""
    try:
        with tempfile.NamedTemporaryFile(dir=directory, prefix=".bilevel-probe-"):
            pass
    except OSError as exc:
        raise ModelError(f"--{flag} {path!r}: cannot write in {directory!r} ({exc.strerror}); give a writable "
                         "path") from exc


def _check_paths(args: argparse.Namespace) -> None:
    """Output paths are checked (and probed for writing) before any work, so a long run never ends in a traceback."""
    for flag in ("json",):
        path = getattr(args, flag, None)
        if path:
            parent = os.path.dirname(os.path.abspath(path))
            if os.path.isdir(path):
                raise ModelError(f"--{flag} {path!r} is a directory; give a file name inside it")
            if os.path.exists(path) and not os.path.isfile(path):
                raise ModelError(f"--{flag} {path!r} is not a regular file (a device, pipe or socket): results are "
                                 "written whole to a file beside it and renamed over it; give a file path")
            if not os.path.isdir(parent):
                raise ModelError(f"--{flag} {path!r}: directory {parent!r} does not exist; create it first")
            _probe_directory(flag, path, parent)
    out = getattr(args, "out", None)
    if out:
        if os.path.exists(out) and not os.path.isdir(out):
            raise ModelError(f"--out {out!r} is a file, not a directory; give a directory (it is created if missing)")
        existing = os.path.abspath(out)
        while not os.path.exists(existing):
            existing = os.path.dirname(existing)
        if not os.path.isdir(existing):
            raise ModelError(f"--out {out!r}: {existing!r} is a file, not a directory; give a directory")
        _probe_directory("out", out, existing)


USAGE_ERRORS = (ModelError, InvalidData, UnknownName, UnknownOption)
"""Named errors that are the caller's input (exit 2, as argparse); every other named error is a failure (exit 1)."""


def _error_line(exc: BaseException) -> str:
    """One line describing a named error (an OSError names its path, a MemoryError the flags that size a run)."""
    if isinstance(exc, MemoryError):
        return "out of memory; give smaller sizes (--sims, --starts, --param sizes) or fewer --workers"
    if isinstance(exc, OSError) and exc.filename:
        return f"{exc.strerror}: {exc.filename!r}; check the path"
    return " ".join(str(exc).split()) or type(exc).__name__


def main(argv: Sequence[str] | None = None) -> int:
    """Entry point of the `bilevel` console script. Every flag is validated before any work; a named error (bad
    input, unknown names, unusable paths: exit 2; a failed run, OSError, MemoryError: exit 1) prints one line
    `bilevel COMMAND: error: ...` to stderr, as argparse does, never a traceback."""
    parser = build_parser()
    args = parser.parse_args(argv)
    try:
        _check_numbers(args)
        _check_paths(args)
        return int(args.run(args))
    except BrokenPipeError:  # the reader left (`bilevel list | head`): stop quietly, and let exit flush nothing
        with contextlib.suppress(OSError, ValueError):
            os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())
        return 1
    except (BilevelError, OSError, MemoryError) as exc:
        print(f"bilevel {args.command}: error: {_error_line(exc)}", file=sys.stderr)
        return 2 if isinstance(exc, USAGE_ERRORS) else 1


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
