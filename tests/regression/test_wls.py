"""The joint covariance of a bin's coefficients (``_wls.sandwich_correlation``,
``_wls.score_covariance``) against independent computations: a Monte Carlo over replicate
errors in a fixed design, and closed forms written out here per bin with dense matrices.

Every problem is one fixed set of regressors ``[1, δ, δ̇, δ̇⊗δ]`` (d = 2, P = 9, the
noise-aware design) whose ``R`` replicates, the batch dimension, differ only in their drawn
errors, so one call fits all of them. Bounds come from the Monte Carlo's own sampling error:
an empirical covariance ``S`` of ``R`` Gaussian estimates of true covariance ``Σ``, whitened by
``Σ``, has entries of variance ``(1 + [i = j]) / R``; a mean over replicates has the standard
error of the replicates' spread over ``√R``. A bound of ``_Z`` such standard errors over a few
hundred entries fails by chance with probability about 1e-4 (the seeds are fixed anyway); each
test also checks that a wrong model of the errors is rejected by the same bound.
"""

import math

import torch

from torchconn.regression import _wls
from torchconn.regression.binning import assign_bins
from torchconn.regression.connection import design_blocks
from torchconn.regression.noise_aware import eiv_correction, eiv_row_correction

F64 = torch.float64
D = 2
P = 1 + 2 * D + D * D
#: b̂'s columns δ and the direct ∂Â/∂r's δ̇⊗δ, as noise_aware_regression takes them
COLUMNS = torch.cat([torch.arange(1, 1 + D), torch.arange(1 + 2 * D, P)])
C = COLUMNS.numel()
_Z = 5.0


def _design(n, gen):
    """Fixed latent regressors ``r, ṙ (n, d)``, their design ``X (n, P)``, phase ``(n,)``
    (3 cycles, increasing: a bin's rows run in sample order) and coefficients ``(P, 1)``."""
    phase = 2 * math.pi * 3 * torch.arange(n, dtype=F64) / n
    r = torch.randn(n, D, generator=gen, dtype=F64)
    r_dot = torch.randn(n, D, generator=gen, dtype=F64)
    x = torch.cat(design_blocks(r, r_dot, torch.ones(n, 1, dtype=F64)), -1)
    return phase, r, r_dot, x, torch.randn(P, 1, generator=gen, dtype=F64)


def _fit(phase, r, r_dot, y, n_bins, window, kernel, ridge=0.0, correction=None):
    """Every replicate's bins (``r, r_dot (R, n, d)``, ``y (R, n, 1)``, cycle at 0 so that
    ``δ = r``): the binned samples and the solver's solution."""
    bins = assign_bins(phase.expand(y.shape[:2]), n_bins, window=window, kernel=kernel)
    zero = torch.zeros(n_bins, D, dtype=F64)
    s = _wls.prepare("test", r, r_dot, y, "y", 1, bins, zero, zero)
    sol = _wls.solve(s, design_blocks, P, fn="test", delta_max=None, ridge=ridge, min_samples=None,
                     max_condition=None, on_ill_conditioned="raise", correction=correction)
    return s, sol


def _bin_matrices(phase, x, n_bins, window, kernel, ridge, valid=None):
    """Per bin (dense, written out independently of the solver): the rows' sample indices
    ``(n_m,)``, weights ``(n_m,)``, ``A⁻¹`` of ``A = XᵀWX`` with the ridge ``λ (XᵀWX)ⱼⱼ`` on
    every column but the intercept, and ``X_m (n_m, P)``."""
    bins = assign_bins(phase, n_bins, window=window, kernel=kernel)
    out = []
    for m in range(n_bins):
        w = bins.weight[m].to(F64)
        if valid is not None:
            w = w * valid[bins.index[m]]
        keep = w > 0
        idx, w = bins.index[m][keep], w[keep]
        xm = x[idx]
        a = xm.T @ (w[:, None] * xm)
        penalty = ridge * a.diagonal().clone()
        penalty[0] = 0
        out.append((idx, w, torch.linalg.inv(a + torch.diag(penalty)), xm))
    return out


def _whitened_z(sample_cov, model_cov, n_rep):
    """``max |z|`` of ``L⁻¹ S L⁻ᵀ − I`` (``model_cov = LLᵀ``) in units of its sampling error."""
    chol = torch.linalg.cholesky(model_cov)
    white = torch.linalg.solve_triangular(
        chol, torch.linalg.solve_triangular(chol, sample_cov, upper=False).mT, upper=False)
    eye = torch.eye(model_cov.shape[-1], dtype=F64)
    return float(((white - eye) * math.sqrt(n_rep) / (1 + eye).sqrt()).abs().max())


