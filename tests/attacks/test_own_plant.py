"""docs/own_plant.md runs as shown: its python blocks are executed here, and its printed numbers are checked."""

from __future__ import annotations

import numpy as np

from tests.docs_pages import run_page


def test_own_plant_page_runs_and_prints_what_it_says(tmp_path, monkeypatch) -> None:
    """Fit, max-min attack with float budgets, step figure, destabilize with ARX orders from the data."""
    monkeypatch.chdir(tmp_path)
    namespace = run_page("own_plant.md")
    result, fit = namespace["result"], namespace["fit"]
    theta0 = result.stats["theta_clean"]
    np.testing.assert_allclose(theta0, fit.theta, rtol=1e-9)
    assert result.upper_objective > 2 * result.stats["value_clean"] and result.certificate.passed
    assert np.linalg.norm(result.y["theta"] - theta0) > 0.5 * np.linalg.norm(theta0)
    assert namespace["unstable"].stats["spectral_radius"] > namespace["unstable"].stats["spectral_radius_clean"]
    figure = tmp_path / "own_plant_steps.png"
    assert figure.stat().st_size > 10_000 and figure.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
