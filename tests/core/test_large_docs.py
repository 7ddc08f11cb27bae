"""docs/large.md runs as printed: ridge label poisoning reaches its known optimum, the LP rhs attack is proven."""

from tests.docs_pages import run_page


def test_large_page_runs_as_printed():
    namespace = run_page("large.md")
    assert namespace["res"].certificate.passed
