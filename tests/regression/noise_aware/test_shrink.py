"""Shrinkage: the blend of the corrected and smoothed fits, the harmonic noise of the bins and
the shrunk series."""

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
    TiedMetric,
    TubeRegression,
    observe,
    simulate,
)
from torchconn.physics.gaits import FourierGait
from torchconn.regression.binning import assign_bins

from ..common import (
    DT_SAMPLES,
    a_error_and_scale,
    deliver_corrected_alone,
    fit_pooled,
    noisy_circle_trials,
    unpooled_trials,
)

F64 = torch.float64


def _fit_fields(a, se, m=8):
    """A ConnectionFit with every block equal to ``a`` and standard errors ``se`` (one batch
    element, ``m`` bins, d = 2)."""
    from torchconn.regression.connection import ConnectionFit

    shapes = {"c": (1, m, 3), "b": (1, m, 3, 2), "A": (1, m, 3, 2), "dA": (1, m, 3, 2, 2)}
    vals = {k: torch.full(s, float(a), dtype=F64) for k, s in shapes.items()}
    ses = {"se_" + k: torch.full(s, float(se), dtype=F64) for k, s in shapes.items()}
    n = torch.full((1, m), 100)
    z = torch.zeros(1, m, dtype=F64)
    return ConnectionFit(**vals, **ses, n_samples=n, residual_rms=torch.zeros(1, m, 3,
                         dtype=F64), condition=z, ridge=z, coef=z, se_coef=z)


def test_blend_keeps_a_clear_correction_and_drops_one_within_its_noise():
    from torchconn.regression.noise_aware import blend_fits

    smoothed = _fit_fields(1.0, 0.01)

    def blend_fits(smoothed, corrected, _blend=blend_fits):
        return _blend(smoothed, corrected, variance_factor=2.0)

    # differs by 1 with standard errors 0.01: w = 1 - 2 * 0.01² / 1² per entry
    fit, w = blend_fits(smoothed, _fit_fields(2.0, 0.01))
    assert torch.allclose(w, torch.full((1, 4), 1 - 2e-4, dtype=F64))
    assert torch.allclose(fit.A, torch.full_like(fit.A, 2 - 2e-4))
    # differs by 0.5 with standard errors 1: within the noise, the smoothed estimate stays
    fit, w = blend_fits(smoothed, _fit_fields(1.5, 1.0))
    assert bool((w == 0).all()) and torch.equal(fit.dA, smoothed.dA)
    # in between: w = 1 - 2 V / D² = 1 - 2 * 0.25 / 1 = 0.5
    fit, w = blend_fits(smoothed, _fit_fields(2.0, 0.5))
    assert torch.allclose(w, torch.full((1, 4), 0.5, dtype=F64))
    assert torch.allclose(fit.b, torch.full_like(fit.b, 1.5))


@pytest.mark.parametrize("m, tolerance", [(8, 0.06), (64, 0.015)])
def test_blend_bands_cover_the_shrink_against_a_monte_carlo(m, tolerance):
    """The tie's bands of the shrunk estimate (blend_fits' cov_b_dA) against a Monte Carlo
    of the combination's errors: the corrected estimate unbiased with standard errors 1, the
    smoothed one without noise but attenuated (its bias 1.4 per entry, so D² ≈ 3 V and
    w ≈ 0.5). The combination's squared error is (1 − w)² a² + w² V for a fixed w; the bands
    with the shift allowed for have that expectation (their shift term estimates
    (1 − w)² a² from D² − V), the interpolated ones only w² V, a third of it. ``w`` is
    estimated from the block it shrinks, which the bands do not model: over 8 bins (120
    entries of b̂ and ∂Â/∂r) they came out 3.7 % narrow, over 64 bins 0.6 %."""
    from torchconn.regression.noise_aware import blend_fits
    from torchconn.regression.noise_aware.shrink import rescaled_covariance

    gen = torch.Generator().manual_seed(0)
    k, bias = 4000 if m == 8 else 1000, 1.4

    def batch(fit):  # the fit repeated over k elements
        return dataclasses.replace(fit, **{f.name: getattr(fit, f.name).expand(
            (k,) + getattr(fit, f.name).shape[1:]).clone() for f in dataclasses.fields(fit)
            if isinstance(getattr(fit, f.name), torch.Tensor)})

    corrected = batch(_fit_fields(0.0, 1.0, m))  # the truth is 0
    noise = {name: torch.randn(getattr(corrected, name).shape, generator=gen, dtype=F64)
             for name in ("c", "b", "A", "dA")}
    n_cov = 2 + 4  # b̂ and ∂Â/∂r of one row, d = 2
    cov = torch.eye(n_cov, dtype=F64).expand(corrected.b.shape[:-1] + (n_cov, n_cov))
    corrected = dataclasses.replace(corrected, **noise, cov_b_dA=cov.clone())
    smoothed = batch(_fit_fields(bias, 0.0, m))
    fit, w = blend_fits(smoothed, corrected)
    assert 0.4 < float(w[:, 3].mean()) < 0.6
    e = torch.cat([fit.b.flatten(-2), fit.dA.flatten(-3)], -1).square().sum((1, 2))  # (k,)
    # the bands with the shift, and the interpolated ones (the covariance rescaled only)
    interpolated = rescaled_covariance(corrected.cov_b_dA, (corrected.se_b, corrected.se_dA),
                                       (fit.se_b, fit.se_dA))
    found = {}
    for name, cov in (("shift", fit.cov_b_dA), ("interpolated", interpolated)):
        v = cov.diagonal(dim1=-2, dim2=-1).sum((1, 2, 3))
        ratio = float(e.sum() / v.sum())  # E[e²] / E[se²], and its sampling error
        found[name] = (ratio, float((e - ratio * v).std() / (math.sqrt(k) * v.mean())))
    ratio, se = found["shift"]
    assert abs(ratio - 1) < tolerance + 3 * se, found
    assert found["interpolated"][0] > 2.5, found


