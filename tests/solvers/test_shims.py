"""The deprecated module bilevel.solvers.base (removed in bilevel 0.2.0) still gives user code its names, and warns."""

import importlib
import sys

import pytest


def test_old_base_module_warns_and_reexports() -> None:
    sys.modules.pop("bilevel.solvers.base", None)
    with pytest.warns(DeprecationWarning, match="removed in bilevel 0.2.0"):
        base = importlib.import_module("bilevel.solvers.base")
    from bilevel.solvers import MethodRun, Prepared, prepare
    from bilevel.solvers.verdict.finalize import finalize

    assert (base.MethodRun, base.Prepared, base.prepare, base.finalize) == (MethodRun, Prepared, prepare, finalize)
