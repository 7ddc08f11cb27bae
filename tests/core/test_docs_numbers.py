"""Numbers quoted in README.md and docs/ equal the committed results they come from.

Each quote names its page, a pattern that finds the number in the prose (exactly once) and the value read
from the committed result file; a page edited without its result, or a result re-run without its page,
fails here, so prose cannot drift from what was measured.
"""

import csv
import json
import re
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import pytest

from bilevel.problems import registry

ROOT = Path(__file__).resolve().parents[2]
RESULTS = ROOT / "docs" / "results"


def _text(path: str) -> str:
    return (ROOT / path).read_text()


def _one(pattern: str, text: str, where: str) -> re.Match[str]:
    matches = list(re.finditer(pattern, text))
    assert len(matches) == 1, f"{where}: pattern {pattern!r} found {len(matches)} times (expected once)"
    return matches[0]


def _vrft_report_median_ms() -> str:
    return _one(r"Median time per max-min attack: ([\d.]+) ms", _text("docs/results/vrft/report.md"), "report").group(1)


def _vrft_timings() -> dict[str, list[float]]:
    return json.loads((RESULTS / "vrft" / "timings.json").read_text())


def _vrft_summary(sweep: str, scenario: str) -> str:
    row = _one(rf"\| {re.escape(sweep)} \| ([\d.]+)% \| ([\d.]+)% \|", _text("docs/results/vrft/report.md"), "report")
    return row.group(1 if scenario == "A" else 2)


def _vrft_table1_b(eps_u: str) -> list[str]:
    """Scenario-B, paper-convention row of Table 1 in the report: 'rate [lo, hi]' per eps_y."""
    report = _text("docs/results/vrft/report.md")
    table = report[report.index("| Scenario B |"):]
    table = table[:table.index("\n\n")]
    row = _one(rf"\| eps_u = {re.escape(eps_u)} \|(.*)\|", table, "report table 1 B").group(1)
    return [f"{m.group(1)} [{m.group(2)}, {m.group(3)}]" for m in re.finditer(r"([\d.]+)% \[([\d.]+), ([\d.]+)\]", row)]


def _detection(case: str) -> tuple[str, str]:
    rows = {r["case"]: r for r in _markdown_rows(RESULTS / "defenses-quick" / "detection.md")}
    return rows[case]["detected (95% CI)"], rows[case]["attack succeeded"]


def _markdown_rows(path: Path) -> list[dict[str, str]]:
    lines = [line for line in path.read_text().splitlines() if line.startswith("|")]
    header = [cell.strip() for cell in lines[0].strip("|").split("|")]
    return [dict(zip(header, (c.strip() for c in line.strip("|").split("|")))) for line in lines[2:]]


def _compare_rows() -> list[dict[str, str]]:
    with open(RESULTS / "compare" / "compare.csv", newline="") as f:
        return list(csv.DictReader(f))


@dataclass(frozen=True)
class Quote:
    """A number quoted on `page`: the pattern's first group must equal `expected()`."""

    name: str
    page: str
    pattern: str
    expected: Callable[[], str]