def _empirical(coef):
    """Covariance ``(M, c, c)`` over replicates of the columns of ``coef (R, M, P, 1)``."""
    x = coef[:, :, COLUMNS, 0]
    x = x - x.mean(0)
    return torch.einsum("rmc,rme->mce", x, x) / (x.shape[0] - 1)


def _mean_z(per_rep, expected):
    """``max |z|`` of the replicates' mean of ``per_rep (R, ...)`` against ``expected``."""
    mean = per_rep.mean(0)
    se = per_rep.std(0) / math.sqrt(per_rep.shape[0])
    return float(((mean - expected) / se.clamp_min(1e-300)).abs().max())


def _corr(cov):
    sd = cov.diagonal(dim1=-2, dim2=-1).sqrt()
    return cov / (sd[..., :, None] * sd[..., None, :])


def test_sandwich_correlation_is_the_covariance_of_the_estimates_under_homoscedastic_noise():
    # Fixed regressors and errors of one variance: the coefficients' covariance is exactly
    # σ² A⁻¹(XᵀW²X)A⁻¹ (σ²(XᵀX)⁻¹ for 0/1 weights), so sandwich_correlation must equal its
    # correlation, written out per bin here, to rounding -- for overlapping 0/1 bins with
    # missing samples and for tricube weights with a ridge -- and the empirical
    # correlation of 2000 replicates' estimates within its sampling error ((1 − ρ²)/√R). Under
    # errors whose variance grows with |δ̇| the same correlation is rejected by that bound.
    gen = torch.Generator().manual_seed(11)
    n, n_rep = 240, 2000
    phase, r, r_dot, x, beta = _design(n, gen)
    valid = (torch.rand(n, generator=gen) > 0.15).to(F64)
    cases = [("box", 1.0, 0.0, valid), ("tricube", 1.5, 0.3, None)]
    for kernel, window, ridge, ok in cases:
        e = torch.randn(n_rep, n, 1, generator=gen, dtype=F64)
        y = x @ beta + 0.5 * e
        if ok is not None:
            y = torch.where(ok[:, None] > 0, y, torch.nan)
        rr, rd = r.expand(n_rep, n, D), r_dot.expand(n_rep, n, D)
        s, sol = _fit(phase, rr, rd, y, 4, window, kernel, ridge)
        assert bool((sol.ridge > 0).all()) == (ridge > 0)
        got = _wls.sandwich_correlation(s, design_blocks, sol, COLUMNS).reshape(n_rep, 4, C, C)
        # the design is fixed: every replicate's correlation is the same
        torch.testing.assert_close(got, got[:1].expand_as(got), rtol=0, atol=1e-12)
        closed = []
        for _, w, a_inv, xm in _bin_matrices(phase, x, 4, window, kernel, ridge, ok):
            closed.append(_corr((a_inv @ xm.T @ ((w**2)[:, None] * xm) @ a_inv)
                                [COLUMNS][:, COLUMNS]))
        closed = torch.stack(closed)
        torch.testing.assert_close(got[0], closed, rtol=0, atol=1e-10)
        emp = _corr(_empirical(sol.coef.reshape(n_rep, 4, P, 1)))
        z = (emp - closed) * math.sqrt(n_rep) / (1 - closed**2).clamp_min(1e-3)
        assert float(z.abs().max()) < _Z, (kernel, ridge, float(z.abs().max()))

    # heteroscedastic errors: the homoscedastic correlation is not theirs
    y = x @ beta + (0.2 + r_dot.square().sum(-1, keepdim=True)) * torch.randn(
        n_rep, n, 1, generator=gen, dtype=F64)
    s, sol = _fit(phase, r.expand(n_rep, n, D), r_dot.expand(n_rep, n, D), y, 4, 1.5, "tricube")
    got = _wls.sandwich_correlation(s, design_blocks, sol, COLUMNS).reshape(n_rep, 4, C, C)[0]
    emp = _corr(_empirical(sol.coef.reshape(n_rep, 4, P, 1)))
    z = (emp - got) * math.sqrt(n_rep) / (1 - got**2).clamp_min(1e-3)
    assert float(z.abs().max()) > 2 * _Z, float(z.abs().max())


