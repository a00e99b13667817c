"""The tied, noise-corrected metric regression: sample intervals, the errors-in-variables
correction, the noise estimate, accuracy and band coverage against the swimmer's exact metric,
and clear errors for data that cannot give a metric."""

import math

import pytest
import torch

from torchconn.phase.fourier import fourier_design
from torchconn.regression.metric import tied_metric_coefficients, tied_metric_predict, tied_metric_regression

F64 = torch.float64


# ----------------------------------------------------------------------------- EIV correction
def _constant_metric_data(n: int, noise_var: float, seed: int = 0):
    """Samples around a circle with a constant metric and exact power; noisy velocities."""
    g = torch.Generator().manual_seed(seed)
    m_true = torch.tensor([[2.0, 0.5], [0.5, 1.0]], dtype=F64)
    phase = torch.arange(n, dtype=F64) * (2 * math.pi / 64)
    gdot = torch.stack([-torch.sin(phase), torch.cos(phase)], -1)
    v = gdot + 0.3 * torch.randn(n, 2, generator=g, dtype=F64)
    power = torch.einsum("ni,ij,nj->n", v, m_true, v)
    v_obs = v + math.sqrt(noise_var) * torch.randn(n, 2, generator=g, dtype=F64)
    return m_true, phase, v_obs, power


def test_noise_correction_removes_the_errors_in_variables_bias():
    s = 0.05  # noise variance of the velocity, half the offsets' own 0.09
    m_true, phase, v_obs, power = _constant_metric_data(200_000, s)
    zeros = torch.zeros_like(v_obs)
    centres = torch.arange(8, dtype=F64) * (2 * math.pi / 8)
    gd_m = torch.stack([-torch.sin(centres), torch.cos(centres)], -1)
    fits = {}
    for name, nv in (("raw", None), ("corrected", torch.full((2,), s, dtype=F64))):
        fits[name] = tied_metric_regression(zeros, v_obs, power, phase, centres, gd_m, order=0,
                                            derivative_order=None, noise_variance=nv)
    z_raw = ((fits["raw"].M[0] - m_true) / fits["raw"].se_M[0]).abs()
    z_cor = ((fits["corrected"].M[0] - m_true) / fits["corrected"].se_M[0]).abs()
    print(f"|z| uncorrected {z_raw.max():.1f}, corrected {z_cor.max():.2f}")
    assert z_raw.max() > 10  # the bias is many standard errors
    assert z_cor.max() < 4  # gone, within the standard errors
    assert float(fits["corrected"].noise_correction.min()) == 1.0
    # M̂γ̇ and the on-cycle power are the same metric applied to γ̇
    f = fits["corrected"]
    torch.testing.assert_close(f.M_gamma_dot, (f.M @ gd_m[..., None])[..., 0])
    torch.testing.assert_close(f.power_on_cycle, (gd_m * f.M_gamma_dot).sum(-1))


def _harmonic_metric_data(n_cycles: int, harmonic: int, seed: int):
    """Samples with ``M(φ) = M0 + M1 cos(harmonic·φ)`` (Fourier order ``harmonic``), exact power
    plus white noise, 64 samples per cycle."""
    g = torch.Generator().manual_seed(seed)
    n = 64 * n_cycles
    phase = torch.arange(n, dtype=F64) * (2 * math.pi / 64)
    m0 = torch.tensor([[2.0, 0.5], [0.5, 1.0]], dtype=F64)
    m1 = torch.tensor([[0.3, -0.2], [-0.2, 0.25]], dtype=F64)
    m = m0 + torch.cos(harmonic * phase)[:, None, None] * m1
    v = torch.stack([-torch.sin(phase), torch.cos(phase)], -1)
    v = v + 0.3 * torch.randn(n, 2, generator=g, dtype=F64)
    power = torch.einsum("ni,nij,nj->n", v, m, v) + 0.05 * torch.randn(n, generator=g, dtype=F64)
    return phase, v, power


