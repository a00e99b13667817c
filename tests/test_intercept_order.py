"""The intercept's Fourier order chosen from held-out cycles (TubeRegression.intercept_order)."""

import dataclasses
import math

import numpy as np
import pytest
import torch

from torchconn import ConnectionEstimator, NLinkSwimmer, TiedMetric, TubeRegression, simulate
from torchconn.cycles import whole_cycle_weights
from torchconn.evaluation.models import error_summary, reference_models
from torchconn.phase import held_out_order
from torchconn.phase.fourier import FourierSeries, fit_fourier
from torchconn.physics.gaits import reference_gait


def _periodic(theta, orders, amp=1.0):
    """Sum of harmonics ``orders`` of amplitude ``amp / k`` at phases ``theta``."""
    return sum(amp / k * torch.cos(k * theta + 0.3 * k) for k in orders)


def test_held_out_order_keeps_the_harmonics_the_data_resolve():
    gen = torch.Generator().manual_seed(0)
    t = torch.arange(30 * 64, dtype=torch.float64) * (2 * math.pi / 64)
    theta = t.expand(3, -1)
    clean = _periodic(theta, (1, 2, 5, 9))
    noise = 0.02 * torch.randn(theta.shape, generator=gen, dtype=torch.float64)
    values = torch.stack([clean + noise, clean - noise], -1)  # (3, T, 2)
    w = whole_cycle_weights(theta)
    chosen = held_out_order(theta, w, values, 20)
    # harmonic 9 (amplitude 0.11) is kept; noise harmonics may win a few by chance, not all
    assert bool((chosen >= 9).all() & (chosen <= 13).all()), chosen
    pure = held_out_order(theta, w, noise.unsqueeze(-1), 20)
    assert bool((pure <= 2).all())  # noise alone: (nearly) nothing above the mean
    pooled = held_out_order(theta, w, values, 20, n_pooled=1)
    assert pooled.shape == () and 9 <= int(pooled) <= 13


def test_truncated_zeroes_the_harmonics_above_each_elements_order():
    phi = torch.linspace(0, 2 * math.pi, 48, dtype=torch.float64)[:-1]
    values = torch.stack([_periodic(phi, (1, 4, 7)), _periodic(phi, (1, 4, 7))]).unsqueeze(-1)
    series = fit_fourier(phi, values, 10, value_ndim=1)
    cut = series.truncated(torch.tensor([4, 10]))
    low = fit_fourier(phi, values, 4, value_ndim=1)
    torch.testing.assert_close(cut(phi)[0], low(phi)[0])  # equispaced: truncation = refit
    torch.testing.assert_close(cut(phi)[1], values[1])
    assert isinstance(cut, FourierSeries) and cut.order == 10


def test_intercept_order_above_the_bins_is_refused():
    with pytest.raises(ValueError, match="intercept_order must satisfy 2\\*intercept_order < n_bins=48"):
        TubeRegression(intercept_order=24)
    with pytest.raises(ValueError, match="intercept_order"):
        TubeRegression(intercept_order="high")


def _errors(name, seeds, eta_factor):
    """x RMS error of the default model against the simulator's ``A(r)ṙ`` on the same smoothed
    shapes, and of the same model with its intercept at ``fourier_order``."""
    system = NLinkSwimmer(int(name[0]))
    traj = simulate(system, reference_gait(name), eta=0.025 * eta_factor, alpha=0.05,
                    n_cycles=30, samples_per_cycle=64, substeps=8, seeds=seeds)
    est = ConnectionEstimator(regression=TubeRegression(), complexity="fixed",
                              metric=TiedMetric(enabled=False),
                              held_out_folds=0).fit(traj)
    model = est.model_
    fixed = dataclasses.replace(model, c=fit_fourier(model.bins.phase, model.bins.c, 12,
                                                     value_ndim=1))

    def error(m):
        preds = reference_models(system, m, est.trajectory_)
        return error_summary(preds["data_driven"], preds["ground_truth"])[0][..., 0]

    return model.meta["intercept_order"], error(model), error(fixed)


def test_the_9link_intercept_gets_the_harmonics_its_body_velocity_has():
    """The 9-link reference gait's on-cycle body velocity has harmonics above 12: the chosen
    intercept order is higher and the model's error against the simulator's own body velocity
    (A(r)ṙ on the same smoothed shapes) falls; the 3-link's stays at the given order, so its
    model is the one of order 12."""
    seeds = np.array([[311, 312]])
    orders, err, err_fixed = _errors("9link", seeds, 0.25)
    assert all(k > 12 for k in orders[0])
    assert bool((err < 0.75 * err_fixed).all()), (err, err_fixed)
    orders3, err3, err3_fixed = _errors("3link", seeds, 1.0)
    assert orders3 == [[12, 12]]
    torch.testing.assert_close(err3, err3_fixed, rtol=1e-12, atol=0)
