"""Registry of named bilevel problems: builder, parameters, known optimum and its source."""

from __future__ import annotations

import importlib
import importlib.util
import inspect
import os
import sys
from dataclasses import dataclass, field
from types import ModuleType
from typing import Any, Callable

from ..errors import BilevelError, ModelError, UnknownName, did_you_mean
from ..model import BilevelProblem


@dataclass(frozen=True)
class ProblemSpec:
    """A registered instance: how to build it and what is known about it (optimum, solution, source)."""

    name: str
    build: Callable[..., BilevelProblem]
    source: str
    optimum: float | None = None
    solution: dict[str, Any] | None = None
    lower_optimum: float | None = None
    tags: tuple[str, ...] = ()
    description: str = ""
    defaults: dict[str, Any] = field(default_factory=dict)


_REGISTRY: dict[str, ProblemSpec] = {}


def register(name: str, *, source: str, optimum: float | None = None, solution: dict[str, Any] | None = None,
             lower_optimum: float | None = None, tags: tuple[str, ...] = (), description: str = "",
             defaults: dict[str, Any] | None = None
             ) -> Callable[[Callable[..., BilevelProblem]], Callable[..., BilevelProblem]]:
    """Decorator registering a problem builder under `name` with its known optimum and source."""

    def decorate(build: Callable[..., BilevelProblem]) -> Callable[..., BilevelProblem]:
        if name in _REGISTRY:
            raise ModelError(f"a problem named {name!r} is already registered")
        summary = " ".join((build.__doc__ or "").strip().split("\n\n")[0].split())  # the docstring's first paragraph
        _REGISTRY[name] = ProblemSpec(name, build, source, optimum, solution, lower_optimum, tuple(tags),
                                      description or summary, dict(defaults or {}))
        return build

    return decorate


def _load_builtin() -> None:
    from . import defended_deepc, defended_identification, defended_vrft, defended_willems  # noqa: F401  (registers)
    from . import deepc, identification, literature, vrft, willems  # noqa: F401


BUILDER_MARK = "__bilevel_problem_builder__"


def problem_builder(build: Callable[..., BilevelProblem]) -> Callable[..., BilevelProblem]:
    """Decorator declaring `build` a problem builder that `bilevel solve/compare MODULE:FUNCTION` may call (the CLI
    refuses any other callable); its keyword defaults and annotations type the `--param NAME=VALUE` values."""
    if not callable(build):
        raise ModelError(f"@problem_builder decorates a function returning a BilevelProblem, not {build!r}")
    setattr(build, BUILDER_MARK, True)
    return build


def _import_user_module(ref: str, module_ref: str) -> ModuleType:
    """MODULE of a `MODULE:FUNCTION` reference: a path ending in .py is loaded from that file (its directory is not
    put on sys.path); a dotted name is imported normally, the working directory searched last (appended to
    sys.path), so a file there never shadows an installed package. Importing runs the module's top-level code."""
    try:
        if module_ref.endswith(".py"):
            path = os.path.abspath(module_ref)
            if not os.path.isfile(path):
                raise UnknownName(f"problem {ref!r}: no file {module_ref!r}; give an existing path/to/file.py:FUNCTION")
            name = "bilevel_user_" + "".join(c if c.isalnum() else "_" for c in path)
            if name in sys.modules:
                return sys.modules[name]
            loader = importlib.util.spec_from_file_location(name, path)
            module = importlib.util.module_from_spec(loader)
            sys.modules[name] = module
            try:
                loader.loader.exec_module(module)
            except BaseException:
                del sys.modules[name]
                raise
            return module
        if os.getcwd() not in sys.path:
            sys.path.append(os.getcwd())
        return importlib.import_module(module_ref)
    except BilevelError:
        raise
    except ImportError as exc:
        raise UnknownName(f"problem {ref!r}: cannot import module {module_ref!r} ({exc}); install it, run from its "
                          "directory, or give its file as path/to/file.py:FUNCTION") from exc
    except Exception as exc:  # the user's module failed at import: its top-level code is not ours to trace
        raise ModelError(f"problem {ref!r}: importing {module_ref!r} raised {type(exc).__name__}: {exc}; fix the "
                         "module's top-level code") from exc


def _register_reference(ref: str) -> None:
    """Register the builder `module:function` under the name `ref` (its keyword defaults become parameters); only
    a function marked with @problem_builder is accepted, checked before it is ever called."""
    module_ref, _, attr = ref.rpartition(":")
    if not module_ref or not attr:
        raise UnknownName(f"problem {ref!r}: give MODULE:FUNCTION (a dotted module or path/to/file.py, a colon, "
                          "the builder's name)")
    module = _import_user_module(ref, module_ref)
    build = getattr(module, attr, None)
    if build is None or not callable(build):
        raise UnknownName(f"problem {ref!r}: module {module_ref!r} has no function {attr!r}; give "
                          "MODULE:FUNCTION with a function returning a BilevelProblem")
    if getattr(build, BUILDER_MARK, False) is not True:
        raise ModelError(f"problem {ref!r}: {attr!r} is not declared a problem builder and is not called; "
                         f"decorate {attr} with @bilevel.problem_builder")
    defaults = {k: p.default for k, p in inspect.signature(build).parameters.items()
                if p.default is not inspect.Parameter.empty}
    register(ref, source=ref, tags=("user",), defaults=defaults)(build)


def spec(name: str) -> ProblemSpec:
    """The spec of `name`: a registered problem, or `module:function` building one (registered on first use);
    raises UnknownName (a KeyError) naming the closest known names otherwise."""
    _load_builtin()
    if not isinstance(name, str):
        raise UnknownName(f"a problem name is a string, got {type(name).__name__} {name!r}; `bilevel list` shows the "
                          "known ones")
    if name not in _REGISTRY and ":" in name:
        _register_reference(name)
    if name not in _REGISTRY:
        raise UnknownName(f"no registered problem {name!r}; {did_you_mean(name, _REGISTRY)}`bilevel list` shows the "
                          "known ones")
    return _REGISTRY[name]


def get(name: str, **params: Any) -> BilevelProblem:
    """Build the registered problem `name` with its default parameters overridden by `params`."""
    s = spec(name)
    try:
        problem = s.build(**{**s.defaults, **params})
    except TypeError as exc:  # an unknown or mistyped parameter
        raise ModelError(f"problem {name!r} rejected its parameters ({exc}); "
                         f"its defaults are {s.defaults}") from exc
    except BilevelError:
        raise
    except Exception as exc:  # a user's builder failed: name it, do not pass its traceback on as ours
        if "user" not in s.tags:
            raise
        raise ModelError(f"problem {name!r}: its builder raised {type(exc).__name__}: {exc}; fix the builder") from exc
    if not isinstance(problem, BilevelProblem):
        raise ModelError(f"problem {name!r}: its builder returned {type(problem).__name__}, not a BilevelProblem")
    problem.name = name
    return problem


def params_for(name: str, params: dict[str, Any]) -> dict[str, Any]:
    """The entries of `params` that problem `name` has as parameters (shared --param values)."""
    return {k: v for k, v in params.items() if k in spec(name).defaults}


def names(tag: str | None = None) -> list[str]:
    """Sorted names of registered problems, optionally only those carrying `tag`."""
    _load_builtin()
    return sorted(n for n, s in _REGISTRY.items() if tag is None or tag in s.tags)
