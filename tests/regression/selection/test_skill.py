"""Held-out skill of a fitted model against the baselines, and its noise-corrected score."""

import math
import warnings

import numpy as np
import pytest
import torch

from torchconn import (
    ConnectionEstimator,
    NoiseAwareRegression,
    TubeRegression,
)
from torchconn.cycles import cycle_blocks
from torchconn.noise import interval_noise_gains
from torchconn.regression import (
    IllConditionedBinWarning,
    assign_bins,
    connection_regression,
)
from torchconn.regression.noise_aware import regression as noise_aware
from torchconn.regression.selection import PoorHeldOutSkillWarning, skill

from ..common import (
    WAVE_SPC,
    assert_close_to_its_scale,
    fit_and_view,
    fit_pooled,
    fourier_columns,
    noisy_circle_trials,
)

F64 = torch.float64


def test_held_out_skill_beats_the_baselines_on_a_long_recording(clean30):
    traj = noisy_circle_trials(0.002, clean=clean30)
    est = fit_pooled(traj)
    with warnings.catch_warnings():
        warnings.simplefilter("error", PoorHeldOutSkillWarning)
        held = est.check_held_out(3)
    assert bool((held.r2 > held.r2_phase_average).all())
    assert bool((held.r2 > held.r2_template).all())
    # score() on a recording the fit never saw, phased by the fitted phaser
    new = noisy_circle_trials(0.002, n_cycles=8, n_trials=1, seed=5)
    fresh = est.score(new)
    assert bool((fresh.r2 > fresh.r2_phase_average).all())
    # reproducible: the blocks are whole cycles in order, nothing random
    assert torch.equal(est.cross_validate(3).r2, held.r2)


def test_noise_corrected_score_uses_the_filters_noise_gains():
    """The held-out score's input-noise correction (``cross_validate(noise_corrected=True)``)
    takes the noise of the samples the model sees: the filter's gains
    (``interval_noise_gains``), not the box's ``σ²/2`` and ``2σ²/(hΔt)²`` (3.5x and 1.6x too much
    for a triangle over 8 samples)."""
    from torchconn.regression.selection.skill import _noise_of

    traj = noisy_circle_trials(0.005, n_cycles=10, n_trials=2)
    model = fit_pooled(traj).model_
    meta = model.meta
    h, kernel = meta["velocity_interval"], meta["velocity_kernel"]
    assert kernel == "triangle" and h > 2
    var_delta, var_rate = _noise_of(model, traj.dt, pool=True)
    g_delta, g_rate = interval_noise_gains(h, traj.dt, kernel)
    sigma2 = torch.tensor(meta["noise_r"], dtype=F64).square()
    torch.testing.assert_close(var_delta, sigma2 * g_delta)
    torch.testing.assert_close(var_rate, sigma2 * g_rate)
    assert g_delta < 0.5 / 2 and g_rate < 2 / (h * traj.dt) ** 2


F64 = torch.float64


def test_cross_validate_matches_the_refitting_one_when_nothing_is_rechosen(eight):
    traj, cycle, _ = eight
    reg = TubeRegression(n_bins=24, fourier_order=6, window=2.0)
    down = skill.cross_validate(traj, cycle, reg, pool=False)
    refit = skill.cross_validate(traj, cycle, reg, pool=False, refit=True)
    torch.testing.assert_close(down.r2, refit.r2, rtol=0, atol=1e-9)
    torch.testing.assert_close(down.r2_phase_average, refit.r2_phase_average)


