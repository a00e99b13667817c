"""Phase binning and the batched connection / metric regressions (torchconn.regression)."""

from __future__ import annotations

import math
import warnings

import numpy as np
import pytest
import torch

from torchconn.physics.systems import AffineConnectionSystem, NLinkSwimmer
from torchconn.regression import (
    IllConditionedBinWarning,
    assign_bins,
    connection_regression,
)
from torchconn.testing.paper_metric import metric_regression

F64 = torch.float64


# ----------------------------------------------------------------------------- helpers
def circle(phi: torch.Tensor, d: int, radius: float = 0.5) -> tuple[torch.Tensor, torch.Tensor]:
    """A circle of ``radius`` in the first two joints (others 0) and its φ-derivative."""
    g = torch.zeros(phi.shape + (d,), dtype=F64)
    gd = torch.zeros(phi.shape + (d,), dtype=F64)
    g[..., 0], g[..., 1] = radius * torch.cos(phi), radius * torch.sin(phi)
    gd[..., 0], gd[..., 1] = -radius * torch.sin(phi), radius * torch.cos(phi)
    return g, gd


def tube_samples(batch, n, d, *, sigma=0.1, sigma_dot=0.1, seed=0, cycles=20):
    """Phases uniform over many cycles, ``r = γ(φ) + δ``, ``ṙ = γ'(φ) + δ̇``."""
    gen = torch.Generator().manual_seed(seed)
    phi = torch.rand(batch + (n,), generator=gen, dtype=F64) * (2 * math.pi * cycles)
    g, gd = circle(phi, d)
    r = g + sigma * torch.randn(batch + (n, d), generator=gen, dtype=F64)
    r_dot = gd + sigma_dot * torch.randn(batch + (n, d), generator=gen, dtype=F64)
    return phi, r, r_dot, gen


def cycle_at_centres(n_bins: int, d: int):
    phi_m = torch.arange(n_bins, dtype=F64) * (2 * math.pi / n_bins)
    return circle(phi_m, d)


# ----------------------------------------------------------------------------- binning
def test_assign_bins_matches_brute_force():
    gen = torch.Generator().manual_seed(1)
    phase = (torch.rand(2, 3, 300, generator=gen, dtype=F64) - 0.3) * 40  # negative, many cycles
    phase[0, 1, ::7] = torch.nan
    m = 7
    for window, kernel in [(0.5, "box"), (0.8, "tricube"), (1.3, "epanechnikov")]:
        bins = assign_bins(phase, m, window=window, kernel=kernel)
        assert bins.index.shape == (2, 3, m, bins.max_count)
        assert bins.max_count == int(bins.count.max())
        h = 2 * math.pi / m
        ph = phase.numpy()
        for idx in np.ndindex(2, 3):
            for k in range(m):
                off = np.remainder(ph[idx] - k * h + math.pi, 2 * math.pi) - math.pi
                inside = np.flatnonzero((off >= -window * h) & (off < window * h))
                got = bins.index[idx + (k,)][: bins.count[idx + (k,)]].numpy()
                assert sorted(got.tolist()) == inside.tolist()
                s = np.abs(off[got]) / (window * h)
                want = {"box": np.ones_like(s), "tricube": (1 - s**3) ** 3,
                        "epanechnikov": 1 - s**2}[kernel]
                np.testing.assert_allclose(bins.weight[idx + (k,)][: len(got)].numpy(), want,
                                           atol=1e-12)
                assert (bins.weight[idx + (k,)][len(got):] == 0).all()
        if window == 0.5:  # a partition: every finite sample in exactly one bin
            assert (bins.count.sum(-1) == torch.isfinite(phase).sum(-1)).all()


def test_assign_bins_validates():
    with pytest.raises(ValueError, match="window"):
        assign_bins(torch.zeros(10, dtype=F64), 4, window=2.0)
    with pytest.raises(ValueError, match="kernel"):
        assign_bins(torch.zeros(10, dtype=F64), 4, kernel="gauss")
    with pytest.raises(ValueError, match="inf"):
        assign_bins(torch.tensor([0.0, math.inf], dtype=F64), 4)