def _score_expectation(bins, sigma, lags, beta):
    """Per bin of ``bins`` (:func:`_bin_matrices`), closed forms for fixed regressors and
    errors ``e`` of covariance ``sigma (n, n)``: the covariance of the estimates
    ``A⁻¹XᵀWΣWXA⁻¹``, and the expectation of score_covariance's
    ``A⁻¹ (Σ_{|t−s| ≤ lags} w_t w_s x_t x_sᵀ ê_t ê_s) A⁻¹ · n/(n − P)``
    with the residuals ``ê = (I − H)(Xβ + e)``, ``H = X A⁻¹XᵀW`` (with a ridge ``(I − H)Xβ``
    is its bias, not 0): ``E[êêᵀ] = (I − H)(Σ + Xββᵀ Xᵀ)(I − H)ᵀ``. Both ``(M, c, c)``."""
    truth, expected = [], []
    for idx, w, a_inv, xm in bins:
        n = idx.numel()
        sig = sigma[idx][:, idx]
        wx = w[:, None] * xm
        truth.append((a_inv @ wx.T @ sig @ wx @ a_inv)[COLUMNS][:, COLUMNS])
        resid = torch.eye(n, dtype=F64) - xm @ a_inv @ wx.T
        mean = xm @ beta
        e_res = resid @ (sig + mean @ mean.T) @ resid.T
        near = ((idx[:, None] - idx[None, :]).abs() <= lags).to(F64)
        middle = wx.T @ (e_res * near) @ wx
        expected.append((a_inv @ middle @ a_inv)[COLUMNS][:, COLUMNS] * n / (n - P))
    return torch.stack(truth), torch.stack(expected)


def test_score_covariance_is_its_closed_form_with_heteroscedastic_and_overlapping_rows():
    # Fixed regressors; errors whose standard deviation grows with |δ̇|, as a row's noise does
    # with the regressors' noise times the coefficients, and in the first case moving averages
    # over 3 samples (rows up to 2 samples apart correlated, as overlapping interval
    # differences are). Over 2000 replicates: the estimates' empirical covariance must be the
    # closed form A⁻¹XᵀWΣWXA⁻¹ (whitened, within its sampling error), and the mean of
    # score_covariance must be its own closed-form expectation (within the replicates'
    # standard error), for tricube weights with lags=2 and for 0/1 weights with missing
    # samples and a ridge with lags=0; with the overlap ignored (lags=0 on the moving
    # averages) the same bounds reject it. (That expectation is not the truth: an HC1
    # estimate, its n/(n − P) is exact only for rows of equal leverage. Here, 60-180 rows of
    # P = 9 columns with the noise largest where the leverage is, its variances are 0.53-1.05
    # of the true ones, mean 0.75-0.78; see score_covariance.)
    gen = torch.Generator().manual_seed(12)
    n, n_rep, n_bins, lags = 240, 2000, 4, 2
    phase, r, r_dot, x, beta = _design(n, gen)
    sd = 0.2 + r_dot.square().sum(-1)
    valid = (torch.rand(n, generator=gen) > 0.15).to(F64)
    band = ((torch.arange(n)[:, None] - torch.arange(n)[None, :]).abs() <= lags).to(F64)
    moving = band * (lags + 1 - (torch.arange(n)[:, None] - torch.arange(n)[None, :]).abs()
                     ) / (lags + 1)  # covariance of the 3-sample moving average
    for kernel, window, ridge, ok, lag in (("tricube", 1.5, 0.0, None, lags),
                                          ("box", 1.0, 0.05, valid, 0)):
        eps = torch.randn(n_rep, n + lag, generator=gen, dtype=F64)
        e = sum(eps[:, j:j + n] for j in range(lag + 1)) / math.sqrt(lag + 1)
        y = (x @ beta)[:, 0] + sd * e
        if ok is not None:
            y = torch.where(ok > 0, y, torch.nan)
        s, sol = _fit(phase, r.expand(n_rep, n, D), r_dot.expand(n_rep, n, D), y[..., None],
                      n_bins, window, kernel, ridge)
        got = _wls.score_covariance(s, design_blocks, sol, COLUMNS, lags=lag).reshape(
            n_rep, n_bins, C, C)
        sigma = sd[:, None] * sd[None, :] * (moving if lag else torch.eye(n, dtype=F64))
        mats = _bin_matrices(phase, x, n_bins, window, kernel, ridge, ok)
        truth, expected = _score_expectation(mats, sigma, lag, beta)
        emp = _empirical(sol.coef.reshape(n_rep, n_bins, P, 1))
        assert _whitened_z(emp, truth, n_rep) < _Z, (kernel, _whitened_z(emp, truth, n_rep))
        assert _mean_z(got, expected) < _Z, (kernel, _mean_z(got, expected))
        if lag:  # the overlap ignored
            _, alone = _score_expectation(mats, sigma, 0, beta)
            assert _mean_z(got, alone) > 2 * _Z, _mean_z(got, alone)
            assert _whitened_z(emp, alone, n_rep) > 2 * _Z


