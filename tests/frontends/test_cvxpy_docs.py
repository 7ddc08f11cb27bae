"""docs/cvxpy.md runs as shown: its python blocks are executed here, and its printed lines are checked."""

from __future__ import annotations

from tests.docs_pages import run_page


def test_cvxpy_page_runs_and_prints_what_it_says() -> None:
    namespace = run_page("cvxpy.md")
    assert namespace["res"].certificate.passed
