"""Held-out skill without refits: downdated normal equations against true refits, the check
that every fit runs, and its warning."""

import dataclasses
import math
import warnings

import numpy as np
import pytest
import torch

from torchconn import (
    ConnectionEstimator,
    NLinkSwimmer,
    NoiseAwareRegression,
    SelfConsistentCycle,
    TiedMetric,
    TubeRegression,
    observe,
    simulate,
)
from torchconn.cycles import cycle_blocks, few_cycles
from torchconn.noise import IntervalSamples
from torchconn.regression import (
    IllConditionedBinWarning,
    LocalConnectionModel,
    assign_bins,
    connection_regression,
    selection,
)
from torchconn.regression.noise_aware import noise_aware_regression
from torchconn.regression.noise_aware import regression as noise_aware
from torchconn.regression.selection import PoorHeldOutSkillWarning, complexity, skill

from ...recordings import wave_gait

F64 = torch.float64
SPC = 126  # samples per cycle (Δt ≈ 0.05)


def _recording(n_cycles: int, n_trials: int = 1, omega: float = 0.005, seed: int = 0,
               n_links: int = 5):
    seeds = np.arange(n_trials) + 100 * seed
    clean = simulate(NLinkSwimmer(n_links), wave_gait(n_links - 1), eta=0.025, n_cycles=n_cycles,
                     samples_per_cycle=SPC, seeds=seeds)
    return observe(clean, omega, seeds=seeds)


@pytest.fixture(scope="module")
def eight():
    """Two trials of the 5-link, 8 cycles each, ω = 0.005, prepared (smoothed and phased)."""
    traj = ConnectionEstimator().prepare(_recording(8, n_trials=2))
    return traj, SelfConsistentCycle().fit(traj), SelfConsistentCycle().fit(traj, pool=True)


def _setup(traj, cycle, reg, pool):
    model = reg.fit(traj, cycle, pool=pool)
    view = skill.regression_view(traj, reg, model, pool=pool, flatten=False)
    return model, view, cycle_blocks(view.phase, 3)


def _close(a, b):
    scale = float(b[torch.isfinite(b)].abs().max())
    torch.testing.assert_close(a, b, rtol=0, atol=1e-9 * scale, equal_nan=True)


@pytest.mark.parametrize("ridge", [0.0, 0.3])
def test_downdated_fits_equal_refits_without_each_block(eight, ridge):
    traj, cycle, _ = eight
    reg = TubeRegression(n_bins=24, fourier_order=6, window=2.0)
    model, view, fold = _setup(traj, cycle, reg, pool=False)
    coef = skill.held_out_coefficients(traj, reg, model, view, fold, 3, pool=False,
                                       ridges=(ridge,))[0]
    for f in range(3):
        bins = assign_bins(torch.where(fold == f, torch.nan, view.phase), 24, window=2.0,
                           kernel="tricube")
        refit = connection_regression(view.r, view.r_dot, view.xi, bins, model.bins.gamma,
                                      model.bins.gamma_dot, ridge=ridge)
        _close(coef[f], refit.coef)


def test_downdated_noise_aware_fits_equal_refits_with_the_noise_correction(eight):
    traj, _, cycle = eight
    reg = NoiseAwareRegression(n_bins=16, fourier_order=4)
    model, view, fold = _setup(traj, cycle, reg, pool=True)
    assert float(torch.as_tensor(model.meta["noise_r"]).min()) > 0  # the correction is on
    coef = skill.held_out_coefficients(traj, reg, model, view, fold, 3, pool=True)[0]
    h = model.meta["velocity_interval"]
    var = torch.as_tensor(model.meta["noise_r"], dtype=F64).square()
    flat = [x.reshape((-1,) + x.shape[2:]) for x in (view.phase, view.r, view.r_dot, view.xi)]
    for f in range(3):
        phase = torch.where(fold.reshape(-1) == f, torch.nan, flat[0])
        samples = IntervalSamples(phase, *flat[1:], h=h, dt=traj.dt)
        bins = assign_bins(phase, 16, window=model.meta["window"], kernel="tricube")
        refit = noise_aware_regression(samples, bins, model.bins.gamma, model.bins.gamma_dot,
                                       var)
        _close(coef[f], refit.coef)