def test_score_covariance_with_the_correction_is_the_covariance_of_corrected_estimates():
    # Errors in the regressors, removed by the errors-in-variables correction: the latent
    # regressors are fixed (δ, δ̇ ∈ {±1}², the full factorial by sample index, so every row
    # has the same leverage and HC1's n/(n − P) is exact), and each replicate observes them
    # with noise of standard deviation 0.4 (a known variance, corrected for; the guard leaves
    # the correction whole) and the response with 0.1. Over 1200 replicates the corrected
    # estimates' empirical covariance must be the mean of score_covariance with each row's
    # share of the correction (eiv_row_correction), within its sampling error. Without that
    # share the scores are not centred and the same bound rejects it; the solver's sandwich
    # (sandwich_correlation times the standard errors: one residual variance for all rows)
    # leaves out the correction's own variance and is rejected by far (variances 1.2-1.9
    # times too small here).
    gen = torch.Generator().manual_seed(5)
    n, n_rep, n_bins, sd_r = 1200, 1200, 2, 0.4
    bits = torch.stack([(torch.arange(n) >> k) & 1 for k in range(4)], -1).to(F64) * 2 - 1
    r, r_dot = bits[:, :D], bits[:, D:]
    phase = 2 * math.pi * 3 * torch.arange(n, dtype=F64) / n
    x = torch.cat(design_blocks(r, r_dot, torch.ones(n, 1, dtype=F64)), -1)
    beta = torch.randn(P, 1, generator=gen, dtype=F64)
    r_obs = r + sd_r * torch.randn(n_rep, n, D, generator=gen, dtype=F64)
    r_dot_obs = r_dot + sd_r * torch.randn(n_rep, n, D, generator=gen, dtype=F64)
    y = x @ beta + 0.1 * torch.randn(n_rep, n, 1, generator=gen, dtype=F64)
    var = torch.full((n_rep * n_bins, D), sd_r**2, dtype=F64)

    def correction(gram, sel):
        return eiv_correction(gram, var[sel], var[sel])

    def row_correction(xw, b, sel):
        return eiv_row_correction(xw, b, var[sel], var[sel])

    s, sol = _fit(phase, r_obs, r_dot_obs, y, n_bins, 0.5, "box", correction=correction)
    assert bool((sol.eiv_scale == 1).all())
    emp = _empirical(sol.coef.reshape(n_rep, n_bins, P, 1))

    def mean(cov):
        return cov.reshape(n_rep, n_bins, C, C).mean(0)

    robust = mean(_wls.score_covariance(s, design_blocks, sol, COLUMNS, lags=0, correction=correction,
                                        row_correction=row_correction))
    assert _whitened_z(emp, robust, n_rep) < _Z, _whitened_z(emp, robust, n_rep)
    uncentred = mean(_wls.score_covariance(s, design_blocks, sol, COLUMNS, lags=0,
                                           correction=correction))
    assert _whitened_z(emp, uncentred, n_rep) > _Z, _whitened_z(emp, uncentred, n_rep)
    corr = _wls.sandwich_correlation(s, design_blocks, sol, COLUMNS, correction=correction)
    se = sol.se[:, COLUMNS, 0]
    solver = mean(corr * se[:, :, None] * se[:, None, :])
    assert _whitened_z(emp, solver, n_rep) > 2 * _Z, _whitened_z(emp, solver, n_rep)