def test_the_check_scores_the_noise_aware_fit_as_blended_with_the_smoothed_one(eight):
    """The held-out fits of a NoiseAwareRegression are combined as its fit combines them: the
    smoothed regression refitted without each block (its own window rule on the other
    blocks) plus the fit's weights times the corrected fit's difference from it. Scoring the
    corrected estimate alone was pessimistic wherever the blend falls back."""
    from torchconn.regression.binning import auto_window

    traj, cycle, _ = eight
    reg = NoiseAwareRegression(n_bins=16, fourier_order=4)
    model, view, fold = fit_and_view(traj, cycle, reg, pool=False)
    w = torch.as_tensor(model.meta["corrected_weight"], dtype=F64)  # (2, 4): c, b, A, ∂A/∂r
    assert bool((w < 1).any()) and bool((w > 0).any())
    corrected = skill.held_out_coefficients(traj, reg, model, view, fold, 3, pool=False)
    blended = skill.blended_held_out(traj, reg, model, corrected, 3, pool=False)[0]
    sm, d = traj.smoothed, traj.shape_dim
    sample_fold = cycle_blocks(traj.phase, 3)
    term = torch.tensor([0] + [1] * d + [2] * d + [3] * d * d)
    # the window rule on the samples outside block 0, as for the corrected fits (the blocks
    # are about equal)
    window = auto_window(torch.where(sample_fold == 0, torch.nan, traj.phase), 16,
                          1 + 2 * d + d * d, reg.samples_per_regressor)
    for f in range(3):
        phase = torch.where(sample_fold == f, torch.nan, traj.phase)
        bins = assign_bins(phase, 16, window=window, kernel="tricube")
        smoothed = connection_regression(sm.r, sm.r_dot, sm.xi, bins, model.bins.gamma,
                                         model.bins.gamma_dot).coef  # (2, M, P, 3)
        weight = w[:, term][:, None, :, None]
        assert_close_to_its_scale(blended[f], smoothed + weight * (corrected[0, f] - smoothed))
    # the check's score is the blend's: at least as good as the corrected estimate's alone
    blend = skill.cross_validate(traj, cycle, reg, pool=False, model=model)
    with pytest.MonkeyPatch.context() as mp:  # the corrected estimate alone, not shrunk
        mp.setattr(noise_aware, "blend_fits", lambda smoothed, corrected, **kwargs: (
            corrected, torch.ones(corrected.n_samples.shape[:-1] + (4,), dtype=F64)))
        alone = skill.cross_validate(traj, cycle, reg, pool=False)
    assert float((blend.r2 - alone.r2).mean()) > 0


def test_a_component_whose_shape_terms_lose_held_out_falls_back_to_the_phase_average(
        short_and_later):
    train, later = short_and_later
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", IllConditionedBinWarning)
        with pytest.warns(PoorHeldOutSkillWarning, match="predicts it by the phase-averaged"):
            # the noise-aware default, without the physics prior (this simulation is of its
            # reference family, which would take over the forecasts)
            est = ConnectionEstimator(prior=None).fit(train)
        warnings.simplefilter("ignore", PoorHeldOutSkillWarning)
        again = ConnectionEstimator(prior=None).fit(train)
    choice = est.complexity_
    assert choice == again.complexity_  # reproducible: whole cycles in order, nothing random
    fallback, conn = choice.phase_averaged[0], choice.connection_only[0]
    assert fallback == (False, True, False) and conn == (True, False, True)
    assert choice.phase_averaged_names() == ["v_y"]
    assert choice.connection_only_names() == ["v_x", "omega"]
    model = est.forecast_model_  # what predict() and score() use
    assert model.meta["phase_averaged"] == [list(fallback)]
    assert model.meta["connection_only"] == [list(conn)]
    # v_y: no shape terms; v_x and ω: Â kept, b̂ and ∂Â/∂r rows 0
    assert bool((model.b.coeffs == 0).all()) and bool((model.dA.coeffs == 0).all())
    assert bool((model.A.coeffs[..., 1, :] == 0).all())
    plain = est.regression_.fit(est.trajectory_, est.limit_cycle_, pool=False)
    for k in (0, 2):  # the connection is the regression's own, untouched
        assert torch.equal(model.A.coeffs[..., k, :], plain.A.coeffs[..., k, :])
        assert torch.equal(model.c.coeffs[..., k], plain.c.coeffs[..., k])
    # v_y's intercept is the least-squares Fourier series of the training data's observed
    # v_y in phase, as the regression sees it (numpy's lstsq, independent of fit_fourier)
    view = skill.regression_view(est.trajectory_, est.regression_, plain, pool=False)
    ok = torch.isfinite(view.phase[0]) & torch.isfinite(view.xi[0]).all(-1)
    k = est.regression_.fourier_order
    harmonics = torch.arange(1, k + 1, dtype=F64)

    def design(ph):
        return torch.cat([torch.ones_like(ph), torch.stack(
            [torch.cos(harmonics * ph), torch.sin(harmonics * ph)], -1).flatten(-2)], -1)

    coef = np.linalg.lstsq(design(view.phase[0, ok, None]).numpy(),
                           view.xi[0, ok, 1].numpy(), rcond=None)[0]
    grid = torch.linspace(0, 2 * math.pi, 50, dtype=F64)
    gen = torch.Generator().manual_seed(1)
    r, r_dot = torch.randn(2, 1, 50, 4, generator=gen, dtype=F64)  # any shape: v_y ignores it
    pred = model.predict(grid[None], r, r_dot)[0, :, 1]
    torch.testing.assert_close(pred, design(grid[:, None]) @ torch.from_numpy(coef), rtol=0,
                               atol=1e-10)
    # held out, on the training cycles and on the later ones, v_y ties the phase average
    # exactly, and ω keeps beating it
    for s in (est.held_out_skill_, est.score(later)):
        assert float(s.r2[..., 1]) == float(s.r2_phase_average[..., 1])
        assert float(s.r2[..., 2]) > float(s.r2_phase_average[..., 2])
        assert not bool(s.worse_than_phase_average.any())
    # the estimator's cross_validate agrees with the fit's own check
    assert torch.equal(est.cross_validate(3).r2, est.held_out_skill_.r2)