def test_held_out_order_equals_refits_on_the_other_blocks():
    """The order of M(φ) chosen from the blocks' normal equations is the one true refits
    without each block of whole cycles predict best, and it finds the metric's own order."""
    centres = torch.arange(8, dtype=F64) * (2 * math.pi / 8)
    gd = torch.stack([-torch.sin(centres), torch.cos(centres)], -1)
    data = [_harmonic_metric_data(40, 2, seed=0), _harmonic_metric_data(40, 0, seed=1)]
    chosen, alone = [], []
    for phase, v, power in data:
        zeros = torch.zeros_like(v)
        fit = tied_metric_regression(zeros, v, power, phase, centres, gd, order=4,
                                     derivative_order=None, held_out_order=True)
        # refits: five blocks of eight whole cycles, each held out in turn
        fold = torch.div(torch.floor(phase / (2 * math.pi)) * 5, 40, rounding_mode="floor")
        sse = torch.zeros(5, 5, dtype=F64)  # [block, order]
        for k in range(5):
            for b in range(5):
                train = torch.where((fold == b)[:, None], math.nan, v)
                coef = tied_metric_regression(zeros, train, power, phase, centres, gd, order=k,
                                              derivative_order=None).coef
                pred, _ = tied_metric_predict(coef, zeros, v, phase, order=k,
                                              derivative_order=None)
                sse[b, k] = ((power - pred)[fold == b]).square().sum()
        # the rule: the least total among the largest order and the lower orders that beat it
        # by more than one standard error of the per-block differences
        diff = sse - sse[:, -1:]
        beats = diff.sum(0) + (5 / 4 * (diff - diff.mean(0)).square().sum(0)).sqrt() < 0
        beats[-1] = True
        expected = int(torch.where(beats, sse.sum(0), math.inf).argmin())
        print(f"held-out SSE by order {sse.sum(0).numpy().round(3)}, chosen {int(fit.order)}")
        assert int(fit.order) == expected
        # the harmonics above the chosen order are zero
        assert bool((fit.coef[3 * (2 * int(fit.order) + 1):] == 0).all())
        chosen.append(int(fit.order))
        alone.append(fit)
    # the second harmonic is resolved where the metric has it (a spurious third may come in
    # by chance: 3 on this seed); nothing above the first where the metric is constant
    assert chosen[0] >= 2 and chosen[1] <= 1
    # each batch element chooses on its own data
    batch = [torch.stack(x) for x in zip(*data, strict=True)]
    fit = tied_metric_regression(torch.zeros_like(batch[1]), batch[1], batch[2], batch[0],
                                 centres, gd.expand(2, 8, 2), order=4, derivative_order=None,
                                 held_out_order=True)
    assert fit.order.tolist() == chosen
    # ... and fits as it does alone: alone it is solved at its own order's size, in the batch
    # the harmonics between its order and the other element's are kept as identity rows
    for i, one in enumerate(alone):
        for name in ("coef", "se_coef", "M", "se_M", "condition", "noise_correction"):
            torch.testing.assert_close(getattr(fit, name)[i], getattr(one, name), rtol=1e-9,
                                       atol=1e-12 * float(getattr(one, name).abs().max()))