def test_a_fits_diagnostics_are_the_choices_its_meta_records(eight, tmp_path):
    """The typed diagnostics selection reads carry the fit's own choices: a noise-aware
    fit's interval, noise level and blend weights per trial, a tube fit's window and no
    noise-aware fields; a model saved and loaded keeps them."""
    traj, cycle, _ = eight
    noisy = NoiseAwareRegression(n_bins=16, fourier_order=4).fit(
        traj, cycle, pool=False)
    diag = noisy.diagnostics
    assert torch.equal(torch.as_tensor(diag.velocity_interval),
                       torch.as_tensor(noisy.meta["velocity_interval"]))
    assert torch.as_tensor(diag.noise_r).shape == (2, 4)  # trials, joints
    assert torch.equal(torch.as_tensor(diag.noise_r), torch.as_tensor(noisy.meta["noise_r"]))
    weight = torch.as_tensor(diag.corrected_weight)
    assert weight.shape == (2, 4) and bool(((weight >= 0) & (weight <= 1)).all())
    assert diag.velocity_kernel == noisy.meta["velocity_kernel"]
    with pytest.raises(dataclasses.FrozenInstanceError):
        diag.window = 1.0
    assert LocalConnectionModel.load(noisy.save(tmp_path / "model")).diagnostics == diag
    tube = TubeRegression(n_bins=16, fourier_order=4, window=2.0).fit(
        traj, cycle, pool=False)
    assert tube.diagnostics.window == 2.0
    assert tube.diagnostics.noise_r is None and tube.diagnostics.corrected_weight is None


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
    model, view, fold = _setup(traj, cycle, reg, pool=False)
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
        _close(blended[f], smoothed + weight * (corrected[0, f] - smoothed))
    # the check's score is the blend's: at least as good as the corrected estimate's alone
    blend = skill.cross_validate(traj, cycle, reg, pool=False, model=model)
    with pytest.MonkeyPatch.context() as mp:  # the corrected estimate alone, not shrunk
        mp.setattr(noise_aware, "blend_fits", lambda smoothed, corrected, **kwargs: (
            corrected, torch.ones(corrected.n_samples.shape[:-1] + (4,), dtype=F64)))
        alone = skill.cross_validate(traj, cycle, reg, pool=False)
    assert float((blend.r2 - alone.r2).mean()) > 0


@pytest.fixture(scope="module")
def short():
    """One trial of the 5-link, 4 cycles, ω = 0.005: the default complexity overfits it."""
    return _recording(4, seed=3)


def test_the_fit_warns_by_itself_and_auto_complexity_stops_the_overfit(short):
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", IllConditionedBinWarning)
        with pytest.warns(PoorHeldOutSkillWarning, match="worse than their phase-averaged"):
            fixed = ConnectionEstimator(complexity="fixed").fit(short)
        assert bool(fixed.held_out_skill_.worse_than_phase_average.any())
        assert fixed.complexity_ is None
        warnings.simplefilter("error", PoorHeldOutSkillWarning)
        off = ConnectionEstimator(complexity="fixed", held_out_folds=0).fit(short)  # no check
        assert off.held_out_skill_ is None
        warnings.simplefilter("ignore", PoorHeldOutSkillWarning)
        auto = ConnectionEstimator().fit(short)
    # a complexity as given: one model connects and forecasts
    assert fixed.forecast_model_ is fixed.model_ and off.forecast_model_ is off.model_
    # the default chose a simpler model; the fit's settings record what was fitted
    assert auto.complexity_ is not None and auto.regression.n_bins == 48
    assert auto.regression_.n_bins == auto.complexity_.n_bins
    assert auto.model_.meta["settings"]["regression"]["n_bins"] == auto.complexity_.n_bins
    gain = auto.held_out_skill_.r2 - fixed.held_out_skill_.r2
    assert bool((gain > 0).all())


def test_a_complexity_the_recording_cannot_carry_is_reported(short):
    # a window just wide enough for the whole recording's bins (30 samples for 25 regressors)
    # leaves too few once a third of the cycles is held out
    reg = TubeRegression(window=1.8)
    with pytest.warns(PoorHeldOutSkillWarning, match="cannot be fitted when one block"):
        est = ConnectionEstimator(regression=reg, complexity="fixed").fit(short)
    assert bool(est.held_out_skill_.unscored.all())



def test_the_shape_terms_must_win_by_more_than_z_standard_errors_of_the_cycles():
    from scipy import stats

    gen = torch.Generator().manual_seed(0)
    gaps = torch.randn(4, 6, 3, generator=gen, dtype=F64) - 0.6  # (trials, cycles, components)
    gaps[1, 4:] = 0.0  # a trial with 4 scored cycles
    gaps[2, :, 1] = 0.0  # a component tied in every cycle: never "better"
    t = torch.full((4, 3), math.nan, dtype=F64)
    for i in range(4):
        for k in range(3):
            g = gaps[i, :, k][gaps[i, :, k] != 0].numpy()
            if len(g) > 1:
                t[i, k] = float(stats.ttest_1samp(g, 0.0).statistic)
    base = torch.full_like(gaps, 2.0)  # the phase average's squared error per cycle
    for z in (0.0, 1.0, 2.5):
        with pytest.MonkeyPatch.context() as mp:
            mp.setattr(complexity, "FALLBACK_Z", z)
            mp.setattr(complexity, "FALLBACK_MARGIN", 0.0)
            better = complexity._clearly_better(torch.stack([gaps, base], -1))
            assert torch.equal(better, torch.nan_to_num(t, nan=math.inf) < -z)
            assert not bool(better[2, 1])
            # and by more than a fraction of the phase average's error
            mp.setattr(complexity, "FALLBACK_MARGIN", 0.1)
            wins = gaps.sum(-2) < -0.1 * base.sum(-2)
            assert torch.equal(complexity._clearly_better(torch.stack([gaps, base], -1)),
                               better & wins)