QUOTES = [
    Quote("README textbook count", "README.md", r"- (\d+) textbook problems with published optima",
          lambda: str(len(registry.names("textbook")))),
    Quote("vrft.md median ms", "docs/vrft.md", r"median \*\*([\d.]+) ms\*\* per max-min attack", _vrft_report_median_ms),
    Quote("vrft.md distinct attacks", "docs/vrft.md", r"the eight sweeps \(([\d,]+) distinct attacks\)",
          lambda: f"{int(sum(v[0] for v in _vrft_timings().values())):,}"),
    Quote("vrft.md attack seconds", "docs/vrft.md", r"took\n\*\*(\d+) s\*\* of attack time",
          lambda: f"{sum(v[1] for v in _vrft_timings().values()):.0f}"),
    Quote("vrft.md destabilize B", "docs/vrft.md", r"destabilizing attack [\d.]+% / ([\d.]+)%",
          lambda: _vrft_summary("destabilize-paper", "B")),
    Quote("vrft.md targeted B", "docs/vrft.md", r"targeted 0% / ([\d.]+)%\.", lambda: _vrft_summary("targeted-paper", "B")),
    Quote("vrft.md targeted B (prose)", "docs/vrft.md", r"rarely destabilizes: ([\d.]+)% in B",
          lambda: _vrft_summary("targeted-paper", "B")),
    Quote("vrft.md max-min A", "docs/vrft.md", r"max-min with the paper convention ([\d.]+)% /",
          lambda: _vrft_summary("maxmin-paper", "A")),
    Quote("vrft.md max-min B", "docs/vrft.md", r"max-min with the paper convention [\d.]+% / ([\d.]+)%;",
          lambda: _vrft_summary("maxmin-paper", "B")),
    Quote("vrft.md path B", "docs/vrft.md", r"along the budget path [\d.]+% / ([\d.]+)%;",
          lambda: _vrft_summary("maxmin-paper-path", "B")),
    Quote("vrft.md prefiltered-drop B", "docs/vrft.md", r"prefiltered-drop [\d.]+% / ([\d.]+)%;",
          lambda: _vrft_summary("maxmin-prefiltered-drop", "B")),
]
for _eps_u, _label in (("0.0", "0"), ("0.1", "0.1"), ("0.2", "0.2")):
    QUOTES.append(Quote(
        f"vrft.md Table 1 B eps_u={_eps_u}", "docs/vrft.md", rf"\n\| {re.escape(_label)} \|(( [^|]+ \|){{5}})\n",
        lambda e=_eps_u: " | ".join(_vrft_table1_b(e))))
for _case, _label in (("vrft-ignores", "VRFT, ignores the check"), ("vrft-respects", r"VRFT, respects it \(outputs only\)"),
                      ("ident-ignores", "identification, ignores the tests"),
                      ("ident-respects", r"identification, stealthy \(5%\)")):
    QUOTES.append(Quote(f"defenses.md detection {_case}", "docs/defenses.md", rf"\| {_label} \| [^|]+ \| ([^|]+) \|",
                        lambda c=_case: _detection(c)[0]))


def _normalize_table1(found: str) -> str:
    """The page's Table 1 cells 'rate [lo, hi] (paper)' reduced to 'rate [lo, hi]' (0.0 cells carry no interval)."""
    cells = [c.strip() for c in found.strip().strip("|").split("|")]
    return " | ".join(re.sub(r"\s*\([\d.]+\)$", "", c) for c in cells)


@pytest.mark.parametrize("quote", QUOTES, ids=[q.name for q in QUOTES])
def test_quoted_number_equals_committed_result(quote: Quote) -> None:
    found = _one(quote.pattern, _text(quote.page), quote.page).group(1)
    expected = quote.expected()
    if "Table 1" in quote.name:
        found = _normalize_table1(found)
        expected = " | ".join(c if not c.startswith("0.0 [0.0,") else "0.0" for c in expected.split(" | "))
    assert found.strip() == expected, f"{quote.page} quotes {found.strip()!r}; the committed result says {expected!r}"


@pytest.mark.parametrize("method", ["global", "hypergradient", "ipopt", "relaxation"])
def test_solvers_page_quotes_the_committed_comparison(method: str) -> None:
    """docs/solvers.md's per-method summary lines are the committed compare.md's, word for word."""
    bullet = _one(rf"- \*\*{method}\*\*: .*\n", _text("docs/results/compare/compare.md"), "compare.md").group(0)
    assert bullet in _text("docs/solvers.md"), f"docs/solvers.md does not quote compare.md's line {bullet.strip()!r}"


def test_solvers_page_total_time_is_the_committed_sum() -> None:
    total = sum(float(row["wall_time"]) for row in _compare_rows())
    quoted = _one(r"`compare.csv` sums to\n(\d+) s \(", _text("docs/solvers.md"), "docs/solvers.md").group(1)
    assert quoted == f"{total:.0f}"


def test_compare_run_covers_every_textbook_problem() -> None:
    """docs/solvers.md's comparison table comes from a run over the whole registered textbook set."""
    run = {row["problem"] for row in _compare_rows()}
    assert run == set(registry.names("textbook"))
