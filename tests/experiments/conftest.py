"""The reference reproduction shared by the sweep tests."""

from __future__ import annotations

import pytest

from bilevel.experiments import willems


@pytest.fixture(scope="session")
def willems_seed0(tmp_path_factory) -> str:
    """An uninterrupted quick Willems reproduction (1 sim, seed 0, 2 workers): the reference tables."""
    out = str(tmp_path_factory.mktemp("willems") / "seed0")
    willems.run_reproduction(sims=1, out_dir=out, quick=True, seed=0, progress=None, workers=2)
    return out