# ----------------------------------------------------------------------------- connection
@pytest.mark.parametrize("d", [2, 3])
def test_connection_exact_for_affine_toy(d):
    system = AffineConnectionSystem.random(d, seed=d)
    phi, r, r_dot, _ = tube_samples((2,), 3000, d, seed=d)
    xi = system.body_velocity(r, r_dot)
    bins = assign_bins(phi, 8)
    g_m, gd_m = cycle_at_centres(8, d)
    fit = connection_regression(r, r_dot, xi, bins, g_m, gd_m)

    a_true = system.connection(g_m)  # (M, 3, d)
    da_true = system.connection_jacobian(g_m)  # (M, 3, d, d) [k, i, j]
    torch.testing.assert_close(fit.A, a_true.expand_as(fit.A), atol=1e-8, rtol=0)
    torch.testing.assert_close(fit.dA, da_true.expand_as(fit.dA), atol=1e-8, rtol=0)
    c_true = (a_true @ gd_m.unsqueeze(-1)).squeeze(-1)
    b_true = torch.einsum("mkij,mi->mkj", da_true, gd_m)
    torch.testing.assert_close(fit.c, c_true.expand_as(fit.c), atol=1e-8, rtol=0)
    torch.testing.assert_close(fit.b, b_true.expand_as(fit.b), atol=1e-8, rtol=0)
    assert fit.residual_rms.max() < 1e-10
    assert (fit.n_samples == bins.count).all()
    p = 1 + 2 * d + d * d
    assert fit.coef.shape == (2, 8, p, 3) and fit.se_dA.shape == fit.dA.shape

    # the limit cycle may differ per batch element
    per_batch = connection_regression(r, r_dot, xi, bins, g_m.expand(2, 8, d), gd_m.expand(2, 8, d))
    torch.testing.assert_close(per_batch.A, fit.A, atol=1e-12, rtol=0)


def _reference_rows(bins, b, m, *arrays):
    """The weighted rows of bin ``m`` of batch element ``b`` as numpy arrays."""
    k = int(bins.count[b, m])
    idx = bins.index[b, m, :k].numpy()
    w = bins.weight[b, m, :k].numpy()
    keep = w > 0
    return (w[keep],) + tuple(a[b].numpy()[idx[keep]] for a in arrays)


def _reference_fit(x, y, w):
    """lstsq on √w-weighted rows, and the sandwich standard errors with the effective dof."""
    sw = np.sqrt(w)[:, None]
    beta = np.linalg.lstsq(sw * x, sw * y, rcond=None)[0]
    a = x.T @ (w[:, None] * x)
    g2 = x.T @ ((w**2)[:, None] * x)
    a_inv = np.linalg.inv(a)
    dof = w.sum() - np.trace(a_inv @ g2)
    sigma2 = (w[:, None] * (y - x @ beta) ** 2).sum(0) / dof
    cov = a_inv @ g2 @ a_inv
    return beta, np.sqrt(np.outer(np.diag(cov), sigma2))


@pytest.mark.parametrize("window, kernel", [(0.5, "box"), (0.75, "tricube")])
def test_connection_matches_per_bin_lstsq(window, kernel):
    d = 2
    system = AffineConnectionSystem.random(d, seed=5)
    phi, r, r_dot, gen = tube_samples((2,), 900, d, seed=5)
    # a non-affine response so the fit has residuals
    xi = system.body_velocity(r, r_dot) + 0.3 * torch.sin(3 * r[..., :1]) * r_dot[..., 1:] \
        + 0.05 * torch.randn(2, 900, 3, generator=gen, dtype=F64)
    bins = assign_bins(phi, 6, window=window, kernel=kernel)
    g_m, gd_m = cycle_at_centres(6, d)
    fit = connection_regression(r, r_dot, xi, bins, g_m, gd_m)
    for b in range(2):
        for m in range(6):
            w, rr, rd, y = _reference_rows(bins, b, m, r, r_dot, xi)
            delta, delta_dot = rr - g_m[m].numpy(), rd - gd_m[m].numpy()
            cross = np.einsum("ni,nj->nij", delta_dot, delta).reshape(len(w), d * d)
            x = np.concatenate([np.ones((len(w), 1)), delta, delta_dot, cross], 1)
            beta, se = _reference_fit(x, y, w)
            got = fit.coef[b, m].numpy()
            assert np.abs(got - beta).max() <= 1e-10 * np.abs(beta).max()
            np.testing.assert_allclose(fit.se_coef[b, m].numpy(), se, rtol=1e-8)
            assert int(fit.n_samples[b, m]) == len(w)


