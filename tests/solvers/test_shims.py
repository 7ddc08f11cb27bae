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


def test_renames_state_their_removal_version() -> None:
    """Every rename shim names the release that removes it (RENAMES_REMOVED_IN): renamed options and attributes."""
    import bilevel as bl
    from bilevel.errors import RENAMES_REMOVED_IN, UnknownOption

    assert RENAMES_REMOVED_IN == "0.2.0"
    bp = bl.BilevelProblem("renames")
    x = bp.upper_variable("x", lb=0, ub=1)
    y = bp.lower_variable("y")
    bp.minimize_upper((x - y) ** 2)
    bp.minimize_lower((y - x) ** 2)
    with pytest.raises(AttributeError, match=f"goes in bilevel {RENAMES_REMOVED_IN}"):
        bp.starts
    with pytest.raises(UnknownOption, match=f"polish was renamed: use branch_polish; this note goes in bilevel {RENAMES_REMOVED_IN}"):
        bp.solve(method="ipopt", polish=True)