@pytest.fixture(scope="module")
def short_and_later():
    """One trial of the 5-link, ω = 0.005: 4 cycles to fit and the next 4 to score."""
    traj = _recording(8, seed=SHORT_SEED).with_fields(power=None)
    cut = 4 * SPC + 1
    return traj.slice_time(0, cut), traj.slice_time(cut, traj.n_samples)


SHORT_SEED = 7  # v_y falls back to the phase average, v_x and ω keep the connection alone


def test_a_component_whose_shape_terms_lose_held_out_falls_back_to_the_phase_average(
        short_and_later):
    train, later = short_and_later
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", IllConditionedBinWarning)
        with pytest.warns(PoorHeldOutSkillWarning, match="predicts it by the phase-averaged"):
            est = ConnectionEstimator().fit(train)  # the noise-aware default
        warnings.simplefilter("ignore", PoorHeldOutSkillWarning)
        again = ConnectionEstimator().fit(train)
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


def test_the_template_stays_the_connection_s_where_a_component_falls_back(short_and_later):
    """v_y falls back to the phase average (SHORT_SEED): the forecasting model's ĉ is that
    average there, and the template column used to repeat it; it is Â(γ)γ̇ of the fit."""
    train, later = short_and_later
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        est = ConnectionEstimator().fit(train)
    assert est.complexity_.phase_averaged == ((False, True, False),)
    scored, held = est.score(later), est.held_out_skill_
    for s in (scored, held):
        assert float(s.r2[..., 1]) == float(s.r2_phase_average[..., 1])
        assert abs(float(s.r2_template[..., 1] - s.r2_phase_average[..., 1])) > 1e-3
    # score(): ĉ of the connection model_, computed here from the samples score() sees
    view = skill.regression_view(est._prepare_new(later, None), est.regression_,
                                 est.forecast_model_, pool=False)
    ok = torch.isfinite(view.phase) & torch.isfinite(view.xi).all(-1)
    y, c = view.xi[ok], est.model_.c(view.phase)[ok]
    r2 = 1 - (y - c).square().sum(0) / (y - y.mean(0)).square().sum(0)
    torch.testing.assert_close(scored.r2_template.reshape(-1), r2, rtol=0, atol=1e-12)


def _same_series_and_bins(a, b):
    """Every Fourier series and per-bin tensor of two models equal bit for bit."""
    for name in ("gamma", "c", "b", "A", "dA", "dA_fit", "M"):
        x, y = getattr(a, name), getattr(b, name)
        assert (x is None) == (y is None), name
        assert x is None or torch.equal(x.coeffs, y.coeffs), name
    for f in dataclasses.fields(a.bins):
        x, y = getattr(a.bins, f.name), getattr(b.bins, f.name)
        assert (x is None) == (y is None), f.name
        assert x is None or torch.equal(x, y), f.name