@pytest.mark.parametrize("kernel", ["box", "tricube"])
def test_connection_matches_lstsq_at_many_regressors(kernel):
    # d = 6: P = 49 regressors (L⁻¹ by a block split, see _wls._triangular_inverse), with
    # dropped samples and a tube radius that removes rows
    d = 6
    system = AffineConnectionSystem.random(d, seed=6)
    phi, r, r_dot, gen = tube_samples((2,), 2400, d, seed=6)
    xi = system.body_velocity(r, r_dot) + 0.2 * torch.cos(2 * r[..., 2:3]) * r_dot[..., :1] \
        + 0.05 * torch.randn(2, 2400, 3, generator=gen, dtype=F64)
    xi[0, ::7, 1] = torch.nan
    bins = assign_bins(phi, 4, window=0.75, kernel=kernel)
    g_m, gd_m = cycle_at_centres(4, d)
    fit = connection_regression(r, r_dot, xi, bins, g_m, gd_m, delta_max=0.3)
    for b in range(2):
        for m in range(4):
            w, rr, rd, y = _reference_rows(bins, b, m, r, r_dot, xi)
            delta, delta_dot = rr - g_m[m].numpy(), rd - gd_m[m].numpy()
            keep = (np.linalg.norm(delta, axis=1) < 0.3) & np.isfinite(y).all(1)
            w, y, delta, delta_dot = w[keep], y[keep], delta[keep], delta_dot[keep]
            cross = np.einsum("ni,nj->nij", delta_dot, delta).reshape(len(w), d * d)
            x = np.concatenate([np.ones((len(w), 1)), delta, delta_dot, cross], 1)
            beta, se = _reference_fit(x, y, w)
            assert np.abs(fit.coef[b, m].numpy() - beta).max() <= 1e-10 * np.abs(beta).max()
            np.testing.assert_allclose(fit.se_coef[b, m].numpy(), se, rtol=1e-8)
            np.testing.assert_allclose(
                fit.residual_rms[b, m].numpy(),
                np.sqrt((w[:, None] * (y - x @ beta) ** 2).sum(0) / w.sum()), rtol=1e-8)
            assert int(fit.n_samples[b, m]) == len(w)


@pytest.mark.parametrize("kernel", ["box", "tricube"])
def test_connection_standard_errors_calibrated(kernel):
    d, n_trials, m = 2, 40, 8
    system = AffineConnectionSystem.random(d, seed=11)
    phi, r, r_dot, gen = tube_samples((n_trials,), 1500, d, seed=11)
    xi = system.body_velocity(r, r_dot) + 0.05 * torch.randn(n_trials, 1500, 3, generator=gen,
                                                             dtype=F64)
    bins = assign_bins(phi, m, window=0.5 if kernel == "box" else 0.8, kernel=kernel)
    g_m, gd_m = cycle_at_centres(m, d)
    fit = connection_regression(r, r_dot, xi, bins, g_m, gd_m)
    for est, se, true in [(fit.A, fit.se_A, system.connection(g_m)),
                          (fit.dA, fit.se_dA, system.connection_jacobian(g_m)),
                          (fit.c, fit.se_c, (system.connection(g_m) @ gd_m.unsqueeze(-1))[..., 0])]:
        z = ((est - true) / se).flatten()
        assert abs(float(z.std()) - 1) < 0.1, float(z.std())
        assert abs(float(z.mean())) < 0.1


def test_delta_max_and_condition():
    d = 2
    system = AffineConnectionSystem.random(d, seed=13)
    phi, r, r_dot, gen = tube_samples((1,), 3000, d, seed=13)
    xi = system.body_velocity(r, r_dot) + 0.01 * torch.randn(1, 3000, 3, generator=gen, dtype=F64)
    bins = assign_bins(phi, 6)
    g_m, gd_m = cycle_at_centres(6, d)
    fit = connection_regression(r, r_dot, xi, bins, g_m, gd_m, delta_max=0.2)
    members = bins.gather(r) - g_m.unsqueeze(-2)  # (1, M, Nmax, d)
    inside = (members.norm(dim=-1) < 0.2) & (bins.weight > 0)
    assert (fit.n_samples == inside.sum(-1)).all() and (fit.n_samples < bins.count).all()
    assert (fit.A - system.connection(g_m)).abs().max() < 0.05

    # the reported condition bounds κ₁ of the equilibrated normal matrix from above, tightly
    for m in range(6):
        w, rr, rd = _reference_rows(bins, 0, m, r, r_dot)
        de, dd = rr - g_m[m].numpy(), rd - gd_m[m].numpy()
        keep = np.linalg.norm(de, axis=1) < 0.2
        de, dd = de[keep], dd[keep]
        x = np.concatenate([np.ones((len(de), 1)), de, dd,
                            np.einsum("ni,nj->nij", dd, de).reshape(len(de), -1)], 1)
        a = x.T @ x
        a_s = a / np.sqrt(np.outer(np.diag(a), np.diag(a)))
        kappa1 = np.linalg.cond(a_s, 1)
        assert kappa1 * (1 - 1e-9) <= float(fit.condition[0, m]) <= 9 * kappa1


