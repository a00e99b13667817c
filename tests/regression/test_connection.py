"""Phase binning and the batched connection / metric regressions (torchconn.regression)."""

from __future__ import annotations

import math
import warnings

import numpy as np
import pytest
import torch

from torchconn.physics.systems import AffineConnectionSystem, NLinkSwimmer
from torchconn.regression import IllConditionedBinWarning, assign_bins, connection_regression
from torchconn.regression.connection import connection_design

from .common import circle, cycle_at_centres, reference_fit, reference_rows, tube_samples

F64 = torch.float64


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
            w, rr, rd, y = reference_rows(bins, b, m, r, r_dot, xi)
            delta, delta_dot = rr - g_m[m].numpy(), rd - gd_m[m].numpy()
            cross = np.einsum("ni,nj->nij", delta_dot, delta).reshape(len(w), d * d)
            x = np.concatenate([np.ones((len(w), 1)), delta, delta_dot, cross], 1)
            beta, se = reference_fit(x, y, w)
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
            w, rr, rd, y = reference_rows(bins, b, m, r, r_dot, xi)
            delta, delta_dot = rr - g_m[m].numpy(), rd - gd_m[m].numpy()
            keep = (np.linalg.norm(delta, axis=1) < 0.3) & np.isfinite(y).all(1)
            w, y, delta, delta_dot = w[keep], y[keep], delta[keep], delta_dot[keep]
            cross = np.einsum("ni,nj->nij", delta_dot, delta).reshape(len(w), d * d)
            x = np.concatenate([np.ones((len(w), 1)), delta, delta_dot, cross], 1)
            beta, se = reference_fit(x, y, w)
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
        w, rr, rd = reference_rows(bins, 0, m, r, r_dot)
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


def test_the_ridge_can_leave_the_connection_unpenalised():
    # the solver's ridge against its closed form: (XᵀX + λ D) β = Xᵀy with D the diagonal of
    # XᵀX on every column but the intercept and Â's (δ̇); without the exemption Â shrinks
    from torchconn.regression import _wls
    from torchconn.regression.connection import unpenalised_columns

    gen = torch.Generator().manual_seed(3)
    d, n = 2, 400
    x = connection_design(0.1 * torch.randn(n, d, generator=gen, dtype=F64),
                          0.3 * torch.randn(n, d, generator=gen, dtype=F64))
    beta_true = torch.randn(x.shape[-1], 3, generator=gen, dtype=F64)
    y = x @ beta_true + 0.05 * torch.randn(n, 3, generator=gen, dtype=F64)
    gram, rhs = x.T @ x, x.T @ y
    free = unpenalised_columns(d)
    assert free.tolist() == [False] * 3 + [True] * 2 + [False] * 4
    lam = 1.0
    chol, failed, _, _ = _wls.ridge_cholesky(gram.clone()[None], lam, free)
    beta = torch.cholesky_solve(rhs[None], chol)[0]
    pen = torch.where(free, 0.0, lam * gram.diagonal())
    pen[0] = 0
    assert not bool(failed.any())
    assert torch.allclose(beta, torch.linalg.solve(gram + torch.diag(pen), rhs), atol=1e-12)
    a = slice(1 + d, 1 + 2 * d)
    assert torch.allclose(beta[a], beta_true[a], atol=0.05)  # Â as without a ridge
    chol_all, _, _, _ = _wls.ridge_cholesky(gram.clone()[None], lam)  # every column
    shrunk = torch.cholesky_solve(rhs[None], chol_all)[0]
    assert float(shrunk[a].norm()) < 0.8 * float(beta_true[a].norm())


def test_ridge_cholesky_is_torchs_factor_or_the_identity_where_it_fails():
    # the factor is torch's own, bit for bit and in its column-major layout (the triangular
    # solves' rounding depends on it); a matrix that is not positive definite gets the
    # identity and is flagged, and a dead column a unit pivot
    from torchconn.regression import _wls

    gen = torch.Generator().manual_seed(4)
    x = torch.randn(3, 60, 6, generator=gen, dtype=F64)
    gram = x.mT @ x
    off = 2 * (gram[1, 0, 0] * gram[1, 1, 1]).sqrt()
    gram[1, 0, 1] = gram[1, 1, 0] = off  # not positive definite, positive diagonal
    gram[2, :, 4] = gram[2, 4, :] = 0.0  # a dead column
    chol, failed, dead, d2 = _wls.ridge_cholesky(gram.clone(), 0.0)
    ref, info = torch.linalg.cholesky_ex(gram)
    assert failed.tolist() == [False, True, False] and (info[1] != 0).item()
    assert torch.equal(chol[0], ref[0]) and chol.stride() == ref.stride()
    assert torch.equal(chol[1], torch.eye(6, dtype=F64))
    assert dead.tolist() == [[False] * 6] * 2 + [[False] * 4 + [True, False]]
    assert torch.equal(d2, gram.diagonal(dim1=-2, dim2=-1))
    pivoted = gram[2].clone()
    pivoted[4, 4] = 1.0
    assert torch.equal(chol[2], torch.linalg.cholesky(pivoted))


def test_row_sums_in_place_are_the_running_sums():
    from torchconn.regression import _wls

    x = torch.randn(4, 37, 5, generator=torch.Generator().manual_seed(5), dtype=F64)
    x[:, 30:] = 0  # padding rows
    expected = _wls._row_sum(x, -2)
    assert torch.equal(expected, x[:, :30].cumsum(-2)[:, -1])  # padding leaves it unchanged
    assert torch.equal(_wls._row_sum_(x.clone(), -2), expected)
