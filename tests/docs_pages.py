"""Run a docs page's Python blocks and compare what they print with the `# expected` comments of its print lines;
list every code block of a page (Python, shell commands, displayed text) for the tests that run or check them."""

from __future__ import annotations

import contextlib
import io
import re
import shlex
from dataclasses import dataclass
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
PAGES = ("README.md", *sorted(p.name for p in (ROOT / "docs").glob("*.md")))
"""Every page whose code blocks the tests run or check: the README and docs/*.md."""

KINDS = {"python": "python", "text": "text", "": "shell"}
"""A fenced block's language -> its kind (``` alone: shell commands); an indented block is shell. Text is a display
(a formula, a signature, a printed output), never run."""

SHELL_REASON = re.compile(r"<!--\s*shell:\s*(.*?)\s*-->")
"""`<!-- shell: REASON -->` on the line before a shell block: why its commands other than `bilevel ...` are not run."""


@dataclass(frozen=True)
class Block:
    """A code block of a page: its kind, its first line (numbered as on the page), its lines, and the reason given
    by a `<!-- shell: REASON -->` marker before it (None without one)."""

    page: str
    line: int
    kind: str
    lines: tuple[str, ...]
    reason: str | None

    def commands(self) -> list[list[str]]:
        """A shell block's commands as argument lists: `\\` continuations joined, `# comments` dropped, commands
        chained by &&, ; or & apart."""
        text = "\n".join(self.lines).replace("\\\n", " ")
        out: list[list[str]] = []
        for line in text.splitlines():
            command: list[str] = []
            for word in shlex.split(line, comments=True) + ["&&"]:
                if word in ("&&", ";", "&"):
                    out += [command] if command else []
                    command = []
                else:
                    command.append(word)
        return out


def page_path(name: str) -> Path:
    """The file of a page: README.md at the repository root, any other in docs/."""
    return ROOT / name if name == "README.md" else ROOT / "docs" / name


def code_blocks(name: str) -> list[Block]:
    """Every fenced block (```python, ```text or ``` for shell) and indented block (4 spaces after a blank line) of a
    page; a fence with another language fails, so that no block goes unclassified."""
    lines = page_path(name).read_text().splitlines()
    blocks, i = [], 0

    def reason(before: int) -> str | None:
        previous = [line for line in lines[:before] if line.strip()]
        match = SHELL_REASON.fullmatch(previous[-1].strip()) if previous else None
        return match.group(1) if match else None

    while i < len(lines):
        if lines[i].startswith("```"):
            language = lines[i][3:].strip()
            assert language in KINDS, f"{name} line {i + 1}: a ```{language} block; use ```python, ```text or ```"
            end = next(j for j in range(i + 1, len(lines)) if lines[j].startswith("```"))
            blocks.append(Block(name, i + 2, KINDS[language], tuple(lines[i + 1:end]), reason(i)))
            i = end + 1
        elif lines[i].startswith("    ") and lines[i].strip() and (i == 0 or not lines[i - 1].strip()):
            end = i
            while end < len(lines) and (lines[end].startswith("    ") or not lines[end].strip()):
                end += 1
            code = [line[4:] for line in lines[i:end]]
            while not code[-1].strip():
                code.pop()
            blocks.append(Block(name, i + 1, "shell", tuple(code), reason(i)))
            i = end
        else:
            i += 1
    return blocks


def _run(code: list[str], start: int, stop: int, page: Path, namespace: dict) -> list[str]:
    """Execute code lines [start, stop) (numbered as on the page) and return the lines they printed."""
    out = io.StringIO()
    with contextlib.redirect_stdout(out):
        exec(compile("\n" * start + "\n".join(code[start:stop]), str(page), "exec"), namespace)
    return out.getvalue().splitlines()


def run_page(name: str, namespace: dict | None = None, until: str | None = None) -> dict:
    """Execute the ```python blocks of docs/<name> (README.md: the repository root's) in one namespace (`namespace`
    when given, so that a caller keeps it if the page raises), up to the first code line starting with `until`.

    Each line that starts with `print(` must print one line, the text after its `#`; a print line whose comment
    is `# ...` runs without comparison (for long output the page shows below). Nothing else may print."""
    page = page_path(name)
    code, inside = [], False
    for line in page.read_text().splitlines():  # non-code lines become blank, so line numbers are the page's
        inside = line.strip() == "```python" or (inside and line.strip() != "```")
        code.append(line if inside and line.strip() != "```python" else "")
    if until is not None:
        stop = next(i for i, line in enumerate(code) if line.startswith(until))
        code = code[:stop]
    namespace = {} if namespace is None else namespace
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
