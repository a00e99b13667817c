"""The errors-in-variables solve: the correction of the Gram matrix, its guard, its rows,
the offsets at a held connection and the sampling factor."""

import dataclasses
import math

import numpy as np
import pytest
import torch

from torchconn import (
    ConnectionEstimator,
)
from torchconn.noise import (
    interval_samples,
)
from torchconn.regression.binning import assign_bins
from torchconn.regression.connection import connection_design
from torchconn.regression.noise_aware import eiv_correction, noise_aware_regression
from torchconn.regression.noise_aware.eiv import sampling_factor

from ..common import noisy_circle_trials

F64 = torch.float64


def test_eiv_correction_is_the_expected_noise_part_of_the_gram_matrix():
    # Monte Carlo: E[X̃ᵀWX̃] − XᵀWX over noise draws equals the correction in expectation
    g = torch.Generator().manual_seed(1)
    d, n, reps = 2, 50, 20000
    delta = 0.3 * torch.randn(n, d, generator=g, dtype=F64)
    rate = 0.5 * torch.randn(n, d, generator=g, dtype=F64) + 0.2
    w = torch.rand(n, generator=g, dtype=F64)
    var_delta = torch.tensor([0.01, 0.04], dtype=F64)
    var_rate = torch.tensor([0.09, 0.02], dtype=F64)

    def gram(x):
        return (x * w[:, None]).mT @ x

    true = gram(connection_design(delta, rate))
    noisy_d = delta + var_delta.sqrt() * torch.randn(reps, n, d, generator=g, dtype=F64)
    noisy_r = rate + var_rate.sqrt() * torch.randn(reps, n, d, generator=g, dtype=F64)
    observed = gram(connection_design(noisy_d, noisy_r))  # (reps, P, P)
    corrected = observed - eiv_correction(observed, var_delta.expand(reps, d),
                                          var_rate.expand(reps, d))
    err = (corrected.mean(0) - true).abs().max()
    scale = true.abs().max()
    assert float(err) < 0.01 * float(scale)
    # and without the correction the difference is far larger than the Monte Carlo error
    assert float((observed.mean(0) - true).abs().max()) > 10 * float(err)


def test_eiv_guard_scales_the_correction_down_instead_of_failing():
    traj = noisy_circle_trials(0.005, n_cycles=10, n_trials=1)
    phase = ConnectionEstimator().prepare(traj).phase
    iv = interval_samples(traj.pose, traj.r, phase, traj.dt, 1)
    bins = assign_bins(iv.phase, 12, window=1.0, kernel="tricube")
    gamma = torch.zeros(1, 12, 2, dtype=F64)
    # a wildly overstated noise level would make the corrected Gram matrix indefinite
    fit = noise_aware_regression(iv, bins, gamma, gamma, torch.full((2,), 0.5, dtype=F64))
    assert bool((fit.eiv_scale < 1).all()) and bool((fit.eiv_scale > 0).all())
    assert bool(torch.isfinite(fit.A).all())


def test_eiv_guard_scale_is_the_generalised_eigenvalue_bound():
    # κ = min(1, 0.9 / λ_max) with λ_max the largest generalised eigenvalue of (corr, gram),
    # here from scipy's generalised symmetric eigensolver, on bins where the full correction
    # is safe (κ = 1, settled by the guard's positive-definiteness test), bins where it is
    # not (κ < 1) and a bin whose Gram matrix is singular (κ = 0)
    from scipy.linalg import eigh

    from torchconn.regression._wls import _guarded_correction

    g = torch.Generator().manual_seed(5)
    b, n, d = 24, 60, 3
    delta = 0.2 * torch.randn(b, n, d, generator=g, dtype=F64)
    rate = 0.5 * torch.randn(b, n, d, generator=g, dtype=F64)
    x = connection_design(delta, rate)
    gram = x.mT @ x
    gram[-1] = gram[-1, :, :1] @ gram[-1, :1, :] / gram[-1, 0, 0]  # rank one: singular
    level = torch.logspace(-4, -1, b, dtype=F64).unsqueeze(-1)
    corr = eiv_correction(gram, level * torch.ones(b, d, dtype=F64),
                          4 * level * torch.ones(b, d, dtype=F64))
    corrected, kappa = _guarded_correction(gram, corr)
    lam = torch.tensor([eigh(c.numpy(), gm.numpy(), eigvals_only=True)[-1]
                        for c, gm in zip(corr[:-1], gram[:-1], strict=True)], dtype=F64)
    expected = torch.clamp(0.9 / lam, max=1.0)
    assert bool((kappa[:-1] == 1).any()) and bool((kappa[:-1] < 1).any())
    assert torch.allclose(kappa[:-1], expected, rtol=1e-9, atol=0)
    assert float(kappa[-1]) == 0
    assert torch.equal(corrected, gram - kappa[:, None, None] * corr)


