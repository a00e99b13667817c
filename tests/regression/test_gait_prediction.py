"""Gait prediction from a local model: exact on the affine toy, second order in the distance
from the recorded cycle, phase alignment, and the models drawn for its intervals."""

import dataclasses
import math
import warnings

import numpy as np
import pytest
import torch

from torchconn import AffineConnectionSystem, NLinkSwimmer
from torchconn.improve import (
    circle_gait,
    exact_local_model,
)
from torchconn.phase.fourier import fourier_design
from torchconn.physics.gaits import FourierGait, evaluate
from torchconn.regression.gait_prediction import ExcursionWarning, sample_models

from ..recordings import wobbled_gait


def test_affine_toy_prediction_is_exact():
    """First-order model of an affine connection is exact: predicted = true displacement."""
    system = AffineConnectionSystem.random(d=2, scale=0.3, seed=3)
    base = circle_gait(2, 0.6)
    model = exact_local_model(system, base, tube_rms=0.1, n_grid=64)
    near = wobbled_gait(base, 0.15)
    pred = model.evaluate_gait(near, phase_offset=0.0, n_draws=0, n_steps=256)
    true = evaluate(system, near, n_steps=256)
    torch.testing.assert_close(pred.displacement, true.displacement, atol=1e-6, rtol=0)
    # constant metric: the cost along the cycle is exact too
    torch.testing.assert_close(pred.cost, true.cost, atol=1e-6, rtol=0)


def test_prediction_error_is_second_order_in_distance():
    """On the swimmer the first-order model's error grows as distance² (log-log slope ≈ 2)."""
    system = NLinkSwimmer(3)
    base = circle_gait(2, 1.0)
    model = exact_local_model(system, base, tube_rms=0.1)
    eps = np.array([0.02, 0.04, 0.08, 0.16])
    err = []
    for e in eps:
        gait = wobbled_gait(base, float(e))
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", ExcursionWarning)
            pred = model.evaluate_gait(gait, phase_offset=0.0, n_draws=0)
        err.append(float(torch.linalg.vector_norm(pred.displacement - evaluate(system, gait)
                                                  .displacement)))
    slope = np.polyfit(np.log(eps), np.log(err), 1)[0]
    assert 1.8 < slope < 2.2, (slope, err)


def test_fitted_model_predicts_nearby_gait_within_its_interval(fitted_3link):
    system, _, model = fitted_3link
    base = FourierGait(model.gamma.coeffs)
    near = wobbled_gait(base, 0.1)
    pred = model.evaluate_gait(near, phase_offset=0.0, n_draws=64)
    true = evaluate(system, near).displacement
    # x within 4 standard errors plus 10 % (the estimator's bias on a small loop)
    assert abs(float(pred.displacement[0] - true[0])) < 4 * float(pred.displacement_se[0]) + \
        0.1 * abs(float(true[0]))
    assert 0 < float(pred.excursion) < 2
    assert pred.cost is None  # no power column: no metric


def test_alignment_recovers_a_phase_shift(fitted_3link):
    _, _, model = fitted_3link
    shift = 1.0
    base = FourierGait(model.gamma.coeffs)
    c = base.coeffs.clone()  # r(θ + shift): rotate each harmonic's (a_k, b_k)
    k = torch.arange(1, base.order + 1, dtype=torch.float64)[:, None]
    a, b = base.coeffs[1::2], base.coeffs[2::2]
    c[1::2] = a * torch.cos(k * shift) + b * torch.sin(k * shift)
    c[2::2] = b * torch.cos(k * shift) - a * torch.sin(k * shift)
    shifted = FourierGait(c)
    torch.testing.assert_close(shifted(torch.tensor([0.3])), base(torch.tensor([0.3 + shift])))
    a = model.evaluate_gait(base, phase_offset=0.0, n_draws=0)
    b = model.evaluate_gait(shifted, n_draws=0)
    assert abs(b.phase_offset - shift) < 2 * math.pi / 512
    # a phase shift of the same loop: same displacement, up to the start point's frame
    assert abs(float(a.excursion) - float(b.excursion)) < 0.05


