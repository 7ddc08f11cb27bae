"""What a solve prints on the console: nothing from its backends unless asked (verbose=True), and results that
summarize long arrays."""

import numpy as np

import bilevel as bl
from bilevel.problems import registry


def test_global_method_prints_nothing_on_stdout(capfd) -> None:
    """HiGHS's banner is written by its C++ code on file descriptor 1: the node LPs are silenced before it can be."""
    res = registry.get("bard1998-ex5.1.1").solve(method="global")
    out, _ = capfd.readouterr()
    assert res.status is bl.Status.SOLVED and abs(res.upper_objective - -12.0) < 1e-6
    assert out == "", out
