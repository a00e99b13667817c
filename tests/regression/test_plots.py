"""Figures of a fitted local model: Figures returned, drawn into given axes, units, legends,
captions, and nothing written until saved (Agg backend)."""

import dataclasses
import warnings

import matplotlib
import numpy as np
import pytest
import torch
from matplotlib.figure import Figure

from torchconn import ConnectionEstimator, NLinkSwimmer, observe, simulate
from torchconn.plotting import caption_of, save_figure
from torchconn.regression import selection
from torchconn.regression.plots import (
    plot_connection,
    plot_held_out_velocity,
    plot_limit_cycle,
    plot_metric,
)

from ..plot_checks import assert_labelled, assert_units, legend_texts
from .common import circle_gait

matplotlib.use("Agg")


@pytest.fixture(scope="module")
def est():
    """The 3-link on a circle gait, two trials of 9 cycles with power, ω = 0.005, pooled."""
    traj = observe(simulate(NLinkSwimmer(3), circle_gait(), eta=0.025, n_cycles=9,
                            samples_per_cycle=48, seeds=np.arange(2)), 0.005, seeds=np.arange(2))
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        return ConnectionEstimator(pool=True).fit(traj)


def test_held_out_velocity_draws_the_forward_check(est, tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    fig = plot_held_out_velocity(est, trial=1)
    assert isinstance(fig, Figure) and caption_of(fig)
    axes = fig.axes
    assert len(axes) == 3
    for ax, unit in zip(axes, ("BL/s", "BL/s", "rad/s"), strict=True):
        assert_units(ax.get_ylabel(), unit)
    assert_units(axes[-1].get_xlabel(), "s")
    assert legend_texts(axes[0]) == ["recorded", "model, fitted without these cycles",
                                     "phase average of the earlier cycles", "held-out cycles"]
    assert "held-out R² model" in axes[0].get_title()
    # the model's line is the forward check's prediction of trial 1 on its last block
    pred = selection.forward_prediction(est.trajectory_, est.limit_cycle_, est.regression_,
                                        est.forecast_model_, pool=True,
                                        prior_weight=est.prior_weight_,
                                        frame=est.reference_.frame)
    y = axes[0].get_lines()[1].get_ydata()
    expect = pred.predicted[1, :, 0].numpy()
    held = np.isfinite(expect)
    assert held.sum() > 48 and np.isfinite(y).sum() == held.sum()
    assert np.allclose(y[np.isfinite(y)], expect[held])
    assert list(tmp_path.iterdir()) == []  # nothing written until saved
    assert save_figure(fig, tmp_path / "h.png").stat().st_size > 10_000


def test_forward_prediction_is_what_the_forward_check_scores(est):
    # the forecasts as delivered: blended with the physics reference where the prior acts
    # (this simulation is of the prior's family, so it does)
    assert bool((est.prior_weight_ > 0).any())
    pred = selection.forward_prediction(est.trajectory_, est.limit_cycle_, est.regression_,
                                        est.forecast_model_, pool=True,
                                        prior_weight=est.prior_weight_,
                                        frame=est.reference_.frame)
    ok = pred.held_out[..., None]
    y = torch.where(ok, pred.view.xi, 0.0)
    n = pred.held_out.sum()

    def r2(p):
        sse = (torch.where(ok, pred.view.xi - p, 0.0) ** 2).sum((0, 1))
        return 1 - sse / ((y ** 2).sum((0, 1)) - y.sum((0, 1)) ** 2 / n)

    assert torch.allclose(r2(pred.predicted), est.forward_skill_.r2, atol=1e-10)
    assert torch.allclose(r2(pred.phase_average), est.forward_skill_.r2_phase_average,
                          atol=1e-10)
    assert (~pred.held_out | torch.isfinite(pred.predicted).all(-1)).all()
    assert torch.isnan(pred.predicted[~pred.held_out]).all()


def test_held_out_velocity_bad_input(est):
    with pytest.raises(ValueError, match=r"trial must be an integer in \[0, 2\), got 2"):
        plot_held_out_velocity(est, trial=2)
    with pytest.raises(ValueError, match="not fitted; call estimator.fit"):
        plot_held_out_velocity(ConnectionEstimator())
    with pytest.raises(ValueError, match="axes must hold 3 x 1"):
        plot_held_out_velocity(est, axes=Figure().subplots(1, 2))


def test_connection_panels_name_rows_joints_and_units(est):
    model = est.model_
    fig = plot_connection(model)
    assert isinstance(fig, Figure) and len(fig.axes) == 3 * 2
    titles = [ax.get_title() for ax in fig.axes]
    assert titles[:2] == ["v_x per joint 1 (tail) rate (BL/rad)",
                          "v_x per joint 2 (head) rate (BL/rad)"]
    assert titles[4] == "ω per joint 1 (tail) rate (rad/rad)"
    assert_labelled(fig.axes[4], x=("rad",), y=("rad/rad",))
    assert_units(fig.axes[0].get_ylabel(), "BL/rad")
    assert "tail" in fig.get_suptitle() and "head" in fig.get_suptitle()
    assert len(legend_texts(fig.axes[0])) == 2
    assert "good" in caption_of(fig).lower()
    # with the truth, drawn into the caller's axes
    fig = Figure()
    grid = fig.subplots(3, 2)
    swimmer = NLinkSwimmer(3)
    out = plot_connection(model, truth=lambda phi: swimmer.connection(model.gamma_at(phi)),
                          axes=grid)
    assert out is fig and "true (simulator)" in legend_texts(grid[0, 0])


def test_limit_cycle_shows_every_joint_against_phase(est):
    traj = est.trajectory_
    fig = plot_limit_cycle(est.model_, traj.smoothed.r, traj.phase)
    assert isinstance(fig, Figure) and caption_of(fig)
    assert [ax.get_title() for ax in fig.axes] == ["joint 1 (tail)", "joint 2 (head)"]
    for i, ax in enumerate(fig.axes):
        assert_labelled(ax, x=("rad",), y=("rad",))
        assert f"r{i + 1}" in ax.get_ylabel()
        samples = ax.get_lines()[0].get_xdata()
        assert samples.size == traj.phase.numel() and 0 <= samples.min() <= samples.max() <= 7
    assert legend_texts(fig.axes[0]) == ["recorded samples", "limit cycle γ(φ)"]
    with pytest.raises(ValueError, match="pass r and phase together"):
        plot_limit_cycle(est.model_, traj.smoothed.r)
    with pytest.raises(ValueError, match=r"r must be \(\.\.\., T, 2\)"):
        plot_limit_cycle(est.model_, traj.smoothed.r[..., :1], traj.phase)


def test_metric_figure_and_its_errors(est):
    fig = plot_metric(est.model_)
    assert isinstance(fig, Figure) and caption_of(fig)
    assert "power unit" in fig.axes[0].get_title() and "(rad)" in fig.axes[-1].get_xlabel()
    assert len(legend_texts(fig.axes[0])) == 2
    with pytest.raises(ValueError, match="plot_metric: the model has no metric"):
        plot_metric(dataclasses.replace(est.model_, M=None))