def test_redrawn_models_spread_like_the_standard_errors(fitted_3link):
    _, _, model = fitted_3link
    # bin values refitted: the spread of A at a bin centre matches its standard error (drawn
    # from the sampling factor, whose diagonal it is) ...
    allowance = model.bins.A_bias_allowance  # a clean pooled fit: its bias allowance too
    assert model.bins.A_sampling_factor is not None and allowance is not None
    phi = model.bins.phase[:1]
    se = model.bins.A_se[0]
    bare = dataclasses.replace(model, bins=dataclasses.replace(model.bins,
                                                               A_bias_allowance=None))
    spread = sample_models(bare, 400, seed=1).connection(phi).std(0)[0]
    ratio = (spread / se).flatten()
    assert float(ratio.median()) == pytest.approx(1.0, abs=0.25)
    # ... and with the allowance, drawn whole beside it, √(se² + allowance²)
    spread = sample_models(model, 400, seed=1).connection(phi).std(0)[0]
    ratio = (spread / (se.square() + allowance[0].square()).sqrt()).flatten()
    assert float(ratio.median()) == pytest.approx(1.0, abs=0.25)


def test_jacobian_draws_take_the_ties_correlation_within_each_bin(fitted_3link):
    # bins.dA_correlation (tie_connection_derivative(correlation=True)) correlates the
    # entries of each bin's draw and leaves each entry's spread: with one correlation R and
    # one standard error per entry in every bin (the series' refit across bins then scales
    # every entry's covariance alike), the draws' correlation at a bin centre is R; without
    # it the draws are those of before, bit for bit.
    _, _, model = fitted_3link
    assert model.bins.dA_correlation is None  # off by default
    d = model.shape_dim
    gen = torch.Generator().manual_seed(3)
    root = torch.randn(d * d, d * d, generator=gen, dtype=torch.float64)
    cov = root @ root.T + 0.5 * torch.eye(d * d, dtype=torch.float64)
    sd = cov.diagonal().sqrt()
    corr = cov / (sd[:, None] * sd[None, :])
    se = torch.full_like(model.bins.dA_se, 1e-2)
    base = dataclasses.replace(model, bins=dataclasses.replace(model.bins, dA_se=se))
    with_corr = dataclasses.replace(base, bins=dataclasses.replace(
        base.bins, dA_correlation=corr.expand(se.shape[:-2] + corr.shape).clone()))
    phi = model.bins.phase[:1]
    drawn = sample_models(with_corr, 4000, seed=1).connection_jacobian(phi)[:, 0]
    err = (drawn - drawn.mean(0)).reshape(4000, 3, d * d)
    emp = torch.einsum("sre,srf->ref", err, err) / 4000
    emp_sd = emp.diagonal(dim1=-2, dim2=-1).sqrt()
    emp_corr = emp / (emp_sd[..., :, None] * emp_sd[..., None, :])
    torch.testing.assert_close(emp_corr, corr.expand(emp_corr.shape), atol=0.06, rtol=0)
    plain = sample_models(base, 400, seed=1).connection_jacobian(phi)
    before = sample_models(model, 400, seed=1)
    again = sample_models(dataclasses.replace(model, bins=dataclasses.replace(
        model.bins, dA_correlation=None)), 400, seed=1)
    assert torch.equal(before.dA.coeffs, again.dA.coeffs)
    assert not torch.allclose(plain, sample_models(with_corr, 400, seed=1)
                              .connection_jacobian(phi))


def test_metric_draws_share_the_bias_and_its_noise_across_entries_and_bins(tmp_path):
    """``sample_models`` draws ``M̂``'s bias allowance (``M_bias``) and that bias estimate's
    own noise (``M_change_factor``, ``F``) as errors shared by every entry and bin: the draws'
    covariance of ``M`` at the bins is ``b bᵀ + F Fᵀ`` (Monte Carlo, 4000 draws, within 5
    standard errors of each covariance entry). Drawing the same ``M_se`` entry by entry (no
    factor) is rejected by the same bound. Both survive a save and load."""
    system, d = NLinkSwimmer(3), 2
    model = exact_local_model(system, circle_gait(2, 0.5), n_grid=16)
    phase, n = model.bins.phase, 4000
    g = torch.Generator().manual_seed(3)

    def smooth(*shape):  # symmetric values of Fourier order 2 at the bins (the series' span)
        c = torch.randn((5, d, d) + shape, generator=g, dtype=torch.float64)
        c = 0.5 * (c + c.transpose(1, 2))
        return torch.einsum("mh,hij...->mij...", fourier_design(phase, 2), c) * 0.01

    bias, factor = smooth(), smooth(3)  # (M, d, d), (M, d, d, R = 3)
    se = (bias.square() + factor.square().sum(-1)).sqrt()
    bins = dataclasses.replace(model.bins, M_se=se, M_bias=bias, M_change_factor=factor)
    model = dataclasses.replace(model, bins=bins)
    back = type(model).load(model.save(tmp_path / "model.npz"))
    assert torch.equal(back.bins.M_change_factor, factor) and torch.equal(back.bins.M_bias, bias)
    closed = (bias.flatten()[:, None] * bias.flatten()[None, :]
              + factor.flatten(0, 2) @ factor.flatten(0, 2).T)
    mc_se = ((closed.diagonal()[:, None] * closed.diagonal()[None, :] + closed.square())
             / n).sqrt()

    def z_max(m) -> float:
        draws = sample_models(m, n, seed=5).metric(phase).flatten(1)  # (S, M d d)
        dev = draws - m.bins.M.flatten()
        z = float(((dev.T @ dev / n - closed) / mc_se).abs().max())
        print(f"max |z| of the draws' covariance: {z:.1f}")
        return z

    assert z_max(back) < 5
    assert z_max(dataclasses.replace(model, bins=dataclasses.replace(
        bins, M_change_factor=None))) > 10


