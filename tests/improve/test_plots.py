"""The improvement loop's figures, drawn from a small synthetic loop (Agg backend)."""

from types import SimpleNamespace

import matplotlib
import pytest
import torch
from matplotlib.figure import Figure

from torchconn import NLinkSwimmer
from torchconn.improve.plots import plot_gaits, plot_rounds
from torchconn.plotting import caption_of

from ..plot_checks import assert_labelled, legend_texts

matplotlib.use("Agg")


def circle(radius):
    def gait(phi):
        return radius * torch.stack([torch.cos(phi), torch.sin(phi)], -1)
    return gait


def loop(objective="displacement", n=3):
    kinds = ("start", "proposal", "excited", "proposal")
    rounds = [SimpleNamespace(index=k, kind=kinds[k % 4], cycles=3, cycles_used=3 * (k + 1),
                              gait=circle(0.5 + 0.2 * k), proposal=circle(0.7 + 0.2 * k),
                              observed=0.1 * k, observed_se=0.01, true=0.1 * k + 0.005,
                              kept_true=0.1 * k + 0.005, moved=k != 1,
                              predicted=0.1 * k + 0.1, predicted_low=0.1 * k + 0.08,
                              predicted_high=0.1 * k + 0.12, realised=0.1 * k + 0.1)
              for k in range(n)]
    return SimpleNamespace(rounds=rounds, settings=SimpleNamespace(objective=objective))


def test_gaits_over_the_curvature(tmp_path):
    fig = plot_gaits(loop(), NLinkSwimmer(3))
    assert isinstance(fig, Figure) and caption_of(fig)
    ax = fig.axes[0]
    assert_labelled(ax, x=("rad",), y=("rad",))
    assert "joint 1 (tail)" in ax.get_xlabel() and "joint 2 (head)" in ax.get_ylabel()
    assert legend_texts(ax) == ["0: start", "1: proposal", "2: excited", "next proposal"]
    assert "(BL/rad²)" in fig.axes[1].get_ylabel()  # the colour bar
    assert list(tmp_path.iterdir()) == []


@pytest.mark.parametrize("objective, unit", [("displacement", "BL"), ("turning", "rad")])
def test_rounds_name_the_objective_with_its_unit(objective, unit):
    fig = Figure()
    ax = fig.subplots()
    assert plot_rounds(loop(objective), ceiling=0.5, ax=ax) is fig
    assert ax.get_xlabel() == "cycles recorded" and f"({unit})" in ax.get_ylabel()
    texts = legend_texts(ax)
    assert len(texts) == 6 and "optimiser, true connection" in texts
    assert "kept gait: true (simulator)" in texts
    assert caption_of(fig)
