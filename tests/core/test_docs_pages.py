"""README.md, docs/tutorial.md and docs/ddc.md run as printed: each print line prints its `# expected` text."""

import numpy as np

import bilevel as bl
from tests.docs_pages import run_page


def test_readme_first_problem_runs_as_printed() -> None:
    namespace = run_page("README.md")
    assert namespace["res"].status is bl.Status.SOLVED


def test_tutorial_runs_as_printed() -> None:
    namespace = run_page("tutorial.md")
    res = namespace["res"]  # section 2's `print(res)` is shown, not compared: its numbers are checked here
    assert res.status is bl.Status.SOLVED and res.certificate.passed and res.method == "ipopt"
    assert abs(res.upper_objective - -12.0) < 1e-6 and abs(res.lower_objective - 4.0) < 1e-6
    np.testing.assert_allclose([res.x["x"][0], res.y["y"][0]], [4.0, 4.0], atol=1e-6)


def test_ddc_example_runs_as_printed() -> None:
    namespace = run_page("ddc.md")
    reference = [0.3343, -0.6132, 0.7285, -0.6628, 0.4827, -0.1252]  # Campi et al. 2002, the N -> infinity fit
    np.testing.assert_allclose(namespace["fit"].theta, reference, atol=5e-3)