def test_shrinkage_falls_back_to_the_smoothed_fit_with_one_9_link_trial():
    # the low-information regime of the paper's Fig. 4B: one 9-link trial (81 regressors per
    # bin), much motion-capture noise; the correction alone is far off, the blend falls back
    seeds = np.array([31, 32])
    from torchconn.physics.gaits import reference_gait

    traj = observe(simulate(NLinkSwimmer(9), reference_gait("9link"), eta=0.025, n_cycles=30,
                            samples_per_cycle=64, seeds=seeds), 0.02, seeds=seeds)
    phi = torch.linspace(0, 2 * math.pi, 101, dtype=F64)[:-1].expand(2, 100)

    def error(regression):
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            # the sweep's setting: fixed complexity (48 bins, order 12), no held-out check
            model = ConnectionEstimator(regression=regression, complexity="fixed",
                                        metric=TiedMetric(enabled=False),
                                        held_out_folds=0).fit(traj).model_
        a_true = NLinkSwimmer(9).connection(model.gamma_at(phi))
        err = (model.connection(phi) - a_true).square().sum((-3, -2, -1)).sqrt()
        return err / a_true.square().sum((-3, -2, -1)).sqrt(), model

    smoothed, _ = error(TubeRegression())
    blended, model = error(NoiseAwareRegression())
    with pytest.MonkeyPatch.context() as mp:
        deliver_corrected_alone(mp)
        alone, _ = error(NoiseAwareRegression())
    assert bool((alone > 1.5 * smoothed).all())  # the failure the fallback exists for
    assert bool((blended <= 1.02 * smoothed).all()), (blended, smoothed)
    assert np.array(model.meta["corrected_weight"]).shape == (2, 4)


@pytest.mark.parametrize("window", [1.0, 1.3, 3.0])
def test_harmonic_noise_of_overlapping_bins_matches_monte_carlo(window):
    # The bias correction keeps a harmonic of Â only where it stands out of the bins' noise;
    # that noise comes from the standard errors and the overlap of neighbouring windows. Bins
    # of pure white noise (weighted means, standard errors exact): the mean power of every
    # harmonic over 200 records matches the predicted noise (ignoring the overlap would
    # under-predict the low harmonics several-fold at 3 spacings). A width that is not a
    # whole number of half spacings (the data-size rule's, on short pooled recordings) raised
    # a RuntimeError here before.
    from torchconn.phase.fourier import fit_fourier
    from torchconn.regression.noise_aware.shrink import harmonic_noise

    gen = torch.Generator().manual_seed(3)
    n_rec, n, m = 200, 3000, 48
    phase = torch.rand(n_rec, n, generator=gen, dtype=F64) * 2 * math.pi
    values = torch.randn(n_rec, n, 6, generator=gen, dtype=F64)
    bins = assign_bins(phase, m, window=window, kernel="tricube")
    w = bins.weight.unsqueeze(-1)
    est = ((w * bins.gather(values)).sum(-2) / w.sum(-2)).reshape(n_rec, m, 3, 2)
    se = (bins.weight.square().sum(-1).sqrt() / bins.weight.sum(-1))[..., None, None]
    centres = torch.arange(m, dtype=F64) * 2 * math.pi / m
    power, noise = harmonic_noise(fit_fourier(centres, est, 6, value_ndim=2),
                                   se.expand(est.shape), bins.window, bins.kernel)
    ratio = power.mean(0) / noise.mean(0)
    assert ((ratio > 0.85) & (ratio < 1.15)).all(), ratio


