"""Dependencies flow downwards only (DESIGN.md, "Layout"): no module of bilevel imports one of a higher layer.

The import graph is read from the package's files with ast (every import statement, also those inside functions,
except annotations-only imports under `if TYPE_CHECKING:`), so an import that is deferred to break a cycle is found
too. The layers are DESIGN.md's chain cli -> experiments -> attacks -> problems -> solvers -> reduction/mpcc -> lower
-> model, with the modules it does not name placed where their imports put them. Inside solvers/, the registered
methods and the dispatcher sit above method "global" (globalopt/), which sits above the verdict (verdict/: finalize,
the local probe, the optimistic selection), which sits above the engine (engine/: what every method shares): the
engine never imports a method, the verdict, the registry or globalopt.
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
    ("solvers",),  # the registered methods and the dispatcher (registry)
    ("solvers.globalopt",),  # method "global" and its parts
    ("solvers.verdict",),  # how a run becomes a result: finalize, the local probe, the optimistic selection
    ("solvers.engine",),  # what every method shares: Prepared and MethodRun, implicit derivatives, ascent, starts, ...
    ("result",),  # the result type holds a certificate
    ("canonical", "certificate", "reduction", "mpcc"),
    ("frontends",),  # other ways to declare a lower level, built into lower-level kinds
    ("lower",),
    ("model",),
    ("linear_maps", "toeplitz", "parameters", "spectral_radius", "sampling", "vech", "threads", "files", "defaults", "kept",
     "real_data", "errors", "sparse_jacobian", "numeric_node"),
)
"""Top to bottom; a module of bilevel/NAME.py or bilevel/NAME/ is in the layer that lists NAME, one of
bilevel/NAME/SUB/ in the layer that lists NAME.SUB where one does (the longest listed prefix)."""

DEFERRED = {
    ("model", "solvers.registry"): "BilevelProblem.solve calls the solvers' dispatcher",
    ("model", "frontends.cvxpy_lower"): "BilevelProblem.lower_cvxpy declares the lower level through the front end",
    ("model", "lower.matrix"): "BilevelProblem.lower_qp checks its matrices with the matrix kind's reader",
    ("linear_maps", "model"): "LinearMap @ expr reads the expression with the model's reader",
}
"""The upward imports the declaration API makes on purpose, inside a function: (importing unit, imported module)."""


def _unit(module: str) -> str:
    """The longest prefix of a dotted module name (after 'bilevel.') that LAYERS lists."""
    parts = module.split(".")
    for k in range(len(parts), 0, -1):
        if any(".".join(parts[:k]) in names for names in LAYERS):
            return ".".join(parts[:k])
    raise AssertionError(f"bilevel.{module} is in no layer of LAYERS; place it there (DESIGN.md's layout)")


def _layer(unit: str) -> int:
    return next(i for i, names in enumerate(LAYERS) if unit in names)


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
        unit = _unit(".".join(parts[:-1] if parts[-1] == "__init__" else parts))
        for line, target in _imports(path):
            other = _unit(target)
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


def _plant(tmp_path, monkeypatch, files: dict[str, str]) -> list[str]:
    """upward_imports() of a fake bilevel package holding `files` (path under bilevel/ -> source)."""
    fake = tmp_path / "bilevel"
    for name, text in {"__init__.py": "", **files}.items():
        path = fake / name
        path.parent.mkdir(parents=True, exist_ok=True)
        for folder in path.relative_to(fake).parents:
            (fake / folder / "__init__.py").touch()
        path.write_text(text)
    monkeypatch.setattr(__import__(__name__, fromlist=["PACKAGE"]), "PACKAGE", fake)
    return upward_imports()


def test_the_engine_imports_no_method_verdict_registry_or_globalopt(tmp_path, monkeypatch) -> None:
    """An engine module that imports a method, the registry, the verdict (deferred, in a function) or globalopt is
    reported; the verdict importing the engine, and a method importing both, are not."""
    found = _plant(tmp_path, monkeypatch, {
        "solvers/engine/x.py": ("from ..ipopt import solve_ipopt\nfrom ..registry import solve\n"
                                "from ..globalopt.form import linear_mpcc\n"
                                "def f():\n    from ..verdict.finalize import finalize\n    return finalize\n"),
        "solvers/verdict/y.py": "from ..engine.x import f\n",
        "solvers/z.py": "from .engine.x import f\nfrom .verdict.y import f\nfrom .globalopt.form import g\n",
        "solvers/globalopt/form.py": "from ..engine import x\n",
    })
    assert found == [
        "bilevel/solvers/engine/x.py:1 imports bilevel.solvers.ipopt (solvers is above solvers.engine)",
        "bilevel/solvers/engine/x.py:2 imports bilevel.solvers.registry (solvers is above solvers.engine)",
        "bilevel/solvers/engine/x.py:3 imports bilevel.solvers.globalopt.form (solvers.globalopt is above "
        "solvers.engine)",
        "bilevel/solvers/engine/x.py:5 imports bilevel.solvers.verdict.finalize (solvers.verdict is above "
        "solvers.engine)",
    ]


def test_the_verdict_imports_no_method(tmp_path, monkeypatch) -> None:
    """A verdict module that imports the hypergradient method is reported."""
    found = _plant(tmp_path, monkeypatch, {"solvers/verdict/probe.py": "from ..hypergradient import descend\n"})
    assert found == ["bilevel/solvers/verdict/probe.py:1 imports bilevel.solvers.hypergradient (solvers is above "
                     "solvers.verdict)"]
