"""Recordings at video rates whose full model no held-out check can score: the connection
alone ``c + Âδ̇`` is scored instead (``complexity.select_connection_alone``).

The estimators here have no physics prior (``prior=None``): these simulations are of the
prior's own reference family, so it would take over the forecasts these tests examine
(``tests/regression/selection/test_prior.py`` tests it)."""

import math
import warnings

import numpy as np
import pytest
import torch

from torchconn import (
    ConnectionEstimator,
    NLinkSwimmer,
    NoiseAwareRegression,
    Phaser,
    TiedMetric,
    observe,
    simulate,
)
from torchconn.cycles import few_cycles
from torchconn.regression import (
    IllConditionedBinWarning,
    LocalConnectionModel,
    TubeRegression,
    assign_bins,
    selection,
)
from torchconn.regression.selection import (
    COMPLEXITY_GRID,
    RIDGE_GRID,
    PoorHeldOutSkillWarning,
    complexity,
    skill,
)

from ...recordings import wave_gait
from ..common import (
    DT_SAMPLES,
    assert_same_model,
    assert_same_series_and_bins,
    nine_link_three_cycles,
    wave_recording,
)

F64 = torch.float64
SPC = 10  # samples per cycle: 50 fps video of a 5 Hz tail beat


def _estimator(**kw) -> ConnectionEstimator:
    """The default estimator without the physics prior (see the module's docstring)."""
    return ConnectionEstimator(prior=None, **kw)


def _recording(n_cycles: int, seed: int, spc: int = SPC):
    """One 5-link trial, ω = 0.005, the simulator's fine step as at 126 samples per cycle."""
    seeds = np.array([seed])
    clean = simulate(NLinkSwimmer(5), wave_gait(), eta=0.025, n_cycles=n_cycles,
                     samples_per_cycle=spc, substeps=2 * math.ceil(504 / spc), seeds=seeds)
    return observe(clean, 0.005, seeds=seeds).with_fields(power=None)


def _fit(train, **kw):
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", IllConditionedBinWarning)
        warnings.simplefilter("ignore", PoorHeldOutSkillWarning)
        return _estimator(phaser=Phaser(min_cycles=2.5), **kw).fit(train)


@pytest.fixture(scope="module")
def video():
    """8 cycles at 10 samples per cycle fitted, the next 6 kept: no (bins, order) of the grid
    can be fitted without a third of the cycles (25 regressors per bin)."""
    traj = _recording(14, seed=10)
    cut = 8 * SPC + 1
    train, later = traj.slice_time(0, cut), traj.slice_time(cut, traj.n_samples)
    return train, later, _fit(train)


def test_a_video_rate_recording_no_full_model_can_score_is_checked_by_the_connection_alone(
        video):
    train, later, est = video
    # no full model of the grid can be scored: the check could not run before
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", IllConditionedBinWarning)
        with pytest.raises(ValueError, match="no candidate could be fitted"):
            complexity.select_complexity(est.trajectory_, est.limit_cycle_,
                                    _estimator().regression, pool=False)
    choice = est.complexity_
    assert choice.checked and choice.connection_regressed
    # chosen by held-out error among the grid's bins and orders
    assert [row[:2] for row in choice.scores] == [k for k in complexity.COMPLEXITY_GRID]
    best = min(choice.scores, key=lambda row: row[3])
    assert (choice.n_bins, choice.fourier_order) == best[:2]
    assert (est.regression_.n_bins, est.regression_.fourier_order) == best[:2]
    held = est.held_out_skill_
    assert not bool(held.unscored.any())
    fallback = choice.phase_average_mask("cpu")
    alone = choice.connection_only_mask("cpu")
    assert torch.equal(fallback, ~alone)
    # the phase-averaged components tie it held out; the others beat it
    assert torch.equal(held.r2[fallback], held.r2_phase_average[fallback])
    assert bool((held.r2[alone] > held.r2_phase_average[alone]).all())
    assert bool(alone.any())  # on this recording the connection predicts something
    # the same data give the same choice
    again = complexity.select_connection_alone(est.trajectory_, est.limit_cycle_,
                                          _estimator().regression, pool=False)
    assert again.choice == choice
    # forecasts: c + Âδ̇ or the phase average, never b̂ or ∂Â/∂r
    forecast = est.forecast_model_
    assert bool((forecast.b.coeffs == 0).all()) and bool((forecast.dA.coeffs == 0).all())
    # the connection delivered is the connection alone, its offsets not estimated
    model = est.model_
    assert model.meta["connection_regressed"] is True
    assert bool((model.dA.coeffs == 0).all()) and bool(model.bins.A_se.isnan().all())
    torch.testing.assert_close(model.A.coeffs[..., alone[0], :],
                               forecast.A.coeffs[..., alone[0], :], rtol=0, atol=0)
    s = est.score(later)
    assert torch.equal(s.r2[fallback], s.r2_phase_average[fallback])