# ---------------------------------------------------------------------------- bad input
def test_gait_outside_the_tube_is_refused(fitted_3link):
    _, _, model = fitted_3link
    far = wobbled_gait(FourierGait(model.gamma.coeffs), 1.5)
    with pytest.raises(ValueError, match="tube radii"):
        model.evaluate_gait(far, phase_offset=0.0, n_draws=0)
    with pytest.warns(ExcursionWarning, match="extrapolates"):
        model.evaluate_gait(wobbled_gait(FourierGait(model.gamma.coeffs), 0.35), phase_offset=0.0,
                            n_draws=0, max_excursion=100)


def test_connection_draws_take_a_s_sampling_factor_and_bias_allowance_whole(tmp_path):
    """``sample_models`` draws ``Â``'s sampling noise from its factor across entries and bins
    (``A_sampling_factor``, ``F``, holding all of ``A_se``) and its bias allowance
    (``A_bias_allowance``, ``b``) as one error shared by every entry and bin: the draws'
    covariance of ``Â`` at the bins is ``F Fᵀ + b bᵀ`` (Monte Carlo, 4000 draws, within 5
    standard errors of each covariance entry); drawn entry by entry from the same ``A_se``
    (no factor, no allowance) it is rejected by the same bound. ``∂Â/∂r``'s draws are those of
    the model without them, bit for bit (the factor and allowance come from a stream of
    their own). Both survive a save and load."""
    system = NLinkSwimmer(3)
    model = exact_local_model(system, circle_gait(2, 0.5), n_grid=16)
    phase, n = model.bins.phase, 4000
    g = torch.Generator().manual_seed(4)

    def smooth(*shape):  # values of Fourier order 2 at the bins (the series' span)
        c = torch.randn((5, 3, 2) + shape, generator=g, dtype=torch.float64)
        return torch.einsum("mh,hij...->mij...", fourier_design(phase, 2), c) * 0.01

    bias, factor = smooth(), smooth(4)  # (M, 3, d), (M, 3, d, R = 4)
    bins = dataclasses.replace(model.bins, A_se=factor.square().sum(-1).sqrt(),
                               dA_se=torch.full_like(model.bins.dA, 1e-3),
                               A_sampling_factor=factor, A_bias_allowance=bias)
    model = dataclasses.replace(model, bins=bins)
    back = type(model).load(model.save(tmp_path / "model.npz"))
    assert torch.equal(back.bins.A_sampling_factor, factor)
    assert torch.equal(back.bins.A_bias_allowance, bias)
    closed = (bias.flatten()[:, None] * bias.flatten()[None, :]
              + factor.flatten(0, 2) @ factor.flatten(0, 2).T)
    mc_se = ((closed.diagonal()[:, None] * closed.diagonal()[None, :] + closed.square())
             / n).sqrt()

    def z_max(m) -> float:
        draws = sample_models(m, n, seed=5).connection(phase).flatten(1)  # (S, M 3 d)
        dev = draws - m.bins.A.flatten()
        z = float(((dev.T @ dev / n - closed) / mc_se).abs().max())
        print(f"max |z| of the draws' covariance: {z:.1f}")
        return z

    assert z_max(back) < 5
    entrywise = dataclasses.replace(model, bins=dataclasses.replace(
        bins, A_sampling_factor=None, A_bias_allowance=None))
    assert z_max(entrywise) > 10
    assert torch.equal(sample_models(back, 8, seed=5).dA.coeffs,
                       sample_models(entrywise, 8, seed=5).dA.coeffs)