def test_cluster_scores_are_each_cycles_share_of_the_error_written_out_per_bin():
    # cluster_scores (what Â's sampling factor is built from) against its closed form per bin,
    # written out here with dense matrices: A⁻¹ Σ_{t ∈ c} w_t x_t ê_t for the rows of cluster c
    # (ê the bin's residuals), for overlapping tricube bins with missing samples and a ridge,
    # on A's columns δ̇ and ∂A/∂r's. Over the clusters the shares sum to A⁻¹ Σ_t w_t x_t ê_t,
    # zero without a ridge (the normal equations), and Σ_c share_c share_cᵀ is the cluster-
    # robust sandwich A⁻¹ (Σ_c s_c s_cᵀ) A⁻¹: with one cluster per row it is score_covariance
    # at lags=0 without its n/(n − P).
    gen = torch.Generator().manual_seed(21)
    n, n_bins = 240, 4
    phase, r, r_dot, x, beta = _design(n, gen)
    valid = (torch.rand(n, generator=gen) > 0.15).to(F64)
    clusters = torch.div(torch.arange(n), 20, rounding_mode="floor")  # 12 "cycles"
    columns = torch.arange(1, P)
    for ridge in (0.0, 0.2):
        y = (x @ beta)[:, 0] + (0.2 + r_dot.square().sum(-1)) * torch.randn(
            n, generator=gen, dtype=F64)
        y = torch.where(valid > 0, y, torch.nan)
        s, sol = _fit(phase, r[None], r_dot[None], y[None, :, None], n_bins, 1.5, "tricube",
                      ridge)
        got = _wls.cluster_scores(s, design_blocks, sol, columns, clusters, 12)  # (M, 12, 1, c)
        closed = []
        for m, (idx, w, a_inv, xm) in enumerate(
                _bin_matrices(phase, x, n_bins, 1.5, "tricube", ridge, valid)):
            resid = y[idx] - xm @ sol.coef[m, :, 0]
            share = torch.zeros(12, P, dtype=F64).index_add_(
                0, clusters[idx], (w * resid)[:, None] * xm) @ a_inv
            closed.append(share[:, columns])
        closed = torch.stack(closed)
        torch.testing.assert_close(got[:, :, 0], closed, rtol=1e-9, atol=1e-12)
        total = got.sum(1).abs().max() / got.abs().max()
        assert (float(total) < 1e-9) == (ridge == 0), (ridge, float(total))
    per_row = _wls.cluster_scores(s, design_blocks, sol, columns, torch.arange(n), n)[:, :, 0]
    robust = _wls.score_covariance(s, design_blocks, sol, columns, lags=0)[:, 0]
    count = (s.weight > 0).sum(-1).to(F64)
    torch.testing.assert_close(per_row.mT @ per_row, robust * ((count - P) / count)[:, None, None],
                               rtol=1e-9, atol=0)


def test_cluster_scores_with_the_correction_sum_to_zero_over_the_clusters():
    # With the errors-in-variables correction the estimate solves Σ_t ψ_t = 0, ψ_t carrying
    # each row's share of the correction (eiv_row_correction): the clusters' shares of the
    # corrected estimates sum to zero only with that share (without it, to the correction
    # times β̂, far from zero).
    gen = torch.Generator().manual_seed(6)
    n, n_bins, sd_r = 400, 2, 0.3
    phase, r, r_dot, x, beta = _design(n, gen)
    r_obs = r + sd_r * torch.randn(n, D, generator=gen, dtype=F64)
    r_dot_obs = r_dot + sd_r * torch.randn(n, D, generator=gen, dtype=F64)
    y = x @ beta + 0.1 * torch.randn(n, 1, generator=gen, dtype=F64)
    var = torch.full((n_bins, D), sd_r**2, dtype=F64)

    def correction(gram, sel):
        return eiv_correction(gram, var[sel], var[sel])

    def row_correction(xw, b, sel):
        return eiv_row_correction(xw, b, var[sel], var[sel])

    s, sol = _fit(phase, r_obs[None], r_dot_obs[None], y[None], n_bins, 0.5, "box",
                  correction=correction)
    assert bool((sol.eiv_scale == 1).all())
    clusters = torch.div(torch.arange(n), 25, rounding_mode="floor")
    kw = dict(correction=correction)
    shares = _wls.cluster_scores(s, design_blocks, sol, COLUMNS, clusters, 16, **kw,
                                 row_correction=row_correction)
    plain = _wls.cluster_scores(s, design_blocks, sol, COLUMNS, clusters, 16, **kw)
    assert float(shares.sum(1).abs().max() / shares.abs().max()) < 1e-9
    assert float(plain.sum(1).abs().max() / plain.abs().max()) > 1e-2