def test_the_check_warns_what_the_connection_alone_predicts(video):
    train = video[0]
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", IllConditionedBinWarning)
        with pytest.warns(PoorHeldOutSkillWarning, match="the connection alone"):
            _estimator(phaser=Phaser(min_cycles=2.5)).fit(train)


def _a_error(model) -> float:
    """Relative RMS of ``Â`` against the swimmer's exact connection along the fitted cycle."""
    phi = torch.linspace(0, 2 * math.pi, 201, dtype=F64)[:-1].expand(1, 200)
    true = NLinkSwimmer(5).connection(model.gamma_at(phi))
    return float((model.connection(phi) - true).square().sum().sqrt()
                 / true.square().sum().sqrt())


def test_a_short_video_rate_recording_the_given_fit_refuses_is_fitted_by_the_connection_alone():
    """5 cycles at 12 samples per cycle (seed 62): the given 48-bin fit cannot be fitted at
    all and no candidate of the grid without a third of the cycles, so the fit used to be
    refused. The connection alone can be scored, and is the model: checked held out, its
    phase-averaged components tie the phase average on the next 4 cycles, and its ``Â`` is
    within 45 % of the swimmer's (the benchmark's 12-per-cycle recordings: 21-48 %)."""
    traj = _recording(9, seed=62, spc=12)
    cut = 5 * 12 + 1
    train, later = traj.slice_time(0, cut), traj.slice_time(cut, traj.n_samples)
    with pytest.raises(ValueError, match="cannot be fitted"):
        _fit(train, complexity="fixed")
    est = _fit(train)
    choice = est.complexity_
    assert choice.checked and choice.connection_regressed
    assert not bool(est.held_out_skill_.unscored.any())
    assert est.model_.meta["connection_regressed"] is True
    assert bool((est.model_.dA.coeffs == 0).all())
    fallback = choice.phase_average_mask("cpu")
    s = est.score(later)
    assert torch.equal(s.r2[fallback], s.r2_phase_average[fallback])
    assert _a_error(est.model_) < 0.45


def test_a_recording_too_short_for_the_connection_alone_says_what_it_needs():
    """5 cycles at 10 samples per cycle: neither the full model nor the connection alone can
    be checked; the error gives the cycles each needs."""
    with pytest.raises(ValueError, match=r"4\.9 cycles per trial at 10 samples per cycle.*"
                       r"the connection alone \(5 regressors per bin\), tried in its place, "
                       r"needs 4\.1, and 6\.2 to be checked"):
        _fit(_recording(5, seed=62))