def test_eiv_row_correction_sums_to_the_bins_correction_times_the_coefficients():
    # The robust covariance's scores carry each row's share of the errors-in-variables
    # correction: linear in the row's Gram matrix, so over a bin's rows they must sum to
    # eiv_correction(XᵀWX) β exactly (any d, any weights).
    from torchconn.regression.connection import connection_design
    from torchconn.regression.noise_aware import eiv_correction, eiv_row_correction

    gen = torch.Generator().manual_seed(3)
    for d in (2, 4):
        delta = torch.randn(5, 40, d, generator=gen, dtype=F64)
        delta_dot = torch.randn(5, 40, d, generator=gen, dtype=F64)
        w = torch.rand(5, 40, generator=gen, dtype=F64)
        xw = connection_design(delta, delta_dot) * w.sqrt().unsqueeze(-1)
        p = xw.shape[-1]
        beta = torch.randn(5, p, 3, generator=gen, dtype=F64)
        var_delta = torch.rand(5, d, generator=gen, dtype=F64)
        var_rate = torch.rand(5, d, generator=gen, dtype=F64)
        rows = eiv_row_correction(xw, beta, var_delta, var_rate)  # (b, n, K, P)
        whole = eiv_correction(xw.mT @ xw, var_delta, var_rate) @ beta  # (b, P, K)
        torch.testing.assert_close(rows.sum(1).mT, whole, rtol=1e-12, atol=1e-10)


