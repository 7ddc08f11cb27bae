"""docs/cvxpy.md runs as shown: its python blocks are executed here, and its printed lines are checked."""

from __future__ import annotations

import contextlib
import io
import re
from pathlib import Path

PAGE = Path(__file__).resolve().parents[2] / "docs" / "cvxpy.md"


def test_cvxpy_page_runs_and_prints_what_it_says() -> None:
    code = "\n".join(re.findall(r"```python\n(.*?)```", PAGE.read_text(), flags=re.S))
    out = io.StringIO()
    namespace: dict = {}
    with contextlib.redirect_stdout(out):
        exec(compile(code, str(PAGE), "exec"), namespace)
    promised = [line.split("#", 1)[1].strip() for line in code.splitlines() if line.startswith("print(")]
    assert out.getvalue().splitlines() == promised
    assert namespace["res"].certificate.passed