@pytest.mark.parametrize("n_cycles, spc", [(14, 10), (6, 16), (4, 126)])
def test_recordings_a_grid_candidate_can_score_or_of_few_cycles_are_unchanged(
        monkeypatch, n_cycles, spc):
    """Where a candidate of the grid can be scored (14 cycles at 10 per cycle, 6 at 16, 4 at
    126), the connection alone is never regressed: the code path that changed is not taken,
    so those fits are as they were."""
    def refused(*args, **kw):
        raise AssertionError("select_connection_alone called")

    monkeypatch.setattr(selection, "select_connection_alone", refused)
    traj = _recording(n_cycles, seed=11, spc=spc)
    est = _fit(traj)
    assert est.complexity_ is None or not est.complexity_.connection_regressed
    assert "connection_regressed" not in est.model_.meta


def test_the_connection_alone_fit_is_the_weighted_least_squares_of_c_and_a(video):
    """Independently: with the smoothed regression (no noise correction, no blend), the whole
    recording's per-bin coefficients of the connection alone are the kernel-weighted least
    squares of ξ on ``[1, δ̇]`` in each bin (numpy)."""
    est = video[2]
    traj, cycle = est.trajectory_, est.limit_cycle_
    reg = TubeRegression()
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", IllConditionedBinWarning)
        alone = complexity.select_connection_alone(traj, cycle, reg, pool=False)
    model = alone.model
    m = alone.regression.n_bins
    window = skill._fold_windows(alone.regression, model.meta, traj.phase,
                                 torch.ones_like(traj.phase, dtype=torch.long), 4)
    bins = assign_bins(traj.phase, m, window=window, kernel=reg.kernel)
    sm = traj.smoothed
    d = 4
    for k in range(m):
        idx, w = bins.index[0, k], bins.weight[0, k]
        keep = w > 0
        idx, w = idx[keep], w[keep].numpy()
        delta_dot = sm.r_dot[0, idx] - model.bins.gamma_dot[0, k]
        x = np.concatenate([np.ones((len(idx), 1)), delta_dot.numpy()], 1)
        sw = np.sqrt(w)[:, None]
        coef = np.linalg.lstsq(x * sw, sm.xi[0, idx].numpy() * sw, rcond=None)[0]
        got = alone.coef[0, k]
        torch.testing.assert_close(got[0], torch.from_numpy(coef[0]), rtol=1e-8, atol=1e-10)
        torch.testing.assert_close(got[1 + d:1 + 2 * d], torch.from_numpy(coef[1:]),
                                   rtol=1e-8, atol=1e-10)
        assert bool((got[1:1 + d] == 0).all()) and bool((got[1 + 2 * d:] == 0).all())


def test_cross_validate_repeats_the_check_the_fit_ran(video):
    """``cross_validate()`` after the fit regresses the connection alone in each fold, as the
    fit's check did: the same held-out skill, and no unscored bins."""
    est = video[2]
    again = est.cross_validate()
    torch.testing.assert_close(again.r2, est.held_out_skill_.r2, rtol=1e-10, atol=1e-12)
    torch.testing.assert_close(again.r2_phase_average, est.held_out_skill_.r2_phase_average,
                               rtol=1e-10, atol=1e-12)
    with pytest.raises(ValueError, match="connection_regressed"):
        skill.cross_validate(est.trajectory_, est.limit_cycle_, est.regression_, pool=False,
                             refit=True, connection_regressed=True)


def test_four_cycles_at_14_samples_per_cycle_are_checked_not_refused():
    # 2 of 3 blocks hold 24 samples, fewer than the 25 an order-12 phase average needs: the
    # held-out baseline takes the order they determine (this raised in fit_fourier before)
    from torchconn.physics.gaits import reference_gait

    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        for seed in (1, 3):
            tr = observe(simulate(NLinkSwimmer(3), reference_gait("3link"), eta=0.025,
                                  n_cycles=4, samples_per_cycle=14, seeds=[seed]), 0.002,
                         seeds=[seed])
            est = _estimator(pool=True).set_params(metric__enabled=False).fit(tr)
            assert est.held_out_skill_ is not None
            assert bool(torch.isfinite(est.held_out_skill_.r2).all())


