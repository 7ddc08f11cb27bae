"""Run a docs page's Python blocks and compare what they print with the `# expected` comments of its print lines."""

from __future__ import annotations

import contextlib
import io
import re
from pathlib import Path

DOCS = Path(__file__).resolve().parents[1] / "docs"


def run_page(name: str) -> dict:
    """Execute docs/<name>'s ```python blocks in one namespace; assert each `print(...)  # text` printed text."""
    page = DOCS / name
    code = "\n".join(re.findall(r"```python\n(.*?)```", page.read_text(), flags=re.S))
    out = io.StringIO()
    namespace: dict = {}
    with contextlib.redirect_stdout(out):
        exec(compile(code, str(page), "exec"), namespace)
    promised = [line.split("#", 1)[1].strip() for line in code.splitlines() if line.startswith("print(")]
    printed = out.getvalue().splitlines()
    assert printed == promised, f"{name} printed {printed}, the page promises {promised}"
    return namespace
