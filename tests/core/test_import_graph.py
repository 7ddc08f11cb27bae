"""Dependencies flow downwards only (DESIGN.md, "Layout"): no module of bilevel imports one of a higher layer.

The import graph is read from the package's files with ast (every import statement, also those inside functions,
except annotations-only imports under `if TYPE_CHECKING:`), so an import that is deferred to break a cycle is found
too. The layers are DESIGN.md's chain cli -> experiments -> attacks -> problems -> solvers -> reduction/mpcc -> lower
-> model, with the modules it does not name placed where their imports put them.
"""

from __future__ import annotations

import ast
from pathlib import Path

import bilevel

PACKAGE = Path(bilevel.__file__).parent

LAYERS = (
    ("cli", "__main__"),
    ("experiments",),
    ("robust",),  # certified robustness: certificates over the attacks and learners, used by experiments
    ("attacks",),
    ("problems",),
    ("ddc",),  # the control substrate: plants, learners, closed-loop analysis; built on the lower-level kinds
    ("solvers",),
    ("result",),  # the result type holds a certificate
    ("canonical", "certificate", "reduction", "mpcc"),
    ("frontends",),  # other ways to declare a lower level, built into lower-level kinds
    ("lower",),
    ("model",),
    ("linear_maps", "toeplitz", "parameters", "spectral_radius", "sampling", "vech", "threads", "files", "defaults", "kept",
     "real_data", "errors", "sparse_jacobian", "numeric_node"),
)
"""Top to bottom; a module of bilevel/NAME.py or bilevel/NAME/ is in the layer that lists NAME."""

DEFERRED = {
    ("model", "solvers.registry"): "BilevelProblem.solve calls the solvers' dispatcher",
    ("model", "frontends.cvxpy_lower"): "BilevelProblem.lower_cvxpy declares the lower level through the front end",
    ("model", "lower.matrix"): "BilevelProblem.lower_qp checks its matrices with the matrix kind's reader",
    ("linear_maps", "model"): "LinearMap @ expr reads the expression with the model's reader",
}
"""The upward imports the declaration API makes on purpose, inside a function: (importing unit, imported module)."""


def _layer(unit: str) -> int:
    for i, names in enumerate(LAYERS):
        if unit in names:
            return i
    raise AssertionError(f"bilevel.{unit} is in no layer of LAYERS; place it there (DESIGN.md's layout)")


def _imports(path: Path) -> list[tuple[int, str]]:
    """(line, module after 'bilevel.') of every import of a bilevel module that can run ('from M import a': M)."""
    package = path.relative_to(PACKAGE.parent).parts[:-1]  # a module's package, or an __init__'s own
    found: list[tuple[int, str]] = []

    def visit(node: ast.AST) -> None:
        if isinstance(node, ast.If) and "TYPE_CHECKING" in ast.unparse(node.test):
            for child in node.orelse:
                visit(child)
            return
        if isinstance(node, ast.ImportFrom):
            base = list(package[: len(package) - node.level + 1]) if node.level else []
            target = ".".join(base + ([node.module] if node.module else []))
            names = [target] if node.module else [f"{target}.{alias.name}" for alias in node.names]
            found.extend((node.lineno, name) for name in names)
        elif isinstance(node, ast.Import):
            found.extend((node.lineno, alias.name) for alias in node.names)
        for child in ast.iter_child_nodes(node):
            visit(child)

    visit(ast.parse(path.read_text(encoding="utf-8")))
    return [(line, name.split(".", 1)[1]) for line, name in found if name.startswith("bilevel.")]


def upward_imports() -> list[str]:
    """'file:line imports bilevel.X (layer above)' for every import from a lower layer to a higher one."""
    bad = []
    for path in sorted(PACKAGE.rglob("*.py")):
        parts = path.relative_to(PACKAGE).with_suffix("").parts
        if parts == ("__init__",):  # the package's facade re-exports every layer
            continue
        unit = parts[0]
        for line, target in _imports(path):
            other = target.split(".")[0]
            if _layer(other) < _layer(unit) and (unit, target) not in DEFERRED:
                bad.append(f"{path.relative_to(PACKAGE.parent)}:{line} imports bilevel.{target} ({other} is above "
                           f"{unit})")
    return bad


def test_no_module_imports_a_higher_layer() -> None:
    assert upward_imports() == []


def test_the_check_sees_deferred_and_relative_imports(tmp_path, monkeypatch) -> None:
    """A problems module that imports attacks inside a function (the cycle-breaking kind) is reported."""
    fake = tmp_path / "bilevel"
    (fake / "problems").mkdir(parents=True)
    (fake / "__init__.py").write_text("")
    (fake / "problems" / "__init__.py").write_text("")
    (fake / "problems" / "x.py").write_text("def f():\n    from ..attacks.vrft import state\n    return state\n")
    monkeypatch.setattr(__import__(__name__, fromlist=["PACKAGE"]), "PACKAGE", fake)
    assert upward_imports() == ["bilevel/problems/x.py:2 imports bilevel.attacks.vrft (attacks is above problems)"]