def test_overfitting_a_short_recording_is_reported_and_complexity_from_cv_stops_it():
    # a short real-like recording: 5-link, 6 cycles, omega = 0.005; fit on 60 %, score the rest
    seeds = np.array([11])
    six = observe(simulate(NLinkSwimmer(5), wave_gait(), eta=0.025, n_cycles=6,
                           samples_per_cycle=DT_SAMPLES, seeds=seeds), 0.005, seeds=seeds)
    cut = int(0.6 * six.n_samples)
    train, test = six.slice_time(0, cut), six.slice_time(cut, six.n_samples)

    def estimator(complexity="fixed"):
        return _estimator(phaser=Phaser(min_cycles=2.0), complexity=complexity,
                                   metric=TiedMetric(enabled=False),
                                   regression=NoiseAwareRegression())

    with warnings.catch_warnings():
        warnings.simplefilter("ignore", IllConditionedBinWarning)
        with pytest.warns(PoorHeldOutSkillWarning, match="worse than their phase-averaged"):
            fixed = estimator().fit(train)  # the fit's own held-out check
        with pytest.warns(PoorHeldOutSkillWarning, match="worse than their phase-averaged"):
            fixed.check_held_out(3)
        cv = estimator().select_complexity(train)
        again = estimator().select_complexity(train)
        auto = estimator("auto").fit(train)  # the default: chosen because fixed loses
    assert cv.complexity_ == again.complexity_ == auto.complexity_  # no randomness
    assert len(cv.complexity_.scores) == len(COMPLEXITY_GRID) * len(RIDGE_GRID)
    s_fixed, s_cv = fixed.score(test), cv.score(test)
    assert bool((s_cv.r2 > s_fixed.r2).all())
    # the chosen model is no worse than the phase-averaged velocity on the later cycles
    assert bool((s_cv.r2 > s_cv.r2_phase_average - 0.01).all())


F64 = torch.float64


def test_the_fit_warns_by_itself_and_auto_complexity_stops_the_overfit(short):
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", IllConditionedBinWarning)
        with pytest.warns(PoorHeldOutSkillWarning, match="worse than their phase-averaged"):
            fixed = _estimator(complexity="fixed").fit(short)
        assert bool(fixed.held_out_skill_.worse_than_phase_average.any())
        assert fixed.complexity_ is None
        warnings.simplefilter("error", PoorHeldOutSkillWarning)
        off = _estimator(complexity="fixed", held_out_folds=0).fit(short)  # no check
        assert off.held_out_skill_ is None
        warnings.simplefilter("ignore", PoorHeldOutSkillWarning)
        auto = _estimator().fit(short)
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
        est = _estimator(regression=reg, complexity="fixed").fit(short)
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


