"""The discrepancy workflow's figures, drawn from small synthetic reports (Agg backend)."""

from types import SimpleNamespace

import matplotlib
import numpy as np
import pytest
from matplotlib.figure import Figure

from torchconn.discrepancy.figures import plot_residual_profiles, plot_terms
from torchconn.discrepancy.residuals import COMPONENTS
from torchconn.plotting import caption_of

from ..plot_checks import assert_labelled, legend_texts

matplotlib.use("Agg")


def report():
    rng = np.random.default_rng(0)
    m = 12
    centres = np.arange(m) * 2 * np.pi / m

    def profile(scale):
        mean = scale * np.sin(centres)[:, None] * np.ones(3) + 0.01 * rng.standard_normal((m, 3))
        return {"centres": centres, "mean": mean, "lo": mean - 0.02, "hi": mean + 0.02}

    comps = dict.fromkeys(COMPONENTS, 0.05)
    return SimpleNamespace(profiles={"before": profile(0.3), "after": profile(0.01)},
                           effects=[SimpleNamespace(name="marker_offset")], verdict="effect",
                           gap_before=comps, gap_after=comps, noise_floor=comps)


def terms(n_entries=16, m=12):
    rng = np.random.default_rng(1)
    z = lambda: rng.standard_normal((m, 3, n_entries)).tolist()  # noqa: E731
    return {"phase": (np.arange(m) * 2 * np.pi / m).tolist(), "reference": "twin",
            "terms": {name: {"z": z()} for name in ("c", "b", "A", "dA")}}


def test_residual_profiles_nominal_line_on_top_and_bands_in_legend(tmp_path):
    fig = plot_residual_profiles(report())
    assert isinstance(fig, Figure) and caption_of(fig)
    for ax in fig.axes:
        assert_labelled(ax, x=("rad",), y=("BL/s", "rad/s"))
        texts = legend_texts(ax)
        assert any("nominal simulator: 95% band" in t for t in texts), texts
        assert any("with marker_offset: 95% band" in t for t in texts), texts
        assert any("noise floor" in t for t in texts)
        nominal, = [ln for ln in ax.get_lines() if ln.get_label().startswith("nominal")]
        others = [ln for ln in ax.get_lines() if ln.get_label().startswith("with")]
        # drawn above the other model, dashed: it cannot hide beneath it
        assert nominal.get_linestyle() == "--"
        assert all(nominal.get_zorder() > o.get_zorder() for o in others)
    assert list(tmp_path.iterdir()) == []


def test_terms_are_summarised_not_one_line_per_entry():
    fig = plot_terms(terms())
    assert isinstance(fig, Figure) and caption_of(fig)
    assert len(fig.axes) == 4 * 3
    for ax in fig.axes:
        assert len(ax.get_lines()) <= 4  # median, largest |z|, zero line: not 16 entries
    assert {"median entry", "entry of largest |z|"} <= set(legend_texts(fig.axes[0]))
    assert any("range over the 16 entries" in t for t in legend_texts(fig.axes[0]))


def test_draws_into_given_axes():
    fig = Figure()
    axes = fig.subplots(1, 3)
    assert plot_residual_profiles(report(), axes=axes) is fig
    fig = Figure()
    assert plot_terms(terms(), axes=fig.subplots(4, 3)) is fig
    with pytest.raises(ValueError, match=r"plot_terms: axes must hold 4 x 3"):
        plot_terms(terms(), axes=Figure().subplots(2, 3))
