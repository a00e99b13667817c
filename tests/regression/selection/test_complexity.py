"""Recordings at video rates whose full model no held-out check can score: the connection
alone ``c + Âδ̇`` is scored instead (``complexity.select_connection_alone``)."""

import math
import warnings

import numpy as np
import pytest
import torch

from torchconn import ConnectionEstimator, NLinkSwimmer, Phaser, observe, simulate
from torchconn.regression import (
    IllConditionedBinWarning,
    TubeRegression,
    assign_bins,
    selection,
)
from torchconn.regression.selection import PoorHeldOutSkillWarning, complexity, skill

from ...recordings import wave_gait

F64 = torch.float64
SPC = 10  # samples per cycle: 50 fps video of a 5 Hz tail beat


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
        return ConnectionEstimator(phaser=Phaser(min_cycles=2.5), **kw).fit(train)


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
                                    ConnectionEstimator().regression, pool=False)
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
                                          ConnectionEstimator().regression, pool=False)
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
            ConnectionEstimator(phaser=Phaser(min_cycles=2.5)).fit(train)


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
            est = ConnectionEstimator(pool=True).set_params(metric__enabled=False).fit(tr)
            assert est.held_out_skill_ is not None
            assert bool(torch.isfinite(est.held_out_skill_.r2).all())
