"""The VRFT figures say what they show: every axis of the step responses (3b, 4) is labelled and titled with the
budgets, and the shaded bands of 3a and 6 are named in the legend."""

from __future__ import annotations

import pytest

from bilevel.experiments import vrft_figures
from bilevel.experiments.vrft import EPS_U, EPS_Y


@pytest.fixture
def drawn(monkeypatch) -> dict:
    """The figures the functions draw, by file name, kept open instead of written."""
    figures: dict = {}

    def keep(fig, out_dir: str, name: str) -> str:
        figures[name] = fig
        return f"{name}.png"

    monkeypatch.setattr(vrft_figures, "save_figure", keep)
    return figures


def _summary(n: int = 8) -> dict:
    """A summary of every (scenario, eps_u, eps_y) cell: means 1 with intervals [0.5, 2] over n simulations."""
    cell = {"n": n, "value": 1.0, "value_lo": 0.5, "value_hi": 2.0, "loss": 1.0, "loss_lo": 0.5, "loss_hi": 2.0}
    return {(s, eu, ey): dict(cell) for s in ("A", "B") for eu in EPS_U for ey in EPS_Y}


def test_step_responses_name_their_axes_and_budgets(drawn) -> None:
    vrft_figures.figure_steps(0, "")
    vrft_figures.figure_targeted(0, "")
    for name in ("fig3b_step", "fig4_targeted_step", "fig5_targeted_bode"):
        for ax in drawn[name].axes:
            assert ax.get_ylabel() and ax.get_xlabel(), name
            assert "eps_u = 0.1" in ax.get_title() and "eps_y = 0.057" in ax.get_title(), (name, ax.get_title())


def test_shaded_bands_are_named_in_the_legend(drawn) -> None:
    summaries = {"maxmin-paper": _summary(), "targeted-paper": _summary()}
    vrft_figures.figure_loss(summaries, "")
    vrft_figures.figure_targeted_losses(summaries, "")
    for name in ("fig3a_loss", "fig6_targeted_losses"):
        fig = drawn[name]
        for ax in fig.axes:
            assert ax.collections, name  # the bands
        legends = [ax.get_legend() for ax in fig.axes if ax.get_legend()] + list(fig.legends)  # per axes or shared
        assert legends, name
        for legend in legends:
            labels = [t.get_text() for t in legend.get_texts()]
            assert "shaded: 95% confidence interval of the mean over 8 simulations" in labels, (name, labels)


def test_legends_stay_off_the_data_and_the_clean_line_stays_visible(drawn) -> None:
    """Fig. 6's legend is one figure legend below the panels (inside, it covered curves); in figs. 3b and 4 the
    clean controller's response is drawn dashed above the poisoned one, so it shows where the two coincide."""
    summaries = {"maxmin-paper": _summary(), "targeted-paper": _summary()}
    vrft_figures.figure_targeted_losses(summaries, "")
    fig = drawn["fig6_targeted_losses"]
    assert len(fig.legends) == 1 and not any(ax.get_legend() for ax in fig.axes)
    vrft_figures.figure_targeted(0, "")
    for ax in drawn["fig4_targeted_step"].axes:
        lines = {line.get_label().split(" (")[0]: line for line in ax.get_lines()}
        assert lines["clean"].get_linestyle() == "--"
        assert lines["clean"].get_zorder() > lines["poisoned"].get_zorder()


def test_every_figure_of_the_report_has_a_caption() -> None:
    assert set(vrft_figures.CAPTIONS) == {"2", "3a", "3b", "4", "5", "6"}
    assert all(len(text) > 40 for text in vrft_figures.CAPTIONS.values())