def test_nan_samples_are_excluded():
    d = 2
    system = AffineConnectionSystem.random(d, seed=2)
    phi, r, r_dot, gen = tube_samples((), 2000, d, seed=2)
    xi = system.body_velocity(r, r_dot) + 0.01 * torch.randn(2000, 3, generator=gen, dtype=F64)
    drop = torch.zeros(2000, dtype=torch.bool)
    drop[::9] = True
    r_nan, xi_nan = r.clone(), xi.clone()
    r_nan[::18, 1] = torch.nan
    xi_nan[9::18, 2] = torch.nan
    g_m, gd_m = cycle_at_centres(6, d)
    fit = connection_regression(r_nan, r_dot, xi_nan, assign_bins(phi, 6), g_m, gd_m)
    keep = ~drop
    ref = connection_regression(r[keep], r_dot[keep], xi[keep], assign_bins(phi[keep], 6),
                                g_m, gd_m)
    torch.testing.assert_close(fit.coef, ref.coef, atol=1e-12, rtol=1e-10)
    torch.testing.assert_close(fit.se_coef, ref.se_coef, atol=1e-12, rtol=1e-10)
    assert (fit.n_samples == ref.n_samples).all()

    r_inf = r.clone()
    r_inf[3, 0] = math.inf
    with pytest.raises(ValueError, match="r contains ±inf"):
        connection_regression(r_inf, r_dot, xi, assign_bins(phi, 6), g_m, gd_m)


def _sparse_bin_data(d=2, batch=(2,)):
    """Uniform phases except bin 3 of the last batch element, which keeps only 4 samples."""
    phi, r, r_dot, _ = tube_samples(batch, 2000, d, seed=3)
    system = AffineConnectionSystem.random(d, seed=3)
    h = 2 * math.pi / 8
    off = torch.remainder(phi - 3 * h + math.pi, 2 * math.pi) - math.pi
    thin = (off[-1].abs() < h / 2).nonzero().flatten()[4:]
    phi = phi.clone()
    phi[-1, thin] += h  # move them to bin 4
    xi = system.body_velocity(r, r_dot)
    return phi, r, r_dot, xi


def test_too_few_samples_raise_warn():
    d = 2
    phi, r, r_dot, xi = _sparse_bin_data(d)
    bins = assign_bins(phi, 8)
    assert int(bins.count[1, 3]) == 4
    g_m, gd_m = cycle_at_centres(8, d)
    with pytest.raises(ValueError, match=r"batch \(1,\) bin 3: 4 samples < min_samples=14"):
        connection_regression(r, r_dot, xi, bins, g_m, gd_m)
    with pytest.warns(IllConditionedBinWarning, match="bin 3"):
        fit = connection_regression(r, r_dot, xi, bins, g_m, gd_m, on_ill_conditioned="warn")
    assert torch.isnan(fit.A[1, 3]).all() and torch.isnan(fit.se_A[1, 3]).all()
    assert torch.isfinite(fit.A[0]).all() and torch.isfinite(fit.A[1, :3]).all()