def test_the_connection_is_unpenalised_and_whole_while_forecasts_keep_the_ridge(
        short_and_later, tmp_path):
    """Seed 7 (4 cycles): held-out error chose ridge 0.1, which penalises Â too, v_y
    predicted by the phase average and v_x, ω by the connection alone. ``model_`` is the fit
    at the complexity chosen the same way with Â unpenalised, every row estimated;
    ``forecast_model_`` (the ridge on Â, those rows 0) is what predict(), score() and the
    check use, as before the two were told apart. Â of the first is much closer to the
    swimmer's."""
    train, later = short_and_later
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", IllConditionedBinWarning)
        warnings.simplefilter("ignore", PoorHeldOutSkillWarning)
        est = ConnectionEstimator().fit(train)
    choice, reg = est.complexity_, est.regression_
    assert choice.ridge > 0 and reg.ridge == choice.ridge and reg.ridge_connection
    traj, cycle = est.trajectory_, est.limit_cycle_
    # the connection: the complexity chosen with Â unpenalised, fitted, nothing zeroed
    free, _ = complexity.select_complexity(traj, cycle, NoiseAwareRegression(ridge_connection=False),
                                      pool=False)
    direct = free.fit(traj, cycle, pool=False)
    _same_series_and_bins(est.model_, direct)
    assert bool((est.model_.A.coeffs[..., 1, :] != 0).any())  # v_y's row estimated
    assert est.model_.meta["settings"]["regression"]["ridge_connection"] is False
    assert est.model_.meta["forecast_model"] == {
        "n_bins": choice.n_bins, "fourier_order": choice.fourier_order,
        "A_ridge": choice.ridge, "phase_averaged": [[False, True, False]],
        "connection_only": [[True, False, True]]}
    # the forecasts: the penalised fit with the chosen rows zeroed, as before
    penalised = reg.fit(traj, cycle, pool=False)
    forecast = skill.with_phase_average(penalised, est.phase_average_,
                                        choice.phase_average_mask("cpu"),
                                        choice.connection_only_mask("cpu"))
    _same_series_and_bins(est.forecast_model_, forecast)
    assert est.forecast_model_.meta["settings"]["regression"]["ridge_connection"] is True
    assert "forecast_model" not in est.forecast_model_.meta
    smoothed = est.smoother.smooth(later)
    prepared = est.prepare(smoothed, est.phaser_.transform(smoothed.smoothed.r))
    expected = forecast.predict(prepared.phase, prepared.smoothed.r, prepared.smoothed.r_dot)
    assert torch.equal(est.predict(later), expected)
    view = skill.regression_view(prepared, reg, forecast, pool=False)
    assert torch.equal(est.score(later).r2, skill.skill(forecast, est.phase_average_, view).r2)
    assert torch.equal(est.cross_validate(3).r2, est.held_out_skill_.r2)
    # against the swimmer's connection along the fitted cycle (measured: 34 % at scale 0.80
    # against 59 % at 0.46)
    phi = torch.linspace(0, 2 * math.pi, 200, dtype=F64)[:-1]

    def error_and_scale(model):
        a_hat = model.connection(phi)[0]
        a_true = NLinkSwimmer(5).connection(model.gamma_at(phi)[0])
        return (float((a_hat - a_true).norm() / a_true.norm()),
                float((a_hat * a_true).sum() / a_true.square().sum()))

    err, scale = error_and_scale(est.model_)
    err_forecast, scale_forecast = error_and_scale(est.forecast_model_)
    assert err < 0.45 and scale > 0.7
    assert err_forecast > 0.55 and scale_forecast < 0.5
    # the model file keeps the connection and says how the forecasts differ
    loaded = LocalConnectionModel.load(est.model_.save(tmp_path / "model.npz"))
    _same_series_and_bins(loaded, est.model_)
    assert loaded.meta["forecast_model"] == est.model_.meta["forecast_model"]


def test_one_search_chooses_both_complexities_fitting_no_ridge_0_candidate_twice(
        short_and_later, monkeypatch):
    """Seed 7 (4 cycles): :func:`complexity.select_complexities` of the regression with Â
    penalised and without makes the choices :func:`complexity.select_complexity` makes for each
    alone (equal scores, bins, order, ridge and masks), while each ``(n_bins, order)`` gets
    one whole-recording fit and one held-out pass per setting, and ridge 0 (which penalises
    nothing) is solved once: in the first setting's pass."""
    train, _ = short_and_later
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", IllConditionedBinWarning)
        warnings.simplefilter("ignore", PoorHeldOutSkillWarning)
        est = ConnectionEstimator(complexity="fixed").fit(train)
    traj, cycle = est.trajectory_, est.limit_cycle_
    both = (NoiseAwareRegression(), NoiseAwareRegression(ridge_connection=False))
    alone = [complexity.select_complexity(traj, cycle, reg, pool=False) for reg in both]
    passes, fits = [], []
    held_out, fit = skill.held_out_coefficients, NoiseAwareRegression.fit

    def counted_pass(traj, regression, *args, ridges=None, **kwargs):
        if type(regression) is NoiseAwareRegression:  # not the smoothed blend's own pass
            passes.append((regression.n_bins, regression.ridge_connection, tuple(ridges)))
        return held_out(traj, regression, *args, ridges=ridges, **kwargs)

    def counted_fit(self, *args, **kwargs):
        fits.append(self.n_bins)
        return fit(self, *args, **kwargs)

    monkeypatch.setattr(complexity, "held_out_coefficients", counted_pass)
    monkeypatch.setattr(NoiseAwareRegression, "fit", counted_fit)
    together = complexity.select_complexities(traj, cycle, both, pool=False)
    assert together == alone
    assert alone[0][1].ridge > 0 and alone[0][1] != alone[1][1]  # the choices differ here
    grid = [n_bins for n_bins, _ in complexity.COMPLEXITY_GRID]
    assert sorted(fits) == sorted(grid)
    assert sorted(passes) == sorted([(n, True, complexity.RIDGE_GRID) for n in grid]
                                    + [(n, False, complexity.RIDGE_GRID[1:]) for n in grid])
    with pytest.raises(ValueError, match="differ only in ridge_connection"):
        complexity.select_complexities(traj, cycle, (both[0], both[1].replace(n_bins=96)),
                                  pool=False)