def test_order_bias_is_the_change_at_two_more_harmonics():
    """``order_bias`` leaves M̂ alone and adds the outer product of the change of M̂ at two more
    harmonics of M(φ) (a refit at order K + 2) and that change's own variance to its
    covariance, per batch element at its own chosen order."""
    centres = torch.arange(8, dtype=F64) * (2 * math.pi / 8)
    gd = torch.stack([-torch.sin(centres), torch.cos(centres)], -1)
    phase, v, power = _harmonic_metric_data(40, 3, seed=2)
    zeros = torch.zeros_like(v)
    kw = dict(derivative_order=None)
    plain = tied_metric_regression(zeros, v, power, phase, centres, gd, order=2, **kw)
    wide = tied_metric_regression(zeros, v, power, phase, centres, gd, order=2, order_bias=True,
                                  **kw)
    richer = tied_metric_regression(zeros, v, power, phase, centres, gd, order=4, **kw)
    assert plain.bias_M is None
    assert torch.equal(wide.M, plain.M) and torch.equal(wide.coef, plain.coef)
    torch.testing.assert_close(wide.bias_M, richer.M - plain.M)
    # the third harmonic left out is a bias many standard errors large
    assert float((wide.bias_M.abs() / plain.se_M).max()) > 5
    torch.testing.assert_close(wide.se_M.square(), plain.se_M.square() + wide.bias_M.square()
                               + wide.se_bias_M.square())
    # M̂γ̇'s bands widen by at least the bias's square (and the change's variance beside it)
    bias_mgd = (wide.bias_M @ gd[..., None])[..., 0]
    assert bool((wide.se_M_gamma_dot.square()
                 >= (plain.se_M_gamma_dot.square() + bias_mgd.square()) * (1 - 1e-12)).all())
    # a batch: each element at its own held-out order (4 where the metric has the third
    # harmonic, lower where it is constant) and its own K + 2
    other = _harmonic_metric_data(40, 0, seed=1)
    batch = [torch.stack(x) for x in zip((phase, v, power), other, strict=True)]
    fit = tied_metric_regression(torch.zeros_like(batch[1]), batch[1], batch[2], batch[0],
                                 centres, gd.expand(2, 8, 2), order=4, held_out_order=True,
                                 order_bias=True, **kw)
    assert fit.order[0] > fit.order[1]
    for i in range(2):
        k = int(fit.order[i])
        one = [x[i] for x in batch]
        low, high = (tied_metric_regression(torch.zeros_like(one[1]), one[1], one[2], one[0],
                                            centres, gd, order=o, **kw) for o in (k, k + 2))
        torch.testing.assert_close(fit.bias_M[i], high.M - low.M, rtol=1e-7,
                                   atol=1e-10 * float(high.M.abs().max()))
    # too few samples for two more harmonics: a warning, the bands not widened
    phase, v, power = (x[:64] for x in _harmonic_metric_data(1, 3, seed=3))  # 45 <= 64 < 81
    zeros = torch.zeros_like(v)
    with pytest.warns(UserWarning, match="bands are not widened"):
        short = tied_metric_regression(zeros, v, power, phase, centres, gd, order=2,
                                       order_bias=True, **kw)
    assert short.bias_M is None
    torch.testing.assert_close(short.se_M, tied_metric_regression(
        zeros, v, power, phase, centres, gd, order=2, **kw).se_M, rtol=0, atol=0)


