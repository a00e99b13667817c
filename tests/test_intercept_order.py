"""The intercept's Fourier order chosen from held-out cycles (TubeRegression.intercept_order)."""

import dataclasses
import math

import numpy as np
import pytest
import torch

from torchconn import ConnectionEstimator, NLinkSwimmer, TubeRegression, simulate
from torchconn.evaluation.models import error_summary, reference_models
from torchconn.phase import held_out_order, whole_cycle_weights
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
    est = ConnectionEstimator(regression=TubeRegression(metric=False), complexity="fixed",
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


def _short_fit(order_choice, n_cycles=4, seed=31):
    """The default estimator at the fixed complexity (48 bins, order 12) on the first
    ``n_cycles`` cycles of a 5-link wave (ω = 0.005, 126 samples per cycle), and the next 4
    cycles."""
    from torchconn import NoiseAwareRegression, Phaser, observe
    from torchconn.physics.gaits import FourierGait

    coeffs = torch.zeros(3, 4, dtype=torch.float64)
    lag = torch.arange(4, dtype=torch.float64) * (math.pi / 2)
    coeffs[1], coeffs[2] = 0.7 * torch.cos(lag), 0.7 * torch.sin(lag)
    seeds = np.array([seed])
    clean = simulate(NLinkSwimmer(5), FourierGait(coeffs), eta=0.025, n_cycles=n_cycles + 4,
                     samples_per_cycle=126, seeds=seeds)
    traj = observe(clean, 0.005, seeds=seeds).with_fields(power=None)
    cut = n_cycles * 126 + 1
    est = ConnectionEstimator(
        regression=NoiseAwareRegression(short_intercept_order=order_choice),
        phaser=Phaser(min_cycles=2.5), complexity="fixed", held_out_folds=0)
    return est.fit(traj.slice_time(0, cut)), traj.slice_time(cut, traj.n_samples)


@pytest.mark.parametrize("choice", ["phase_average", "model"])
def test_a_short_recordings_intercept_drops_the_harmonics_held_out_cycles_do_not_carry(choice):
    """4 cycles: each component's intercept keeps the harmonics up to an order chosen on
    held-out blocks, below 12 for v_x; everything else is the order-12 fit's bit for bit, its
    intercept's harmonics up to that order too; and the 4 later cycles' v_x is predicted
    better than by the order-12 intercept (measured, 5-link wave, seeds 30-34, 3-6 cycles, this
    complexity: the truncated intercept's v_x R² on later cycles was higher in 14 of 20
    recordings, by 0.134 here, lower by up to 0.032)."""
    est, later = _short_fit(choice)
    full, _ = _short_fit(None)
    orders = torch.tensor(est.model_.meta["intercept_component_order"])  # (1, 3)
    assert orders.shape == (1, 3) and int(orders[0, 0]) < 12
    assert "intercept_component_order" not in full.model_.meta
    for name in ("A", "b", "dA"):
        assert torch.equal(getattr(est.model_, name).coeffs, getattr(full.model_, name).coeffs)
    c, c_full = est.model_.c.coeffs[0], full.model_.c.coeffs[0]  # (2K+1, 3)
    harmonic = (torch.arange(c.shape[0]) + 1) // 2  # coefficient k of [a0, a1, b1, ...]
    kept = harmonic[:, None] <= orders[0]
    assert torch.equal(c[kept], c_full[kept]) and bool((c[~kept] == 0).all())
    r2, r2_full = est.score(later).r2[0, 0], full.score(later).r2[0, 0]
    assert float(r2) > float(r2_full) + 0.05, (r2, r2_full)


def test_a_long_recordings_intercept_is_not_truncated():
    """12 cycles: nothing is chosen, the model is the one without the option bit for bit (4 x
    30 cycles: README, "Short recordings")."""
    est, _ = _short_fit("phase_average", n_cycles=12)
    full, _ = _short_fit(None, n_cycles=12)
    assert "intercept_component_order" not in est.model_.meta
    for name in ("c", "A", "b", "dA"):
        assert torch.equal(getattr(est.model_, name).coeffs, getattr(full.model_, name).coeffs)


def test_the_phase_average_the_check_falls_back_to_gets_the_intercepts_orders():
    """With the option and the auto complexity, the phase average of the check and of
    ``score()`` has the orders chosen for it (harmonics above them 0), and a component that
    falls back to it ties it exactly on later cycles."""
    from torchconn import NoiseAwareRegression, Phaser

    est, later = _short_fit("phase_average")
    auto = ConnectionEstimator(regression=NoiseAwareRegression(
        short_intercept_order="phase_average"), phaser=Phaser(min_cycles=2.5))
    with pytest.warns(UserWarning):
        auto.fit(est.trajectory_)
    meta = auto.model_.meta
    orders = torch.tensor(meta["phase_average_order"])  # (1, 3)
    assert bool((orders <= auto.regression_.fourier_order).all())
    coeffs = auto.phase_average_.coeffs[0]  # (2K+1, 3)
    harmonic = (torch.arange(coeffs.shape[0]) + 1) // 2
    assert bool((coeffs[harmonic[:, None] > orders[0]] == 0).all())
    fallen = torch.tensor(auto.complexity_.phase_averaged)
    assert bool(fallen.any())
    s = auto.score(later)
    assert torch.equal(s.r2[fallen], s.r2_phase_average[fallen])
