"""The sweep's figures, drawn from small synthetic tables (Agg backend)."""

from types import SimpleNamespace

import matplotlib
import numpy as np
import pytest
from matplotlib.figure import Figure

from torchconn.plotting import caption_of
from torchconn.sweep.figures import fig3b, fig3c, fig4a, fig4b, make_figures

from ..plot_checks import assert_units, legend_texts

matplotlib.use("Agg")

LEVELS = (0.5, 1.0, 2.0)
EXPERIMENTS = [SimpleNamespace(name="sys", levels=LEVELS, noise_kind="system"),
               SimpleNamespace(name="obs", levels=LEVELS, noise_kind="observation")]
MODELS = ("ground_truth", "data_driven", "analytic", "template")


def tables():
    t = np.linspace(0, 4 * np.pi, 40)
    traces = [{"experiment": "sys", "component": "x", "model": m, "t": float(ti),
               "value": float(np.sin(ti) + 0.01 * j)} for j, m in enumerate(MODELS) for ti in t]
    phase_errors = [{"experiment": "sys", "level": 1.0, "model": m, "component": "x",
                     "phase": float(p), "mean": 0.01 * np.sin(p), "rms": 0.02}
                    for m in ("data_driven", "analytic") for p in np.linspace(0, 6, 12)]
    results = [{"experiment": e, "model": "data_driven" if e == "obs" else m, "component": "x",
                "metric": metric, "level": lv, "value": lv * (1 + 0.1 * trial)}
               for e in ("sys", "obs") for m in ("data_driven", "analytic")
               for metric in ("rms_vs_ground_truth", "rms_vs_observed") for lv in LEVELS
               for trial in range(3)]
    return results, phase_errors, traces


def test_each_figure_has_units_a_legend_and_a_caption(tmp_path):
    results, phase_errors, traces = tables()
    figures = [fig3b(traces), fig3c(phase_errors, EXPERIMENTS), fig4a(results, EXPERIMENTS),
               fig4b(results, EXPERIMENTS)]
    for fig in figures:
        assert isinstance(fig, Figure) and caption_of(fig)
        ax = fig.axes[0]
        assert_units(ax.get_ylabel(), "BL/time unit")
        assert len(legend_texts(ax)) >= 2
    assert "(rad)" in figures[1].axes[0].get_xlabel()
    assert any("range over trials" in t for t in legend_texts(figures[2].axes[0]))
    assert list(tmp_path.iterdir()) == []


def test_make_figures_writes_what_the_tables_support(tmp_path):
    results, phase_errors, traces = tables()
    made = make_figures(tmp_path, results, phase_errors, [], EXPERIMENTS[:1])
    assert sorted(p.name for p in made) == ["fig3c_error_vs_phase.png", "fig4a_system_noise.png"]
    assert sorted(p.name for p in tmp_path.iterdir()) == sorted(p.name for p in made)
    assert fig3b([]) is None


def test_draws_into_given_axes():
    results, _, _ = tables()
    fig = Figure()
    assert fig4a(results, EXPERIMENTS, axes=[fig.subplots()]) is fig
    with pytest.raises(ValueError, match="fig4a: axes must hold 1 x 1"):
        fig4a(results, EXPERIMENTS, axes=Figure().subplots(1, 2))
