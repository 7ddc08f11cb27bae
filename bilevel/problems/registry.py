"""Registry of named bilevel problems: builder, parameters, known optimum and its source."""

from __future__ import annotations

import importlib
import inspect
from dataclasses import dataclass, field
from typing import Any, Callable

from ..errors import ModelError, UnknownName
from ..model import BilevelProblem
from ..result import BilevelResult


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
    attack: Callable[..., BilevelResult] | None = None
    """The problem's structured attack, attack(starts=, seed=, **params) -> BilevelResult (`bilevel compare`'s
    method "structured"), for the attack problems that have one."""


_REGISTRY: dict[str, ProblemSpec] = {}


def register(name: str, *, source: str, optimum: float | None = None, solution: dict[str, Any] | None = None,
             lower_optimum: float | None = None, tags: tuple[str, ...] = (), description: str = "",
             defaults: dict[str, Any] | None = None, attack: Callable[..., BilevelResult] | None = None
             ) -> Callable[[Callable[..., BilevelProblem]], Callable[..., BilevelProblem]]:
    """Decorator registering a problem builder under `name` with its known optimum and source."""

    def decorate(build: Callable[..., BilevelProblem]) -> Callable[..., BilevelProblem]:
        if name in _REGISTRY:
            raise ModelError(f"a problem named {name!r} is already registered")
        doc = (build.__doc__ or "").strip().splitlines()
        _REGISTRY[name] = ProblemSpec(name, build, source, optimum, solution, lower_optimum, tuple(tags),
                                      description or (doc[0] if doc else ""), dict(defaults or {}), attack)
        return build

    return decorate


def _load_builtin() -> None:
    from . import literature, vrft, willems  # noqa: F401  (registers on import)


def _register_reference(ref: str) -> None:
    """Register the builder `module:function` under the name `ref` (its keyword defaults become parameters)."""
    module_name, _, attr = ref.partition(":")
    try:
        module = importlib.import_module(module_name)
    except ImportError as exc:
        raise UnknownName(f"problem {ref!r}: cannot import module {module_name!r} ({exc}); make it importable "
                          "(install it, or run from its directory or with PYTHONPATH)") from exc
    build = getattr(module, attr, None)
    if not callable(build):
        raise UnknownName(f"problem {ref!r}: module {module_name!r} has no function {attr!r}; give "
                          "module:function with a function returning a BilevelProblem")
    defaults = {k: p.default for k, p in inspect.signature(build).parameters.items()
                if p.default is not inspect.Parameter.empty}
    register(ref, source=ref, tags=("user",), defaults=defaults)(build)


def spec(name: str) -> ProblemSpec:
    """The spec of `name`: a registered problem, or `module:function` building one (registered on first use);
    raises UnknownName (a KeyError) listing the known names otherwise."""
    _load_builtin()
    if not isinstance(name, str):
        raise UnknownName(f"a problem name is a string, got {type(name).__name__} {name!r}; `bilevel list` shows the "
                          "known ones")
    if name not in _REGISTRY and ":" in name:
        _register_reference(name)
    if name not in _REGISTRY:
        raise UnknownName(f"no registered problem {name!r}; `bilevel list` shows the known ones: "
                          f"{', '.join(sorted(_REGISTRY))}")
    return _REGISTRY[name]


def get(name: str, **params: Any) -> BilevelProblem:
    """Build the registered problem `name` with its default parameters overridden by `params`."""
    s = spec(name)
    try:
        problem = s.build(**{**s.defaults, **params})
    except TypeError as exc:  # an unknown or mistyped parameter
        raise ModelError(f"problem {name!r} rejected its parameters ({exc}); "
                         f"its defaults are {s.defaults}") from exc
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