def test_the_terms_choice_presumes_the_simpler_model_on_few_cycles_only():
    """_choose_terms on made-up per-cycle gaps: the same evidence chooses the connection alone
    on a short recording (4 held-out cycles) and keeps the full model on a longer one (12)."""
    def gaps(full, conn, n):  # per-cycle SSE gaps (model - phase average), phase average 10
        g = torch.tensor([[full, conn]], dtype=F64).repeat(n, 1)
        sign = torch.tensor([1.0, -1.0] * (n // 2), dtype=F64)[:, None]
        g = g + 0.05 * sign * torch.tensor([1.0, -1.0], dtype=F64)  # opposite scatter
        base = torch.full((n, 3), 10.0, dtype=F64)
        return (torch.stack([g[:, :1].expand(n, 3), base], -1),
                torch.stack([g[:, 1:].expand(n, 3), base], -1))

    # both models beat the phase average clearly; the full one beats the connection by
    # less than OFFSET_TERMS_Z standard errors (0.05 per cycle, scatter 0.1)
    few, many = gaps(-2.0, -1.95, 4), gaps(-2.0, -1.95, 12)
    fallback, conn = complexity._choose_terms(*few, True)
    assert not bool(fallback.any()) and bool(conn.all())
    fallback, conn = complexity._choose_terms(*many, False)
    assert not bool(fallback.any()) and not bool(conn.any())
    # models no better than the phase average: it predicts, few cycles or many
    for n in (4, 12):
        worse = gaps(0.5, 0.5, n)
        fallback, conn = complexity._choose_terms(*worse, n == 4)
        assert bool(fallback.all()) and not bool(conn.any())
    # many cycles and a connection clearly better than the full model: the connection alone
    fallback, conn = complexity._choose_terms(*gaps(-1.0, -2.0, 12), False)
    assert not bool(fallback.any()) and bool(conn.all())
    # "short": the phase spans at most FALLBACK_CYCLES cycles, rounded (pooled: summed)
    spans = torch.tensor([[3.0], [6.05], [6.6], [30.0]], dtype=F64)  # cycles per trial
    phase = 2 * math.pi * spans * torch.linspace(0, 1, 200, dtype=F64) + 1.0
    phase[0, :20] = math.nan  # a gap at the start shortens the span
    assert few_cycles(phase, pool=False).tolist() == [True, True, False, False]
    assert not bool(few_cycles(phase[:2], pool=True))  # 2.7 + 6.05 cycles pooled
    assert bool(few_cycles(phase[:1], pool=True))


def test_no_component_falls_back_on_a_long_recording():
    long = _recording(15, n_trials=2, seed=1).with_fields(power=None)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", IllConditionedBinWarning)
        warnings.simplefilter("error", PoorHeldOutSkillWarning)
        auto = ConnectionEstimator(pool=True).fit(long)
        cv = ConnectionEstimator(pool=True, complexity="cv").fit(long)
    for est in (auto, cv):  # every component keeps its shape terms, offset terms included
        assert est.complexity_ is None or (
            est.complexity_.phase_averaged == (False,) * 3
            and est.complexity_.connection_only == (False,) * 3)
        assert "phase_averaged" not in est.model_.meta
        assert "connection_only" not in est.model_.meta
        # nothing shrunk or zeroed: one model connects and forecasts
        assert est.forecast_model_ is est.model_ and "forecast_model" not in est.model_.meta
        plain = est.regression_.fit(est.trajectory_, est.limit_cycle_, pool=True)
        for name in ("c", "A", "b", "dA"):
            assert torch.equal(getattr(est.model_, name).coeffs, getattr(plain, name).coeffs)
        assert bool((est.held_out_skill_.r2 > est.held_out_skill_.r2_phase_average).all())


def _same_model(a, b):
    """Every tensor of two models' bins and series equal bit for bit, and their meta."""
    for name in ("c", "b", "A", "dA", "c_se", "b_se", "A_se", "dA_se", "M", "M_se",
                 "M_gamma_dot", "M_gamma_dot_se", "power_on_cycle", "power_on_cycle_se"):
        x, y = getattr(a.bins, name), getattr(b.bins, name)
        assert x is not None and torch.equal(x, y), name
    for name in ("c", "b", "A", "dA", "M"):
        assert torch.equal(getattr(a, name).coeffs, getattr(b, name).coeffs), name
    assert a.meta == b.meta


def test_the_refit_after_the_complexity_choice_fits_nothing_twice(eight, monkeypatch):
    """``ConnectionEstimator``'s refit with the chosen complexity equals a fresh fit of the
    chosen regression with a fresh metric fit bit for bit, keeps the first fit when the choice
    is the given complexity, and the metric stage is fitted once for all of them (other bins
    only evaluate it elsewhere)."""
    from torchconn.regression import estimator as estimator_module

    traj, cycle, _ = eight
    given, stage = NoiseAwareRegression(), TiedMetric()
    calls = []
    original = TiedMetric.fit
    monkeypatch.setattr(TiedMetric, "fit", lambda *a, **k: calls.append(1) or original(*a, **k))
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        metric = stage, stage.fit(traj, cycle)
        first = estimator_module._fit(given, traj, cycle, False, metric)
        assert first.M is not None
        assert estimator_module._refit(given, given, first, traj, cycle, False, metric) is first
        for chosen in (given.replace(ridge=0.1, fourier_order=6),
                       given.replace(n_bins=24, fourier_order=6)):
            calls.clear()
            refit = estimator_module._refit(chosen, given, first, traj, cycle, False, metric)
            assert not calls, chosen
            _same_model(refit, stage.attach(chosen.fit(traj, cycle), stage.fit(traj, cycle)))
        calls.clear()
        ConnectionEstimator(complexity="cv").fit(traj)
    assert len(calls) == 1  # one metric fit, whatever the candidates


def _fourier_columns(phase, order):
    h = torch.arange(1, order + 1, dtype=F64)
    return torch.cat([torch.ones(phase.shape[0], 1, dtype=F64), torch.stack(
        [torch.cos(h * phase[:, None]), torch.sin(h * phase[:, None])], -1).flatten(-2)], -1)


def test_the_phase_average_takes_each_component_s_order_from_held_out_cycles():
    """``phase_average_orders`` on made-up velocities over 4 cycles (blocks of cycles 0-1, 2,
    3): per component the order of least held-out squared error, refitted by numpy's lstsq
    without each block; a second harmonic, noise alone and a fundamental plus a fifth
    harmonic need at least orders 2, 0 and 5 and get far fewer than the 12 allowed.
    ``phase_average`` gives each component its own least-squares series, its higher
    harmonics 0."""
    gen = torch.Generator().manual_seed(3)
    n = 4 * SPC
    phase = 2 * math.pi * torch.arange(n, dtype=F64) / SPC + 0.4
    noise = 0.05 * torch.randn(n, 3, generator=gen, dtype=F64)
    xi = torch.stack([0.5 * torch.cos(2 * phase), torch.zeros_like(phase),
                      torch.sin(phase) + 0.3 * torch.cos(5 * phase)], -1) + noise
    view = skill.RegressionView(phase, torch.zeros(n, 4, dtype=F64), torch.zeros(n, 4, dtype=F64), xi)
    orders = skill.phase_average_orders(view, 12, pool=False)
    fold = (torch.arange(n) // SPC) * 3 // 4
    sse = torch.zeros(13, 3, dtype=F64)
    for order in range(13):
        x = _fourier_columns(phase, order)
        for f in range(3):
            out = fold == f
            coef = np.linalg.lstsq(x[~out].numpy(), xi[~out].numpy(), rcond=None)[0]
            sse[order] += (xi[out] - x[out] @ torch.from_numpy(coef)).square().sum(0)
    assert orders.tolist() == sse.argmin(0).tolist()
    assert orders[0] >= 2 and orders[1] >= 0 and orders[2] >= 5 and bool((orders < 9).all())
    series = skill.phase_average(view, 12, orders)
    assert series.order == 12
    for k, order in enumerate(orders.tolist()):
        design = _fourier_columns(phase, order)
        coef = np.linalg.lstsq(design.numpy(), xi[:, k].numpy(), rcond=None)[0]
        torch.testing.assert_close(series.coeffs[:2 * order + 1, k], torch.from_numpy(coef),
                                   rtol=0, atol=1e-12)
        assert bool((series.coeffs[2 * order + 1:, k] == 0).all())
    # pooled trials (batch dims first) get one order per component
    two = skill.RegressionView(torch.stack([phase, phase]), view.r.expand(2, n, 4),
                      view.r_dot.expand(2, n, 4), torch.stack([xi, xi.flip(0)]))
    assert skill.phase_average_orders(two, 12, pool=True).shape == (3,)
    assert skill.phase_average_orders(two, 12, pool=False).shape == (2, 3)


def _nine_link_three_cycles():
    """9-link reference gait, 3 cycles fitted (the next 4 kept), ω = 0.005, seed 11: no
    (bins, order) of the grid can be fitted without a third of the cycles with its full
    model's 1 + 2d + d² regressors per bin."""
    from torchconn.physics.gaits import reference_gait

    seeds = np.array([11])
    clean = simulate(NLinkSwimmer(9), reference_gait("9link"), eta=0.025, n_cycles=7,
                     samples_per_cycle=SPC, seeds=seeds)
    traj = observe(clean, 0.005, seeds=seeds).with_fields(power=None)
    cut = 3 * SPC + 1
    return traj.slice_time(0, cut), traj.slice_time(cut, traj.n_samples)


def test_a_short_recording_no_full_model_can_score_is_checked_by_the_connection_alone():
    """The 3-cycle 9-link recording: the connection alone (1 + d regressors per bin) can be
    scored held out, so it is, as on longer video-rate recordings. Before, the given 48-bin
    fit stood unchecked, its forecasts the phase average everywhere and its connection 116 %
    off the swimmer's; now ω is predicted by the connection alone, which beats the phase
    average on the next 4 cycles too (0.996 vs 0.959), and the connection delivered is
    closer to the swimmer's than the unchecked fit's."""
    from torchconn import Phaser

    train, later = _nine_link_three_cycles()
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", IllConditionedBinWarning)
        with pytest.warns(PoorHeldOutSkillWarning, match="the connection alone"):
            est = ConnectionEstimator(phaser=Phaser(min_cycles=2.5)).fit(train)
        given = est.regression_.replace(n_bins=48, fourier_order=12).fit(
            est.trajectory_, est.limit_cycle_)
    choice = est.complexity_
    assert choice.checked and choice.connection_regressed
    assert not bool(est.held_out_skill_.unscored.any())
    assert est.model_.meta["connection_regressed"] is True
    fallback = choice.phase_average_mask("cpu")
    s = est.score(later)
    assert torch.equal(s.r2[fallback], s.r2_phase_average[fallback])
    assert bool((s.r2[~fallback] > s.r2_phase_average[~fallback]).all())
    assert bool((~fallback).any())
    # the phase average is of the chosen order, not the given 48-bin fit's 12
    assert choice.fourier_order < 12
    assert bool((est.phase_average_.coeffs[..., 2 * choice.fourier_order + 1:, :] == 0).all())

    def error(model):  # relative RMS of Â against the swimmer's along the fitted cycle
        phi = torch.linspace(0, 2 * math.pi, 201, dtype=F64)[:-1].expand(1, 200)
        true = NLinkSwimmer(9).connection(model.gamma_at(phi))
        return float((model.connection(phi) - true).square().sum().sqrt()
                     / true.square().sum().sqrt())

    assert error(est.model_) < 0.75 * error(given)


def test_a_short_recording_no_check_can_score_predicts_the_phase_average(monkeypatch):
    """Where not even the connection alone can be scored (made so here), the given
    complexity's fit stands unchecked; on so few cycles it predicts the phase average (before
    it did: R² -0.58 / 0.34 / 0.75 on the next 4 cycles against the phase average's 0.54 /
    0.84 / 0.96)."""
    from torchconn import Phaser

    def unscored(*args, **kw):
        raise ValueError("select_connection_alone: no candidate could be fitted")

    monkeypatch.setattr(selection, "select_connection_alone", unscored)
    train, later = _nine_link_three_cycles()
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", IllConditionedBinWarning)
        with pytest.warns(PoorHeldOutSkillWarning, match="cannot be checked"):
            est = ConnectionEstimator(phaser=Phaser(min_cycles=2.5)).fit(train)
    choice = est.complexity_
    assert not choice.checked and choice.scores == ()
    assert choice.phase_averaged == ((True, True, True),)
    assert bool(est.held_out_skill_.unscored.all())
    assert bool((est.forecast_model_.A.coeffs == 0).all())
    # the connection is the given complexity's fit, unchecked (no ridge was chosen)
    _same_series_and_bins(est.model_, est.regression_.fit(est.trajectory_, est.limit_cycle_))
    assert est.model_.meta["forecast_model"]["A_ridge"] == 0.0
    s = est.score(later)
    assert torch.equal(s.r2, s.r2_phase_average)
    assert bool((s.r2_phase_average > 0.5).all())


def test_warning_names_each_loss_with_both_scores_from_the_same_trial():
    # v_x loses only in trial 1 (0.95 vs 0.97), but the lowest model R² over trials (0.90,
    # trial 0) is below the lowest phase average (0.92, trial 0): per-column minima would
    # read as a win. ω loses in both trials, most in trial 0. v_y never loses.
    r2 = torch.tensor([[0.90, 0.80, 0.50], [0.95, 0.85, 0.60]], dtype=F64)
    base = torch.tensor([[0.88, 0.70, 0.70], [0.97, 0.75, 0.62]], dtype=F64)
    s = skill.Skill(r2=r2, r2_phase_average=base, r2_template=base,
                    n_samples=torch.tensor([100.0, 100.0], dtype=F64))
    with pytest.warns(PoorHeldOutSkillWarning) as record:
        complexity.warn_if_poor(s)
    message = str(record[0].message)
    assert "v_x (held-out R² 0.950 vs phase average 0.970 in trial 1)" in message
    assert "omega (held-out R² 0.500 vs phase average 0.700 in trial 0)" in message
    assert "v_y" not in message
    # one trial: no index; a 2-D batch: the index is the batch's
    one = skill.Skill(r2=r2[1], r2_phase_average=base[1], r2_template=base[1],
                      n_samples=torch.tensor(100.0, dtype=F64))
    with pytest.warns(PoorHeldOutSkillWarning, match=r"v_x \(held-out R² 0.950 vs phase "
                      r"average 0.970\), omega"):
        complexity.warn_if_poor(one)
    grid = skill.Skill(r2=r2.reshape(1, 2, 3), r2_phase_average=base.reshape(1, 2, 3),
                       r2_template=base.reshape(1, 2, 3),
                       n_samples=torch.full((1, 2), 100.0, dtype=F64))
    with pytest.warns(PoorHeldOutSkillWarning, match=r"in trial \(0, 1\)"):
        complexity.warn_if_poor(grid)
    # a loss smaller than the third decimal is printed with the digits that show it
    close = skill.Skill(r2=torch.tensor([0.99212, 0.5, 0.5], dtype=F64),
                        r2_phase_average=torch.tensor([0.99238, 0.4, 0.4], dtype=F64),
                        r2_template=base[0], n_samples=torch.tensor(100.0, dtype=F64))
    with pytest.warns(PoorHeldOutSkillWarning, match=r"v_x \(held-out R² 0.9921 vs phase "
                      r"average 0.9924\)"):
        complexity.warn_if_poor(close)


def test_an_unchecked_fit_on_many_cycles_advises_more_data_not_the_search_it_ran(monkeypatch):
    """5-link wave, 10 cycles at 10 samples per cycle (a tracked zebrafish at 50 fps): no
    candidate can be fitted without a third of the cycles; where the connection alone cannot
    be scored either (made so here: on this recording it can,
    ``tests/test_connection_alone.py``), complexity='auto' keeps the given fit unchecked (10
    cycles are not few); the warning used to advise complexity='cv', the search that had
    just failed."""
    def unscored(*args, **kw):
        raise ValueError("select_connection_alone: no candidate could be fitted")

    monkeypatch.setattr(selection, "select_connection_alone", unscored)
    seeds = np.array([1000])
    clean = simulate(NLinkSwimmer(5), wave_gait(), eta=0.025, n_cycles=10, samples_per_cycle=10,
                     seeds=seeds)
    traj = observe(clean, 0.005, seeds=seeds).with_fields(power=None)
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        est = ConnectionEstimator().fit(traj)
    assert est.complexity_ is None and bool(est.held_out_skill_.unscored.all())
    poor = [str(w.message) for w in caught if issubclass(w.category, PoorHeldOutSkillWarning)]
    assert len(poor) == 1 and "cannot be fitted when one block" in poor[0]
    assert "more samples per cycle" in poor[0] and "complexity='cv'" not in poor[0]
    with pytest.raises(ValueError, match="no candidate could be fitted"):
        ConnectionEstimator(complexity="cv").fit(traj)


def test_components_neither_model_predicts_are_named():
    # v_y: the model (−0.4) is worse than a phase average that has no skill either (−0.1), so
    # worse_than_phase_average does not count it; ω: both above 0. v_x: both ≤ 0, the model
    # better. Both are "without skill" and warned of, with the trial where the model is worst.
    r2 = torch.tensor([[-0.05, -0.40, 0.9], [-0.20, -0.30, 0.8]], dtype=F64)
    base = torch.tensor([[-0.10, -0.10, 0.5], [-0.30, -0.20, 0.5]], dtype=F64)
    s = skill.Skill(r2=r2, r2_phase_average=base, r2_template=base,
                    n_samples=torch.tensor([100.0, 100.0], dtype=F64))
    assert not bool(s.worse_than_phase_average.any())
    assert s.without_skill.any(0).tolist() == [True, True, False]
    with pytest.warns(PoorHeldOutSkillWarning) as record:
        complexity.warn_if_poor(s)
    assert len(record) == 1
    message = str(record[0].message)
    assert message.startswith("neither the model nor the phase-averaged velocity")
    assert "v_x (held-out R² -0.200, phase average -0.300 in trial 1)" in message
    assert "v_y (held-out R² -0.400, phase average -0.100 in trial 0)" in message
    assert "omega" not in message
    # a model with skill, or one whose baseline has it, is not "without skill"
    fine = skill.Skill(r2=r2.abs(), r2_phase_average=base, r2_template=base,
                       n_samples=torch.tensor([100.0, 100.0], dtype=F64))
    with warnings.catch_warnings():
        warnings.simplefilter("error", PoorHeldOutSkillWarning)
        complexity.warn_if_poor(fine)
    # a component that fell back to the phase average ties it exactly: 3 decimals, not 6
    tied = skill.Skill(r2=torch.tensor([-0.114239, 0.8, 0.9], dtype=F64),
                       r2_phase_average=torch.tensor([-0.114239, 0.7, 0.8], dtype=F64),
                       r2_template=base[0], n_samples=torch.tensor(100.0, dtype=F64))
    with pytest.warns(PoorHeldOutSkillWarning, match=r"v_x \(held-out R² -0.114, phase "
                      r"average -0.114\)"):
        complexity.warn_if_poor(tied)