def test_the_phase_average_takes_each_component_s_order_from_held_out_cycles():
    """``phase_average_orders`` on made-up velocities over 4 cycles (blocks of cycles 0-1, 2,
    3): per component the order of least held-out squared error, refitted by numpy's lstsq
    without each block; a second harmonic, noise alone and a fundamental plus a fifth
    harmonic need at least orders 2, 0 and 5 and get far fewer than the 12 allowed.
    ``phase_average`` gives each component its own least-squares series, its higher
    harmonics 0."""
    gen = torch.Generator().manual_seed(3)
    n = 4 * WAVE_SPC
    phase = 2 * math.pi * torch.arange(n, dtype=F64) / WAVE_SPC + 0.4
    noise = 0.05 * torch.randn(n, 3, generator=gen, dtype=F64)
    xi = torch.stack([0.5 * torch.cos(2 * phase), torch.zeros_like(phase),
                      torch.sin(phase) + 0.3 * torch.cos(5 * phase)], -1) + noise
    view = skill.RegressionView(phase, torch.zeros(n, 4, dtype=F64), torch.zeros(n, 4, dtype=F64), xi)
    orders = skill.phase_average_orders(view, 12, pool=False)
    fold = (torch.arange(n) // WAVE_SPC) * 3 // 4
    sse = torch.zeros(13, 3, dtype=F64)
    for order in range(13):
        x = fourier_columns(phase, order)
        for f in range(3):
            out = fold == f
            coef = np.linalg.lstsq(x[~out].numpy(), xi[~out].numpy(), rcond=None)[0]
            sse[order] += (xi[out] - x[out] @ torch.from_numpy(coef)).square().sum(0)
    assert orders.tolist() == sse.argmin(0).tolist()
    assert orders[0] >= 2 and orders[1] >= 0 and orders[2] >= 5 and bool((orders < 9).all())
    series = skill.phase_average(view, 12, orders)
    assert series.order == 12
    for k, order in enumerate(orders.tolist()):
        design = fourier_columns(phase, order)
        coef = np.linalg.lstsq(design.numpy(), xi[:, k].numpy(), rcond=None)[0]
        torch.testing.assert_close(series.coeffs[:2 * order + 1, k], torch.from_numpy(coef),
                                   rtol=0, atol=1e-12)
        assert bool((series.coeffs[2 * order + 1:, k] == 0).all())
    # pooled trials (batch dims first) get one order per component
    two = skill.RegressionView(torch.stack([phase, phase]), view.r.expand(2, n, 4),
                      view.r_dot.expand(2, n, 4), torch.stack([xi, xi.flip(0)]))
    assert skill.phase_average_orders(two, 12, pool=True).shape == (3,)
    assert skill.phase_average_orders(two, 12, pool=False).shape == (2, 3)