@pytest.mark.parametrize(("noise", "ridge"), [(0.0, 0.0), (0.0, 0.3), (0.02, 0.0)])
def test_offsets_refitted_with_a_held_are_the_bins_least_squares_at_that_a(noise, ridge):
    """offset_gain / offsets_at: ĉ and b̂ of each bin re-estimated with Â moved by ΔÂ and held
    there (∂Â/∂r held at its estimate) are the bin's least-squares solution at that Â,
    computed here independently per bin in numpy from the bin's weighted samples: without
    noise and ridge by np.linalg.lstsq of √w[1, δ] on √w(ξ − Âδ̇ − ∂Â/∂r δ̇⊗δ); with a ridge
    by lstsq on the rows augmented with √(λ Σw δ_j²) (the solver's penalty on the
    standardised δ columns); with measurement noise from the corrected normal equations:
    the noise σ²g_r of δ (g_r the filter's gain) removed from Σwδδᵀ, and from the δ-(δ̇⊗δ)
    block the part Σwδ̇_i σ²g_r [j = k] it adds, which enters with ∂Â/∂r held (the
    δ-δ̇ block has none: the two noises are uncorrelated)."""
    from torchconn.noise import IntervalSamples
    from torchconn.regression.noise_aware import offset_gain, offsets_at

    gen = torch.Generator().manual_seed(11)
    d, n, m = 2, 3000, 12
    phase = 2 * math.pi * torch.rand(n, generator=gen, dtype=F64)
    cyc = torch.stack([0.9 * torch.cos(phase), 0.9 * torch.sin(phase)], -1)
    r = cyc + 0.1 * torch.randn(n, d, generator=gen, dtype=F64)
    r_dot = torch.stack([-0.9 * torch.sin(phase), 0.9 * torch.cos(phase)], -1) \
        + 0.3 * torch.randn(n, d, generator=gen, dtype=F64)
    xi = (torch.randn(n, 3, generator=gen, dtype=F64) * 0.05
          + r_dot @ torch.randn(d, 3, generator=gen, dtype=F64)
          + (r * r_dot).sum(-1, keepdim=True) * 0.3)
    samples = IntervalSamples(phase=phase, r=r, r_dot=r_dot, xi=xi, h=3, dt=0.05)
    bins = assign_bins(phase, m, window=1.5, kernel="tricube")
    centres = torch.arange(m, dtype=F64) * (2 * math.pi / m)
    gamma_m = torch.stack([0.9 * torch.cos(centres), 0.9 * torch.sin(centres)], -1)
    gamma_dot_m = torch.stack([-0.9 * torch.sin(centres), 0.9 * torch.cos(centres)], -1)
    var = torch.full((d,), noise**2, dtype=F64)
    fit = noise_aware_regression(samples, bins, gamma_m, gamma_dot_m, var, ridge=ridge)
    assert bool((fit.eiv_scale == 1).all())  # (the guard left the correction whole)
    fit = dataclasses.replace(fit, offset_gain=offset_gain(fit, samples, bins, gamma_m,
                                                           gamma_dot_m, var))
    delta_a = 0.2 * torch.randn(m, 3, d, generator=gen, dtype=F64)
    c, b = offsets_at(fit, delta_a)
    assert float((c - fit.c).abs().max()) > 1e-3  # (the refit moves them)
    g_r = samples.noise_gains()[0]
    for k in range(m):
        w = bins.weight[k].numpy()
        idx = bins.index[k].numpy()[w > 0]
        w = w[w > 0]
        delta = r[idx].numpy() - gamma_m[k].numpy()
        delta_dot = r_dot[idx].numpy() - gamma_dot_m[k].numpy()
        a = (fit.A[k] + delta_a[k]).numpy()  # (3, d)
        cross = np.einsum("kij,ni,nj->nk", fit.dA[k].numpy(), delta_dot, delta)
        y = xi[idx].numpy() - delta_dot @ a.T - cross  # (n, 3)
        x = np.concatenate([np.ones((len(w), 1)), delta], 1)
        sw = np.sqrt(w)[:, None]
        if noise:
            s2 = noise**2 * g_r
            normal = (x * w[:, None]).T @ x
            normal[1:, 1:] -= np.diag(w.sum() * s2 * np.ones(d))
            rhs = (x * w[:, None]).T @ y
            rate_sum = (w[:, None] * delta_dot).sum(0)  # Σw δ̇_i
            rhs[1:] += s2 * np.einsum("i,kij->jk", rate_sum, fit.dA[k].numpy())
            want = np.linalg.solve(normal, rhs)
        else:
            xa, ya = x * sw, y * sw
            if ridge:
                pen = np.sqrt(ridge * (w[:, None] * delta**2).sum(0))
                xa = np.concatenate([xa, np.concatenate([np.zeros((d, 1)), np.diag(pen)], 1)])
                ya = np.concatenate([ya, np.zeros((d, 3))])
            want = np.linalg.lstsq(xa, ya, rcond=None)[0]  # (1 + d, 3)
        np.testing.assert_allclose(c[k].numpy(), want[0], rtol=1e-9, atol=1e-12)
        np.testing.assert_allclose(b[k].numpy(), want[1:].T, rtol=1e-9, atol=1e-12)


# ------------------------------------------------------------ what nearby-gait draws take of Â
def test_sampling_factor_keeps_the_standard_errors_and_the_cycles_correlation():
    """``sampling_factor``: each entry's row of the cycles' shares scaled to its standard error,
    so ``F Fᵀ = D S Sᵀ D`` with ``D = se / ‖S_row‖`` (closed form), compressed to at most ``C``
    directions; an entry without shares or a finite standard error gets zeros."""
    g = torch.Generator().manual_seed(2)
    shares = torch.randn(6, 3, 2, 10, generator=g, dtype=F64)  # (M, 3, d, C = 10 < 36 entries)
    shares[0, 1, 0] = 0
    se = torch.rand(6, 3, 2, generator=g, dtype=F64) + 0.1
    se[2, 0, 1] = torch.nan
    f = sampling_factor(shares, se)
    assert f.shape[:3] == (6, 3, 2) and f.shape[-1] <= 10
    scale = se / shares.square().sum(-1).sqrt()
    scale = torch.where(torch.isfinite(scale), scale, 0.0).flatten()
    flat = shares.flatten(0, 2)
    closed = scale[:, None] * (flat @ flat.T) * scale[None, :]
    got = f.flatten(0, 2) @ f.flatten(0, 2).T
    torch.testing.assert_close(got, closed, rtol=1e-9, atol=1e-12)
    var = f.square().sum(-1)
    assert float(var[0, 1, 0]) < 1e-28 and float(var[2, 0, 1]) < 1e-28  # (SVD rounding)
    ok = torch.ones_like(se, dtype=torch.bool)
    ok[0, 1, 0] = ok[2, 0, 1] = False
    torch.testing.assert_close(var[ok], se[ok].square(), rtol=1e-9, atol=0)
