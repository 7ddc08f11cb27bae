"""Kinds answer for themselves (DESIGN.md, "lower/"): outside bilevel/lower/ no code switches on a lower level's kind
name or unwraps the linear-map kind (ImageLower); it asks the kind (closed_form, nonlinear, affine_kkt, dual_bounded,
nonunique_at, inner_kind, lift_point, pullback, linear_map_arguments, rows_solver, moving_hessian).

Read with ast from the package's files: a comparison (==, !=, in, not in) that mentions a name or attribute called
`kind` and a lower-level kind's name, or an isinstance test or attribute access (`.inner`, `.lift`, `.solve_rows`)
that needs ImageLower's internals.
"""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

import bilevel
from bilevel.lower.base import LowerLevel

PACKAGE = Path(bilevel.__file__).parent

KIND_NAMES = frozenset({"nlp", "lp", "qp", "sdp", "least-squares"})
"""The kind names of bilevel/lower/ (LowerLevel.kind)."""

IMAGE_INTERNALS = frozenset({"inner", "lift", "solve_rows"})
"""ImageLower's attributes that code outside lower/ reaches through inner_kind, lift_point/pullback, rows_solver."""

CONSTRUCTS = {"canonical.py"}
"""Modules that build an ImageLower (they name the class to construct it, never to test for it)."""


def _strings(node: ast.AST) -> set[str]:
    return {n.value for n in ast.walk(node) if isinstance(n, ast.Constant) and isinstance(n.value, str)}


def _mentions_kind(node: ast.AST) -> bool:
    return any((isinstance(n, ast.Name) and n.id.endswith("kind"))
               or (isinstance(n, ast.Attribute) and n.attr == "kind") for n in ast.walk(node))


def violations(source: str, where: str, constructs: bool = False) -> list[str]:
    """Each switch on a lower-level kind name or unwrap of ImageLower in `source`, as 'where:line: what'."""
    found = []
    for node in ast.walk(ast.parse(source)):
        if isinstance(node, ast.Compare) and _mentions_kind(node) and (_strings(node) & KIND_NAMES):
            found.append(f"{where}:{node.lineno}: a switch on the kind name {sorted(_strings(node) & KIND_NAMES)}")
        elif (isinstance(node, ast.Call) and isinstance(node.func, ast.Name) and node.func.id == "isinstance"
              and any(isinstance(n, ast.Name) and n.id == "ImageLower" for n in ast.walk(node))):
            found.append(f"{where}:{node.lineno}: isinstance(..., ImageLower)")
        elif (isinstance(node, ast.Attribute) and node.attr in IMAGE_INTERNALS and not constructs
              and (getattr(node.value, "id", None) in ("low", "lower")
                   or getattr(node.value, "attr", None) == "lower")):
            found.append(f"{where}:{node.lineno}: ImageLower's .{node.attr} reached from a lower level")
    return found


def test_no_kind_switch_outside_lower():
    """No module of bilevel outside lower/ switches on a kind name or unwraps ImageLower."""
    found = []
    for path in sorted(PACKAGE.rglob("*.py")):
        rel = path.relative_to(PACKAGE)
        if rel.parts[0] == "lower":
            continue
        found += violations(path.read_text(encoding="utf-8"), str(rel), str(rel) in CONSTRUCTS)
    assert not found, "ask the lower level (a property or method in bilevel/lower/) instead:\n" + "\n".join(found)


@pytest.mark.parametrize("planted", [
    'if low.kind == "least-squares":\n    pass',
    'ok = prep.canon.lower.kind in ("lp", "qp")',
    'nlp = kind != "nlp"',
    'inner = low.inner if isinstance(low, ImageLower) else low',
    'lift = low.lift',
    'f = prep.canon.lower.solve_rows',
])
def test_planted_switch_is_found(planted: str):
    """The check fails on each planted switch or unwrap."""
    assert violations(planted, "planted.py")


def test_other_kinds_pass():
    """Kinds of other things (constraint senses, cone blocks, parameter kinds) are not lower-level kinds."""
    assert not violations('if c.kind == "<=":\n    pass\nz = blk.kind in ("zero", "nonneg")', "other.py")


def test_kind_names_are_the_kinds():
    """KIND_NAMES lists every kind a lower-level class of bilevel.lower declares."""
    import bilevel.lower.least_squares, bilevel.lower.matrix, bilevel.lower.nlp, bilevel.lower.residual  # noqa: F401
    import bilevel.lower.sdp  # noqa: F401

    def subclasses(cls):
        for sub in cls.__subclasses__():
            yield sub
            yield from subclasses(sub)

    declared = {sub.__dict__["kind"] for sub in subclasses(LowerLevel) if isinstance(sub.__dict__.get("kind"), str)}
    assert declared <= KIND_NAMES and {"lp", "qp", "least-squares"} <= declared