def test_order_change_covariance_is_the_change_s_sampling_covariance():
    """The K -> K + 2 change's own covariance (``order_change_cov``, from the two fits' joint
    influence per cycle) against the empirical covariance of the change over 400 replicates of
    one design that differ only in their power noise (model of order 2, fitted at 2 and 4: the
    change is pure noise). Treating the two fits as independent (the sum of their
    covariances) is rejected by the same bound. ``order_bias`` adds that variance to the
    bands."""
    n_rep, n_cycles = 400, 40
    phase, v, _ = _harmonic_metric_data(n_cycles, 2, seed=4)
    m = (torch.tensor([[2.0, 0.5], [0.5, 1.0]], dtype=F64) + torch.cos(2 * phase)[:, None, None]
         * torch.tensor([[0.3, -0.2], [-0.2, 0.25]], dtype=F64))
    exact = torch.einsum("ni,nij,nj->n", v, m, v)
    g = torch.Generator().manual_seed(5)
    power = exact + 0.05 * torch.randn(n_rep, exact.shape[0], generator=g, dtype=F64)
    rep = (n_rep, -1)
    kw = dict(order=2, derivative_order=None, order_bias=True)
    fit = tied_metric_coefficients(torch.zeros_like(v).expand(rep + (2,)), v.expand(rep + (2,)),
                                   power, phase.expand(rep), **kw)
    change = fit.order_change.flatten(-2)  # (R, W q)
    emp = change.var(0)
    model = fit.order_change_cov.diagonal(dim1=-2, dim2=-1).mean(0)
    live = model > 1e-6 * model.max()  # the harmonics both fits share or the richer one adds
    z = (emp[live] / model[live] - 1) / math.sqrt(2 / n_rep)
    print(f"variance of the change, empirical / modelled: {(emp[live] / model[live]).min():.3f}"
          f" - {(emp[live] / model[live]).max():.3f} (max |z| {z.abs().max():.2f})")
    assert float(z.abs().max()) < 5
    # no bias to find: the change averages to zero within 5 Monte Carlo standard errors
    assert float((change.mean(0)[live].abs() / emp[live].sqrt()).max()) < 5 / math.sqrt(n_rep)
    # the two fits taken as independent: their covariances summed, far too wide
    q, wide = 3, 2 * 4 + 1
    pad = torch.nn.functional.pad
    cov_low = pad(fit.cov[..., :5 * q, :5 * q], (0, (wide - 5) * q, 0, (wide - 5) * q))
    richer = tied_metric_coefficients(torch.zeros_like(v).expand(rep + (2,)),
                                      v.expand(rep + (2,)), power, phase.expand(rep), order=4,
                                      derivative_order=None)
    independent = (cov_low + richer.cov[..., :wide * q, :wide * q]).diagonal(
        dim1=-2, dim2=-1).mean(0)
    z_ind = (emp[live] / independent[live] - 1) / math.sqrt(2 / n_rep)
    assert float(z_ind.abs().max()) > 5
    # the widened bands: the plain ones, the change's square and its own variance (the
    # change's at the phases from its series covariance)
    centres = torch.arange(8, dtype=F64) * (2 * math.pi / 8)
    gd = torch.stack([-torch.sin(centres), torch.cos(centres)], -1)
    one = (torch.zeros_like(v), v, power[0], phase, centres, gd)
    plain = tied_metric_regression(*one, order=2, derivative_order=None)
    post = tied_metric_regression(*one, **kw)
    first = tied_metric_coefficients(*one[:4], **kw)
    design = fourier_design(centres, 4)  # (M, W)
    var_change = torch.einsum("mh,hapa,mp->ma", design, first.order_change_cov.unflatten(
        -1, (wide, q)).unflatten(0, (wide, q)), design)  # (M, q)
    iu, ju = torch.triu_indices(2, 2)
    assert torch.equal(post.M, plain.M)
    torch.testing.assert_close(post.se_bias_M[:, iu, ju].square()
                               * torch.where(iu == ju, 1.0, 4.0).to(F64), var_change)
    torch.testing.assert_close(post.se_M.square(), plain.se_M.square() + post.bias_M.square()
                               + post.se_bias_M.square())
    with pytest.raises(TypeError, match="order_bias must be True or False"):
        tied_metric_regression(*one, order=2, order_bias="posterior")