def test_a_pooled_fits_series_shrinks_the_harmonics_near_the_bins_noise(clean30):
    # Under noise the bins' errors of Â are mostly variance, and the high harmonics of its
    # order-12 series carry more of it than of the connection: shrinking each harmonic by how
    # far its power stands out of its noise expectation must bring Â closer to the exact
    # connection than the plain order-12 least-squares series of the same bins.
    from types import SimpleNamespace

    from torchconn.phase.fourier import fit_fourier

    traj = noisy_circle_trials(0.005, clean=clean30)
    on = fit_pooled(traj)
    plain = fit_fourier(on.model_.bins.phase, on.model_.bins.A, 12, value_ndim=2)
    off = SimpleNamespace(model_=dataclasses.replace(on.model_, A=plain))
    factors = torch.tensor(on.model_.meta["A_harmonic_factors"])  # (harmonic, row)
    assert factors.shape == (13, 3) and bool((factors[0] == 1).all()), factors
    assert float(factors.min()) < 0.5, factors
    assert a_error_and_scale(on)[0] < a_error_and_scale(off)[0], (a_error_and_scale(on),
                                                                  a_error_and_scale(off))


def test_a_pooled_shrink_per_row_keeps_the_9_links_displacement():
    """The 9-link on a travelling wave (pooled 4 x 30 cycles, ω = 0.005, seed 5002 of the
    README's held-out set): one shrink factor per harmonic, from its power summed over all
    24 entries of Â (the previous version, computed here from the plain series), shrinks the
    fundamental that carries the gait's displacement and doubles the model's one-cycle
    displacement error against the swimmer's (`physics.gaits.evaluate`: 22 % against 6 %
    plain); a factor per row of Â (x, y, θ; the default) brings Â closer to the exact
    connection than that (7.8 % against 8.3 %, plain 9.1 %) and the displacement too
    (10 %)."""
    from torchconn.phase.fourier import fit_fourier
    from torchconn.physics.gaits import evaluate
    from torchconn.regression.noise_aware.shrink import _SERIES_SHRINK, harmonic_noise

    coeffs = torch.zeros(3, 8, dtype=F64)  # benchmarks/accuracy.py's circle gait, 9-link
    lag = 2 * math.pi * torch.arange(8, dtype=F64) / 8
    coeffs[1], coeffs[2] = 0.9 * torch.cos(lag), 0.9 * torch.sin(lag)
    gait, seeds = FourierGait(coeffs), np.arange(4) + 1000 * 5002
    clean = simulate(NLinkSwimmer(9), gait, eta=0.025, n_cycles=30, samples_per_cycle=DT_SAMPLES,
                     seeds=seeds)
    est = fit_pooled(observe(clean, 0.005, seeds=seeds))
    model = est.model_
    assert torch.tensor(model.meta["A_harmonic_factors"]).shape == (13, 3)
    plain = fit_fourier(model.bins.phase, model.bins.A, 12, value_ndim=2)
    power, noise = harmonic_noise(plain, model.bins.A_se, model.meta["window"],
                                   est.regression_.kernel)  # (13,): summed over the entries
    factor = (1 - _SERIES_SHRINK * noise / power).clamp(0, 1)
    factor[0] = 1
    per_harmonic = dataclasses.replace(plain, coeffs=plain.coeffs * torch.cat(
        [factor[:1], factor[1:].repeat_interleave(2)])[:, None, None])
    true = evaluate(NLinkSwimmer(9), gait).displacement[:2]
    phi = torch.linspace(0, 2 * math.pi, 201, dtype=F64)[:-1]
    a_true = NLinkSwimmer(9).connection(model.gamma_at(phi))

    def errors(series):
        m = dataclasses.replace(model, A=series)
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            d = m.evaluate_gait(gait, n_draws=0).displacement[:2]
        return (float((series(phi) - a_true).norm() / a_true.norm()),
                float((d - true).norm() / true.norm()))

    (a_row, d_row), (a_harm, d_harm), (a_plain, d_plain) = (
        errors(x) for x in (model.A, per_harmonic, plain))
    assert a_row < a_harm < a_plain, (a_row, a_harm, a_plain)
    assert d_harm > 1.5 * d_plain and d_row < 0.7 * d_harm, (d_row, d_harm, d_plain)


def test_a_shrunk_series_gets_its_offsets_refitted_and_nothing_else_moves(clean30):
    """Where Â's series is shrunk in a pooled fit, ĉ and b̂ are re-estimated to it (the bins'
    least squares, test above): their series are no longer the plain series of the bins,
    which keep their estimates. Unpooled fits shrink nothing and refit nothing."""
    from torchconn.phase.fourier import fit_fourier

    traj = noisy_circle_trials(0.005, clean=clean30)
    a = fit_pooled(traj).model_
    assert a.meta["offsets_refit"] is True
    plain_b = fit_fourier(a.bins.phase, a.bins.b, 12, value_ndim=2)
    assert not torch.equal(a.b.coeffs, plain_b.coeffs)
    prep, cycle = unpooled_trials([0.005, 0.01])
    unpooled = NoiseAwareRegression().fit(prep, cycle)
    assert "offsets_refit" not in unpooled.meta
    assert torch.equal(unpooled.b.coeffs,
                       fit_fourier(unpooled.bins.phase, unpooled.bins.b, 12, value_ndim=2).coeffs)