def test_rank_deficient_design():
    d = 3
    system = AffineConnectionSystem.random(d, seed=4)
    phi, r, r_dot, _ = tube_samples((), 3000, d, seed=4)
    r[..., 2] = 0.0  # joint 3 held fixed: δ₃ ≡ 0 and δ̇₃ ≡ 0 in every bin
    r_dot[..., 2] = 0.0
    xi = system.body_velocity(r, r_dot)
    bins = assign_bins(phi, 8)
    g_m, gd_m = cycle_at_centres(8, d)
    with pytest.raises(ValueError, match="rank-deficient"):
        connection_regression(r, r_dot, xi, bins, g_m, gd_m)
    with pytest.warns(IllConditionedBinWarning):
        fit = connection_regression(r, r_dot, xi, bins, g_m, gd_m, on_ill_conditioned="warn")
    assert torch.isnan(fit.A).all()
    with pytest.warns(IllConditionedBinWarning, match="ridge"):
        fit = connection_regression(r, r_dot, xi, bins, g_m, gd_m, on_ill_conditioned="ridge")
    # the identifiable part is still exact (the dead columns decouple); the rest is NaN
    a_true = system.connection(g_m)
    torch.testing.assert_close(fit.A[..., :2], a_true[..., :2], atol=1e-8, rtol=0)
    assert torch.isnan(fit.A[..., 2]).all() and torch.isnan(fit.dA[..., 2]).all()
    assert (fit.ridge == 0).all() and torch.isfinite(fit.condition).all()


def test_near_collinear_design_gets_ridge():
    d = 2
    phi, r, r_dot, gen = tube_samples((), 3000, d, seed=6)
    system = AffineConnectionSystem.random(d, seed=6)
    g_m, gd_m = cycle_at_centres(8, d)
    r = r.clone()
    # r₂ an affine function of r₁ up to 1e-8: δ₂ nearly collinear with [1, δ₁] in every bin
    r[..., 1] = 0.5 * r[..., 0] + 1e-8 * torch.randn(3000, generator=gen, dtype=F64)
    xi = system.body_velocity(r, r_dot) + 1e-3 * torch.randn(3000, 3, generator=gen, dtype=F64)
    bins = assign_bins(phi, 8)
    with pytest.raises(ValueError, match="condition number"):
        connection_regression(r, r_dot, xi, bins, g_m, gd_m)
    with pytest.warns(IllConditionedBinWarning, match="ridge"):
        fit = connection_regression(r, r_dot, xi, bins, g_m, gd_m, on_ill_conditioned="ridge")
    assert (fit.ridge > 0).all() and (fit.condition <= 1e12).all()
    assert torch.isfinite(fit.A).all() and torch.isfinite(fit.se_A).all()


def test_input_validation():
    d = 3
    phi, r, r_dot, _ = tube_samples((), 500, d)
    xi = torch.zeros(500, 3, dtype=F64)
    bins = assign_bins(phi, 4)
    g2, gd2 = cycle_at_centres(4, 2)
    expect = r"gamma_m must have shape \(\.\.\., M, d\) = \(\.\.\., 4, 3\)"
    with pytest.raises(ValueError, match=expect):
        connection_regression(r, r_dot, xi, bins, g2, gd2)
    g3, gd3 = cycle_at_centres(4, d)
    with pytest.raises(ValueError, match="xi must have shape"):
        connection_regression(r, r_dot, xi[:, :2], bins, g3, gd3)
    with pytest.raises(ValueError, match="assign_bins"):
        connection_regression(r[:400], r_dot[:400], xi[:400], bins, g3, gd3)
    with pytest.raises(ValueError, match="does not broadcast"):
        connection_regression(r, r_dot, xi, bins, g3.expand(2, 4, d), gd3)


def test_float32_follows_dtype():
    d = 2
    system = AffineConnectionSystem.random(d, seed=8)
    phi, r, r_dot, _ = tube_samples((), 2000, d, seed=8)
    xi = system.body_velocity(r, r_dot)
    g_m, gd_m = cycle_at_centres(4, d)
    fit = connection_regression(r.float(), r_dot.float(), xi.float(), assign_bins(phi.float(), 4),
                                g_m, gd_m)
    assert fit.A.dtype == torch.float32
    torch.testing.assert_close(fit.A.double(), system.connection(g_m), atol=1e-3, rtol=0)