def test_the_template_stays_the_connection_s_where_a_component_falls_back(short_and_later):
    """v_y falls back to the phase average (SHORT_SEED): the forecasting model's ĉ is that
    average there, and the template column used to repeat it; it is Â(γ)γ̇ of the fit."""
    train, later = short_and_later
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        est = _estimator().fit(train)
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
        est = _estimator().fit(train)
    choice, reg = est.complexity_, est.regression_
    assert choice.ridge > 0 and reg.ridge == choice.ridge and reg.ridge_connection
    traj, cycle = est.trajectory_, est.limit_cycle_
    # the connection: the complexity chosen with Â unpenalised, fitted, nothing zeroed
    free, _ = complexity.select_complexity(traj, cycle, NoiseAwareRegression(ridge_connection=False),
                                      pool=False)
    direct = free.fit(traj, cycle, pool=False)
    assert_same_series_and_bins(est.model_, direct)
    assert bool((est.model_.A.coeffs[..., 1, :] != 0).any())  # v_y's row estimated
    assert est.model_.meta["settings"]["regression"]["ridge_connection"] is False
    assert est.model_.meta["forecast_model"] == {
        "n_bins": choice.n_bins, "fourier_order": choice.fourier_order,
        "A_ridge": choice.ridge, "phase_averaged": [[False, True, False]],
        "connection_only": [[True, False, True]], "prior_weight": None}
    # the forecasts: the penalised fit with the chosen rows zeroed, as before
    penalised = reg.fit(traj, cycle, pool=False)
    forecast = skill.with_phase_average(penalised, est.phase_average_,
                                        choice.phase_average_mask("cpu"),
                                        choice.connection_only_mask("cpu"))
    assert_same_series_and_bins(est.forecast_model_, forecast)
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
    assert_same_series_and_bins(loaded, est.model_)
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
        est = _estimator(complexity="fixed").fit(train)
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
    # a fit the caller has (the given complexity's, fitted raising on ill-conditioned bins)
    # serves as that candidate's whole-recording fit: the same choices, one fit fewer
    given = both[0].replace(n_bins=grid[-1], fourier_order=complexity.COMPLEXITY_GRID[-1][1])
    assert given.on_ill_conditioned == "raise"
    model = fit(given, traj, cycle, pool=False)
    fits.clear()
    reused = complexity.select_complexities(traj, cycle, both, pool=False,
                                            fitted=((given, model),))
    assert reused == alone
    assert sorted(fits) == sorted(grid[:-1])
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
    long = wave_recording(15, n_trials=2, seed=1).with_fields(power=None)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", IllConditionedBinWarning)
        warnings.simplefilter("error", PoorHeldOutSkillWarning)
        auto = _estimator(pool=True).fit(long)
        cv = _estimator(pool=True, complexity="cv").fit(long)
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
            assert_same_model(refit, stage.attach(chosen.fit(traj, cycle), stage.fit(traj, cycle)))
        calls.clear()
        _estimator(complexity="cv").fit(traj)
    assert len(calls) == 1  # one metric fit, whatever the candidates


def test_a_short_recording_no_full_model_can_score_is_checked_by_the_connection_alone():
    """The 3-cycle 9-link recording: the connection alone (1 + d regressors per bin) can be
    scored held out, so it is, as on longer video-rate recordings. Before, the given 48-bin
    fit stood unchecked, its forecasts the phase average everywhere and its connection 116 %
    off the swimmer's; now ω is predicted by the connection alone, which beats the phase
    average on the next 4 cycles too (0.996 vs 0.959), and the connection delivered is
    closer to the swimmer's than the unchecked fit's."""
    from torchconn import Phaser

    train, later = nine_link_three_cycles()
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", IllConditionedBinWarning)
        with pytest.warns(PoorHeldOutSkillWarning, match="the connection alone"):
            est = _estimator(phaser=Phaser(min_cycles=2.5)).fit(train)
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
    train, later = nine_link_three_cycles()
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", IllConditionedBinWarning)
        with pytest.warns(PoorHeldOutSkillWarning, match="cannot be checked"):
            est = _estimator(phaser=Phaser(min_cycles=2.5)).fit(train)
    choice = est.complexity_
    assert not choice.checked and choice.scores == ()
    assert choice.phase_averaged == ((True, True, True),)
    assert bool(est.held_out_skill_.unscored.all())
    assert bool((est.forecast_model_.A.coeffs == 0).all())
    # the connection is the given complexity's fit, unchecked (no ridge was chosen)
    assert_same_series_and_bins(est.model_, est.regression_.fit(est.trajectory_, est.limit_cycle_))
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
        est = _estimator().fit(traj)
    assert est.complexity_ is None and bool(est.held_out_skill_.unscored.all())
    poor = [str(w.message) for w in caught if issubclass(w.category, PoorHeldOutSkillWarning)]
    assert len(poor) == 1 and "cannot be fitted when one block" in poor[0]
    assert "more samples per cycle" in poor[0] and "complexity='cv'" not in poor[0]
    with pytest.raises(ValueError, match="no candidate could be fitted"):
        _estimator(complexity="cv").fit(traj)


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
