"""docs/own_plant.md runs as shown: its python blocks are executed here, and its printed numbers are checked."""

from __future__ import annotations

import numpy as np

from tests.docs_pages import run_page


def test_own_plant_page_runs_and_prints_what_it_says(tmp_path, monkeypatch) -> None:
    """Fit, max-min attack with float budgets, step figure, destabilize with ARX orders from the data."""
    monkeypatch.chdir(tmp_path)
    namespace = run_page("own_plant.md")
    result, fit = namespace["result"], namespace["fit"]
    np.testing.assert_allclose(result.theta_clean, fit.theta, rtol=1e-9)
    assert result.value > 2 * result.value_clean
    assert np.linalg.norm(result.theta_poisoned - result.theta_clean) > 0.5 * np.linalg.norm(result.theta_clean)
    assert namespace["unstable"].spectral_radius > namespace["unstable"].spectral_radius_clean
    figure = tmp_path / "own_plant_steps.png"
    assert figure.stat().st_size > 10_000 and figure.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