def test_swimmer_error_is_second_order_in_tube_width():
    """Â(γ_m) − A(γ_m) comes from the neglected ∂²A δδ terms: it shrinks like σ²."""
    swimmer, d, m, n = NLinkSwimmer(3), 2, 8, 3000
    g_m, gd_m = cycle_at_centres(m, d)
    sigmas = torch.tensor([0.0125, 0.025, 0.05, 0.1], dtype=F64)
    gen = torch.Generator().manual_seed(7)
    # phases near the bin centres with along-cycle spread ∝ σ, so the whole tube scales with σ
    k = torch.randint(0, m, (4, n), generator=gen)
    phi = k * (2 * math.pi / m) + 2 * sigmas[:, None] * (torch.rand(4, n, generator=gen, dtype=F64)
                                                        * 2 - 1)
    g, gd = circle(phi, d)
    r = g + sigmas[:, None, None] * torch.randn(4, n, d, generator=gen, dtype=F64)
    r_dot = gd + 0.3 * torch.randn(4, n, d, generator=gen, dtype=F64)
    xi = swimmer.body_velocity(r, r_dot)
    fit = connection_regression(r, r_dot, xi, assign_bins(phi, m), g_m, gd_m)
    err = (fit.A - swimmer.connection(g_m)).abs().amax((-3, -2, -1))  # (4,)
    slope = np.polyfit(np.log(sigmas.numpy()), np.log(err.numpy()), 1)[0]
    assert 1.5 < slope < 2.5, (slope, err)
    assert float(err[0]) < 1e-3


# ----------------------------------------------------------------------------- metric
def affine_metric(d: int, seed: int = 0):
    """``M(r) = M0 + Σ_k M1[..., k] r_k``: symmetric, positive definite near the cycle."""
    gen = torch.Generator().manual_seed(seed)
    q = torch.randn(d, d, generator=gen, dtype=F64)
    m0 = q @ q.T + d * torch.eye(d, dtype=F64)
    m1 = 0.3 * torch.randn(d, d, d, generator=gen, dtype=F64)
    m1 = (m1 + m1.transpose(0, 1)) / 2  # [i, j, k] = ∂M_ij/∂r_k

    def metric(r):
        return m0 + torch.einsum("ijk,...k->...ij", m1, r)

    return metric, m1


@pytest.mark.parametrize("d", [2, 3])
def test_metric_exact_for_affine_metric(d):
    metric, m1 = affine_metric(d, seed=d)
    phi, r, r_dot, _ = tube_samples((2,), 4000, d, seed=20 + d)
    power = torch.einsum("...i,...ij,...j->...", r_dot, metric(r), r_dot)
    bins = assign_bins(phi, 6)
    g_m, gd_m = cycle_at_centres(6, d)
    fit = metric_regression(r, r_dot, power, bins, g_m, gd_m)
    assert fit.dM is not None  # enough samples: the derivative block is fitted by default
    torch.testing.assert_close(fit.M, metric(g_m).expand_as(fit.M), atol=1e-8, rtol=0)
    torch.testing.assert_close(fit.dM, m1.expand_as(fit.dM), atol=1e-8, rtol=0)
    p_cycle = torch.einsum("mi,mij,mj->m", gd_m, metric(g_m), gd_m)
    torch.testing.assert_close(fit.power_on_cycle, p_cycle.expand_as(fit.power_on_cycle),
                               atol=1e-8, rtol=0)
    assert torch.equal(fit.M, fit.M.mT) and fit.se_M.shape == fit.M.shape


def test_metric_constant_without_derivative():
    d = 3
    system = AffineConnectionSystem.random(d, seed=9)
    phi, r, r_dot, _ = tube_samples((), 1200, d, seed=9)
    power = system.power(r, r_dot)
    g_m, gd_m = cycle_at_centres(8, d)
    bins = assign_bins(phi, 8)
    fit = metric_regression(r, r_dot, power, bins, g_m, gd_m, with_metric_derivative=False)
    assert fit.dM is None and fit.se_dM is None
    torch.testing.assert_close(fit.M, system.metric(g_m), atol=1e-8, rtol=0)
    # automatic choice: too few samples per bin for the 3rd-order block in d = 8 → left out
    phi8, r8, rd8, _ = tube_samples((), 1200, 8, seed=9)
    fit8 = metric_regression(r8, rd8, (rd8**2).sum(-1), assign_bins(phi8, 8),
                             *cycle_at_centres(8, 8))
    assert fit8.dM is None
    torch.testing.assert_close(fit8.M, torch.eye(8, dtype=F64).expand_as(fit8.M), atol=1e-8,
                               rtol=0)


