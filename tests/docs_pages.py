"""Run a docs page's Python blocks and compare what they print with the `# expected` comments of its print lines."""

from __future__ import annotations

import contextlib
import io
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def _run(code: list[str], start: int, stop: int, page: Path, namespace: dict) -> list[str]:
    """Execute code lines [start, stop) (numbered as on the page) and return the lines they printed."""
    out = io.StringIO()
    with contextlib.redirect_stdout(out):
        exec(compile("\n" * start + "\n".join(code[start:stop]), str(page), "exec"), namespace)
    return out.getvalue().splitlines()


def run_page(name: str) -> dict:
    """Execute the ```python blocks of docs/<name> (README.md: the repository root's) in one namespace.

    Each line that starts with `print(` must print one line, the text after its `#`; a print line whose comment
    is `# ...` runs without comparison (for long output the page shows below). Nothing else may print."""
    page = ROOT / name if name == "README.md" else ROOT / "docs" / name
    code, inside = [], False
    for line in page.read_text().splitlines():  # non-code lines become blank, so line numbers are the page's
        inside = line.strip() == "```python" or (inside and line.strip() != "```")
        code.append(line if inside and line.strip() != "```python" else "")
    namespace: dict = {}
    start = 0
    for i in [i for i, line in enumerate(code) if line.startswith("print(")] + [len(code)]:
        printed = _run(code, start, i, page, namespace)
        assert not printed, f"{name} lines {start + 1}-{i} printed {printed}, which no print line promises"
        if i < len(code):
            assert "#" in code[i], f"{name} line {i + 1}: {code[i]!r} carries no '# expected' comment (or '# ...')"
            promised = code[i].split("#", 1)[1].strip()
            printed = _run(code, i, i + 1, page, namespace)
            wrong = promised != "..." and printed != [promised]
            assert not wrong, f"{name} line {i + 1} printed {printed}, the page promises [{promised}]"
            start = i + 1
    return namespace
