"""docs/own_plant.md runs as shown: its python blocks are executed here, and its printed numbers are checked."""

from __future__ import annotations

import contextlib
import io
import re
from pathlib import Path

import numpy as np

PAGE = Path(__file__).resolve().parents[2] / "docs" / "own_plant.md"


def test_own_plant_page_runs_and_prints_what_it_says(tmp_path, monkeypatch) -> None:
    """Fit, max-min attack with float budgets, step figure, destabilize with ARX orders from the data."""
    code = "\n".join(re.findall(r"```python\n(.*?)```", PAGE.read_text(), flags=re.S))
    monkeypatch.chdir(tmp_path)
    out = io.StringIO()
    namespace: dict = {}
    with contextlib.redirect_stdout(out):
        exec(compile(code, str(PAGE), "exec"), namespace)
    promised = [line.split("#", 1)[1].strip() for line in code.splitlines() if line.startswith("print(")]
    assert out.getvalue().splitlines() == promised
    result, fit = namespace["result"], namespace["fit"]
    np.testing.assert_allclose(result.theta_clean, fit.theta, rtol=1e-9)
    assert result.value > 2 * result.value_clean
    assert np.linalg.norm(result.theta_poisoned - result.theta_clean) > 0.5 * np.linalg.norm(result.theta_clean)
    assert namespace["unstable"].spectral_radius > namespace["unstable"].spectral_radius_clean
    figure = tmp_path / "own_plant_steps.png"
    assert figure.stat().st_size > 10_000 and figure.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