def test_metric_matches_per_bin_lstsq():
    d = 2
    metric, _ = affine_metric(d, seed=1)
    phi, r, r_dot, gen = tube_samples((2,), 1500, d, seed=12)
    power = torch.einsum("...i,...ij,...j->...", r_dot, metric(r), r_dot) \
        + 0.05 * torch.randn(2, 1500, generator=gen, dtype=F64) + 0.2 * r[..., 0] ** 2
    bins = assign_bins(phi, 5, window=0.7, kernel="epanechnikov")
    g_m, gd_m = cycle_at_centres(5, d)
    fit = metric_regression(r, r_dot, power, bins, g_m, gd_m, with_metric_derivative=True)
    iu = np.triu_indices(d)
    for b in range(2):
        for m in range(5):
            w, rr, rd, y = _reference_rows(bins, b, m, r, r_dot, power.unsqueeze(-1))
            de, dd = rr - g_m[m].numpy(), rd - gd_m[m].numpy()
            quad = dd[:, iu[0]] * dd[:, iu[1]]
            x = np.concatenate([np.ones((len(w), 1)), dd, quad, de,
                                np.einsum("nk,nj->nkj", de, dd).reshape(len(w), -1),
                                np.einsum("nk,nq->nkq", de, quad).reshape(len(w), -1)], 1)
            beta, se = _reference_fit(x, y, w)
            assert np.abs(fit.coef[b, m].numpy() - beta[:, 0]).max() <= 1e-10 * np.abs(beta).max()
            np.testing.assert_allclose(fit.se_coef[b, m].numpy(), se[:, 0], rtol=1e-8)


def _collinear_data(d=2, n=3000, seed=6):
    """Bins whose ``δ₂`` is ``0.5 δ₁`` up to 1e-8 (ill-conditioned; the ridge policy fixes
    them) and 1e-3 noise on the body velocity, kernel weights."""
    phi, r, r_dot, gen = tube_samples((), n, d, seed=seed)
    system = AffineConnectionSystem.random(d, seed=seed)
    r = r.clone()
    r[..., 1] = 0.5 * r[..., 0] + 1e-8 * torch.randn(n, generator=gen, dtype=F64)
    xi = system.body_velocity(r, r_dot) + 1e-3 * torch.randn(n, 3, generator=gen, dtype=F64)
    return phi, r, r_dot, xi


@pytest.mark.parametrize("case", ["plain", "ridge", "sparse_warn", "collinear_ridge"])
def test_coefficients_alone_are_the_full_solvers_bit_for_bit(case):
    """``standard_errors=False`` (the bias correction's regressions) skips the residuals and
    the sandwich, and changes no coefficient, condition number, count or ridge by a bit,
    also where the solver warns (NaN bins) or adds a ridge to ill-conditioned bins."""
    d = 2
    g_m, gd_m = cycle_at_centres(8, d)
    opts = {}
    if case in ("plain", "ridge"):
        phi, r, r_dot, gen = tube_samples((3,), 1500, d, seed=1)
        system = AffineConnectionSystem.random(d, seed=1)
        xi = system.body_velocity(r, r_dot) + 0.01 * torch.randn(r.shape[:-1] + (3,),
                                                                 generator=gen, dtype=F64)
        opts = {"ridge": 0.5} if case == "ridge" else {}
    elif case == "sparse_warn":
        phi, r, r_dot, xi = _sparse_bin_data(d)
        opts = {"on_ill_conditioned": "warn"}
    else:
        phi, r, r_dot, xi = _collinear_data(d)
        opts = {"on_ill_conditioned": "ridge"}
    # kernel weights (the sandwich), except where a bin must stay sparse
    bins = (assign_bins(phi, 8) if case == "sparse_warn"
            else assign_bins(phi, 8, window=1.5, kernel="tricube"))
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", IllConditionedBinWarning)
        full = connection_regression(r, r_dot, xi, bins, g_m, gd_m, **opts)
        alone = connection_regression(r, r_dot, xi, bins, g_m, gd_m, standard_errors=False,
                                      **opts)
    for name in ("coef", "c", "b", "A", "dA", "condition", "n_samples", "ridge", "eiv_scale"):
        a, b = getattr(full, name), getattr(alone, name)
        assert torch.equal(a.nan_to_num(), b.nan_to_num()), name
        assert torch.equal(a.isnan(), b.isnan()), name
    assert bool(alone.se_A.isnan().all()) and bool(alone.residual_rms.isnan().all())
    assert bool(full.se_A[full.A.isfinite()].isfinite().all())
    if case == "collinear_ridge":
        assert bool((alone.ridge > 0).any())  # the ridge path ran
    if case == "sparse_warn":
        assert bool(alone.A.isnan().any()) and bool(alone.A.isfinite().any())