def test_change_factor_spans_the_change_s_covariance_across_entries_and_phases():
    """``MetricFit.change_factor_M`` (what nearby-gait draws use) against the closed form: the
    change's series covariance ``order_change_cov`` carried to the phases through the
    series' design, ``(B ⊗ I) Σ (B ⊗ I)ᵀ`` over every pair of (phase, entry), not only its
    diagonal; and that diagonal is ``se_bias_M²``, the variance the posterior bands add. The
    fit without ``order_bias`` stores no factor (its bands hold no such variance)."""
    phase, v, power = _harmonic_metric_data(40, 2, seed=4)
    centres = torch.arange(8, dtype=F64) * (2 * math.pi / 8)
    gd = torch.stack([-torch.sin(centres), torch.cos(centres)], -1)
    data = (torch.zeros_like(v), v, power, phase)
    kw = dict(order=2, derivative_order=None)
    coef = tied_metric_coefficients(*data, **kw, order_bias=True)
    post = coef.at(centres, gd)
    wide = fourier_design(centres, coef.order_change.shape[-2] // 2)  # (M, W)
    q = 3
    cov = coef.order_change_cov.unflatten(-1, (wide.shape[-1], q)).unflatten(0, (
        wide.shape[-1], q))
    closed = torch.einsum("mh,hapb,np->manb", wide, cov, wide)  # (M, q, M, q)
    iu, ju = torch.triu_indices(2, 2)
    scale = torch.where(iu == ju, 1.0, 2.0).to(F64)  # upper coefficients: M_kk, 2 M_kl
    f = post.change_factor_M[:, iu, ju, :] * scale[:, None]  # (M, q, R)
    got = torch.einsum("mar,nbr->manb", f, f)
    torch.testing.assert_close(got, closed, rtol=1e-9, atol=1e-12 * float(closed.abs().max()))
    torch.testing.assert_close(post.change_factor_M.square().sum(-1), post.se_bias_M.square())
    # the cross-phase terms are not negligible: a diagonal-only model would miss them
    off = closed.flatten(0, 1).flatten(1) - torch.diag(closed.flatten(0, 1).flatten(1).diagonal())
    assert float(off.abs().max()) > 0.5 * float(closed.flatten(0, 1).flatten(1).diagonal().max())
    assert tied_metric_regression(*data, centres, gd, **kw).change_factor_M is None


# ----------------------------------------------------------------------------- second order
def _second_order_metric_data(n_cycles: int, seed: int):
    """Exact power of a metric quadratic in the offsets, ``P = vᵀ[M0(φ) + M1_k δ_k +
    ½ H_kl δ_k δ_l] v``, with correlated Gaussian offsets of covariance ``S`` (no noise), and
    the intercept's closed-form bias when the quadratic term is left out: ``½ H : S``."""
    g = torch.Generator().manual_seed(seed)
    n = 64 * n_cycles
    phase = torch.arange(n, dtype=F64) * (2 * math.pi / 64)
    m0 = torch.tensor([[2.0, 0.5], [0.5, 1.0]], dtype=F64)
    m0 = m0 + torch.cos(phase)[:, None, None] * torch.tensor([[0.3, -0.2], [-0.2, 0.25]],
                                                              dtype=F64)
    m1 = torch.tensor([[[0.4, -0.1], [0.2, 0.3]], [[0.2, 0.3], [-0.5, 0.1]]], dtype=F64)
    h = torch.tensor([[[1.5, 0.4], [0.4, -0.8]], [[0.3, 1.1], [1.1, 0.6]],
                      [[0.3, 1.1], [1.1, 0.6]], [[-0.9, 0.2], [0.2, 2.0]]],
                     dtype=F64).reshape(2, 2, 2, 2)  # H[i, j, k, l] = ∂²M_ij/∂r_k∂r_l
    chol = torch.tensor([[0.08, 0.0], [0.03, 0.06]], dtype=F64)
    cov = chol @ chol.T
    delta = torch.randn(n, 2, generator=g, dtype=F64) @ chol.T
    v = torch.stack([-torch.sin(phase), torch.cos(phase)], -1)
    v = v + 0.3 * torch.randn(n, 2, generator=g, dtype=F64)
    m = m0 + torch.einsum("ijk,nk->nij", m1, delta) + 0.5 * torch.einsum(
        "ijkl,nk,nl->nij", h, delta, delta)
    power = torch.einsum("ni,nij,nj->n", v, m, v)
    return phase, delta, v, power, m0, 0.5 * torch.einsum("ijkl,kl->ij", h, cov)


def test_second_order_offset_term_removes_the_tube_s_bias_of_the_metric():
    """``M̂(φ)`` of the first-order tied model absorbs ``½ ∂²M/∂r² : E[δδᵀ]`` (the cause of
    ``predict_gait``'s cost bias on the swimmer, README "Is the cost standard error honest?"):
    on exact data its mean over the phases is the closed form within 10 % of it; with
    ``second_order="full"`` the fit is exact, with ``"diagonal"`` it is not (the offsets here
    are correlated); the allowance ``offset_bias`` is the change between the two fits."""
    phase, delta, v, power, m0, bias = _second_order_metric_data(100, seed=11)
    centres = torch.arange(8, dtype=F64) * (2 * math.pi / 8)
    gd = torch.stack([-torch.sin(centres), torch.cos(centres)], -1)
    truth = m0[:: 64 // 8][:8]  # M0 at the centres (64 samples per cycle, 8 bins)
    kw = dict(order=1, derivative_order=0)
    first = tied_metric_regression(delta, v, power, phase, centres, gd, **kw)
    full = tied_metric_regression(delta, v, power, phase, centres, gd, **kw, second_order="full")
    diag = tied_metric_regression(delta, v, power, phase, centres, gd, **kw,
                                  second_order="diagonal")
    err_first = first.M - truth
    print(f"first-order fit's error {err_first.mean(0).tolist()} against ½H:S {bias.tolist()}")
    torch.testing.assert_close(err_first.mean(0), bias, rtol=0,
                               atol=0.1 * float(bias.abs().max()))
    torch.testing.assert_close(full.M, truth, rtol=0, atol=1e-9)
    assert float((diag.M - truth).abs().max()) > 0.2 * float(bias.abs().max())
    coef = tied_metric_coefficients(delta, v, power, phase, **kw, offset_bias="full")
    torch.testing.assert_close(coef.at(centres, gd).offset_bias_M, full.M - first.M,
                               rtol=0, atol=1e-12)
    with pytest.raises(ValueError, match="second_order must be one of"):
        tied_metric_regression(delta, v, power, phase, centres, gd, **kw, second_order=2)


def test_sampling_factor_spans_the_fit_s_covariance_across_entries_and_phases():
    """``MetricFit.sampling_factor_M`` (what nearby-gait draws use for the fit's own noise)
    against the closed form: the coefficients' sandwich covariance ``cov`` carried to the
    phases, ``(B ⊗ I) Σ (B ⊗ I)ᵀ`` over every pair of (phase, entry); its diagonal is
    ``se_M²`` without a bias allowance."""
    phase, v, power = _harmonic_metric_data(40, 2, seed=4)
    centres = torch.arange(8, dtype=F64) * (2 * math.pi / 8)
    gd = torch.stack([-torch.sin(centres), torch.cos(centres)], -1)
    kw = dict(order=2, derivative_order=None)
    coef = tied_metric_coefficients(torch.zeros_like(v), v, power, phase, **kw)
    fit = coef.at(centres, gd)
    basis, q = fourier_design(centres, 2), 3
    cov = coef.cov[:5 * q, :5 * q].unflatten(-1, (5, q)).unflatten(0, (5, q))
    closed = torch.einsum("mh,hapb,np->manb", basis, cov, basis)
    iu, ju = torch.triu_indices(2, 2)
    scale = torch.where(iu == ju, 1.0, 2.0).to(F64)
    f = fit.sampling_factor_M[:, iu, ju, :] * scale[:, None]
    torch.testing.assert_close(torch.einsum("mar,nbr->manb", f, f), closed, rtol=1e-9,
                               atol=1e-12 * float(closed.abs().max()))
    torch.testing.assert_close(fit.sampling_factor_M.square().sum(-1), fit.se_M.square())


def test_unidentifiable_metric_is_a_clear_error():
    # shape velocity only along the gait: M is known only along γ̇, so the fit must refuse
    n = 4000
    phase = torch.arange(n, dtype=F64) * (2 * math.pi / 64)
    v = torch.stack([-torch.sin(phase), torch.cos(phase)], -1)
    power = (v * v).sum(-1)
    centres = torch.arange(8, dtype=F64) * (2 * math.pi / 8)
    gd = torch.stack([-torch.sin(centres), torch.cos(centres)], -1)
    with pytest.raises(ValueError, match="do not identify the metric"):
        tied_metric_regression(torch.zeros_like(v), v, power, phase, centres, gd, order=3,
                               derivative_order=None)
    with pytest.raises(ValueError, match="usable power samples"):
        tied_metric_regression(torch.zeros_like(v[:40]), v[:40], power[:40], phase[:40],
                               centres, gd, order=6, derivative_order=1)
