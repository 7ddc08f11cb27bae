"""docs/own_plant.md runs as shown: its python blocks are executed here, and its printed numbers are checked."""

from __future__ import annotations

import numpy as np

from tests.docs_pages import run_page


def test_own_plant_page_runs_and_prints_what_it_says(tmp_path, monkeypatch) -> None:
    """VRFT: fit, max-min attack with float budgets, step figure, destabilize with ARX orders from the data.
    Willems: the aircraft pitch instance; the generic solve's point re-evaluated here (K = (U0 + Du) Q S^-1 from
    its Du and Q) has the stable loop the page states, the destabilizing attack's an unstable one with nearly the
    same log-det criterion."""
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

    instance, generic, aircraft = namespace["instance"], namespace["generic"], namespace["aircraft"]
    q, du = generic.y["Q"], generic.x["Du"]
    s = instance.x[:, :-1] @ q
    gain = np.linalg.solve((s + s.T) / 2, ((instance.u + du) @ q).T).T
    assert generic.certificate.passed and np.max(np.abs(du)) <= 0.3 + 1e-9
    assert abs(max(abs(np.linalg.eigvals(aircraft.A + aircraft.B @ gain))) - 0.9845) < 1e-3
    radius = namespace["radius"]
    assert max(abs(np.linalg.eigvals(aircraft.A + aircraft.B @ radius.stats["gain"]))) > 1.2
    # the page's proxy remark: the destabilizing point's log det(Acl Acl') is within 1e-5 below the generic maximum
    log_det = 2 * np.log(abs(np.linalg.det(instance.a_id + instance.b_id @ radius.stats["gain"])))
    assert generic.upper_objective - 1e-5 < log_det < generic.upper_objective
