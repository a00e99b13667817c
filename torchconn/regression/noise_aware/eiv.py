"""The errors-in-variables solve: per-bin regression on interval samples with the joint
angles' measurement noise removed from the normal equations.

The noise's expected contribution to each bin's normal matrix ``XᵀWX`` for the design
``[1, δ, δ̇, δ̇⊗δ]`` is known in closed form from ``XᵀWX`` itself (:func:`eiv_correction`) and
is subtracted (the right-hand side needs no correction); the standard errors are inflated for
the rows' overlap (:func:`~torchconn.noise.overlap_inflation`).
"""

from __future__ import annotations

import dataclasses
import math
import warnings

import torch
from torch import Tensor

from ... import _linalg
from ...noise.intervals import IntervalSamples, overlap_inflation
from .. import _wls
from .._wls import IllConditionedBinWarning
from ..binning import BinIndex
from ..connection import ConnectionFit, design_blocks, fit_from_solution, ridge_exemptions

__all__ = ["eiv_correction", "eiv_row_correction", "noise_aware_regression", "sampling_factor",
           "bin_noise", "flagged_fit", "take_fit", "scatter_fits"]


def eiv_correction(gram: Tensor, var_delta: Tensor, var_rate: Tensor) -> Tensor:
    """Expected noise part of ``XᵀWX`` for the design ``[1, δ, δ̇, δ̇⊗δ]``.

    With observed ``δ̃ = δ + b``, ``δ̇̃ = δ̇ + a``, ``a, b`` independent of each other and of the
    signal, zero mean, diagonal variances ``Σ_b = diag(var_delta)``, ``Σ_a = diag(var_rate)``,
    the expectation of ``Σ w x̃x̃ᵀ`` exceeds ``Σ w xxᵀ`` by (``z_ij = δ̇_i δ_j``, sums over
    the bin's weighted rows, written with the observed sums that estimate them without bias)::

        [δ, δ]      Σw · Σ_b              [δ̇, δ̇]   Σw · Σ_a
        [δ_k, z_ij]  Σwδ̇̃_i · Σ_b,kj       [δ̇_k, z_ij]  Σwδ̃_j · Σ_a,ki
        [z_ij, z_kl] Σwδ̇̃_iδ̇̃_k Σ_b,jl + Σwδ̃_jδ̃_l Σ_a,ik − Σw Σ_a,ik Σ_b,jl

    Every observed sum it needs is an entry of ``gram`` itself.

    Args:
        gram: ``(b, P, P)`` observed ``XᵀWX``, ``P = 1 + 2d + d²``.
        var_delta, var_rate: ``(b, d)`` noise variances of ``δ`` and ``δ̇`` per bin.

    Returns:
        ``(b, P, P)``.
    """
    d = var_delta.shape[-1]
    sb, sa = var_delta, var_rate
    w = gram[:, 0, 0]
    s_delta = gram[:, 0, 1:1 + d]
    s_rate = gram[:, 0, 1 + d:1 + 2 * d]
    q_delta = gram[:, 1:1 + d, 1:1 + d]
    q_rate = gram[:, 1 + d:1 + 2 * d, 1 + d:1 + 2 * d]
    eye = torch.eye(d, dtype=gram.dtype, device=gram.device)
    out = torch.zeros_like(gram)
    out[:, 1:1 + d, 1:1 + d] = torch.diag_embed(w[:, None] * sb)
    out[:, 1 + d:1 + 2 * d, 1 + d:1 + 2 * d] = torch.diag_embed(w[:, None] * sa)
    # [δ_k, z_ij] = S_rate_i sb_k [j = k];  [δ̇_k, z_ij] = S_delta_j sa_k [i = k]
    # (broadcast products, not einsum: with opt_einsum installed every >= 3-operand einsum
    # searches a contraction path in Python; the factors multiply left to right as torch's
    # own einsum does, so the values are the same bit for bit)
    dz = ((sb[:, :, None, None] * s_rate[:, None, :, None]) * eye[:, None, :]).flatten(-2)
    rz = ((sa[:, :, None, None] * s_delta[:, None, None, :]) * eye[:, :, None]).flatten(-2)
    # indices b, i, j, k, l
    zz = ((q_rate[:, :, None, :, None] * sb[:, None, :, None, None]) * eye[:, None, :]
          + (q_delta[:, None, :, None, :] * sa[:, :, None, None, None]) * eye[:, None, :, None]
          - (((w[:, None, None] * sa[:, :, None]) * sb[:, None, :])[..., None, None]
             * eye[:, None, :, None]) * eye[:, None, :]).reshape(-1, d * d, d * d)
    z0 = 1 + 2 * d
    out[:, 1:1 + d, z0:] = dz
    out[:, 1 + d:z0, z0:] = rz
    out[:, z0:, 1:1 + d] = dz.mT
    out[:, z0:, 1 + d:z0] = rz.mT
    out[:, z0:, z0:] = zz
    return out


def eiv_row_correction(xw: Tensor, beta: Tensor, var_delta: Tensor, var_rate: Tensor
                       ) -> Tensor:
    """Each row's share of :func:`eiv_correction` times the coefficients: ``C(w x̃x̃ᵀ) β``
    ``(b, n, K, P)`` for the rows ``xw = √w [1, δ̃, δ̇̃, δ̇̃⊗δ̃] (b, n, P)`` and coefficients
    ``beta = [c, b, A, D] (b, P, K)`` (``D[i, j]`` on column ``δ̇_i δ_j``); summed over the
    rows, :func:`eiv_correction` of the bin's ``XᵀWX`` times ``β``. With ``u = √w``,
    ``ũ = u δ̃``, ``ṽ = u δ̇̃``::

        δ_k        σ²_b,k (u² b_k + u Σ_i ṽ_i D_ik)
        δ̇_k        σ²_a,k (u² A_k + u Σ_j ũ_j D_kj)
        δ̇_i δ_j   u ṽ_i σ²_b,j b_j + u ũ_j σ²_a,i A_i + σ²_b,j ṽ_i Σ_k ṽ_k D_kj
                   + σ²_a,i ũ_j Σ_l ũ_l D_il − u² σ²_a,i σ²_b,j D_ij

    Args:
        xw: ``(b, n, P)``; beta: ``(b, P, K)``; var_delta, var_rate: ``(b, d)`` as in
            :func:`eiv_correction`.
    """
    d = var_delta.shape[-1]
    u = xw[..., :1]  # (b, n, 1)
    ud, ur = xw[..., 1:1 + d], xw[..., 1 + d:1 + 2 * d]
    b_, a_ = beta[:, 1:1 + d], beta[:, 1 + d:1 + 2 * d]  # (b, d, K)
    dd = beta[:, 1 + 2 * d:].unflatten(1, (d, d))  # (b, i, j, K)
    sb, sa = var_delta[:, None, :, None], var_rate[:, None, :, None]  # (b, 1, d, 1)
    u2 = u.square().unsqueeze(-1)  # (b, n, 1, 1)
    uk = u.unsqueeze(-1)
    rate_d = torch.einsum("bni,bijk->bnjk", ur, dd)  # Σ_i ṽ_i D_ij: (b, n, j, K)
    delta_d = torch.einsum("bnj,bijk->bnik", ud, dd)  # Σ_j ũ_j D_ij: (b, n, i, K)
    row_delta = sb * (u2 * b_.unsqueeze(1) + uk * rate_d)  # (b, n, d, K)
    row_rate = sa * (u2 * a_.unsqueeze(1) + uk * delta_d)
    sb_j, sa_i = var_delta[:, None, None, :, None], var_rate[:, None, :, None, None]
    ur_i, ud_j = ur[..., :, None, None], ud[..., None, :, None]  # (b, n, i, 1, 1), (b, n, 1, j, 1)
    row_z = (uk.unsqueeze(-1) * (ur_i * sb_j * b_[:, None, None] + ud_j * sa_i * a_[:, None, :, None])
             + sb_j * ur_i * rate_d.unsqueeze(2) + sa_i * ud_j * delta_d.unsqueeze(3)
             - u2.unsqueeze(-1) * sa_i * sb_j * dd.unsqueeze(1))  # (b, n, i, j, K)
    out = torch.cat([torch.zeros_like(row_delta[..., :1, :]), row_delta, row_rate,
                     row_z.flatten(2, 3)], -2)  # (b, n, P, K)
    return out.mT


def noise_aware_regression(
    samples: IntervalSamples,
    bins: BinIndex,
    gamma_m: Tensor,
    gamma_dot_m: Tensor,
    noise_var: Tensor,
    *,
    delta_max: float | None = None,
    ridge: float = 0.0,
    on_ill_conditioned: str = "raise",
    joint_covariance: bool = False,
    ridge_connection: bool = True,
    cycles: Tensor | None = None,
) -> ConnectionFit:
    """Per-bin ``ξ ≈ c + bδ + Aδ̇ + ∂A/∂r (δ̇⊗δ)`` on interval samples, noise-corrected.

    Args:
        samples: :func:`interval_samples` ``(..., N, ·)``.
        bins: :func:`~torchconn.regression.assign_bins` of ``samples.phase``.
        gamma_m, gamma_dot_m: ``(..., M, d)`` limit cycle and ``γ̇`` at the bin centres.
        noise_var: ``(..., d)`` measurement-noise variance of each joint angle (broadcastable
            to the batch), e.g. :func:`estimate_noise`'s ``measurement²``.
        delta_max, ridge, on_ill_conditioned, ridge_connection: as in
            :func:`~torchconn.regression.connection_regression`.
        joint_covariance: also the joint covariance of each bin's ``b̂`` and direct
            ``∂Â/∂r`` (``cov_b_dA``, for the tie): the sandwich whose diagonal gives the
            standard errors (:func:`~torchconn.regression._wls.sandwich_correlation` times
            them, overlap inflation included). The fit's other fields are the same bit for
            bit. Default False.
        cycles: ``(..., N)`` int64, the whole cycle each sample belongs to (e.g.
            :func:`~torchconn.cycles.cycle_index`), numbered from 0 within the batch element: also each
            cycle's share of the error of ``Â`` (``influence_A``, ``(..., M, 3, d, C)``,
            :func:`~torchconn.regression._wls.cluster_scores` with the rows' noise
            correction): rows of one cycle are correlated (the filter's overlap, the phase
            noise) and one cycle's rows fall in every bin, so its shares carry the
            correlation of ``Â`` across entries and bins. The fit's other fields are the same
            bit for bit.

    Returns:
        :class:`~torchconn.regression.ConnectionFit`. The standard errors are the solver's
        (rows independent) times ``√κ`` for the rows' overlap (:func:`overlap_inflation`; 1
        for the box filter).
    """
    fn = "noise_aware_regression"
    s = _wls.prepare(fn, samples.r, samples.r_dot, samples.xi, "xi", 3, bins, gamma_m,
                     gamma_dot_m)
    d = s.r.shape[-1]
    if not isinstance(noise_var, Tensor) or noise_var.shape[-1:] != (d,):
        raise ValueError(f"{fn}: noise_var must be a tensor (..., d) with d = {d}, got "
                         f"{getattr(noise_var, 'shape', type(noise_var).__name__)}")
    if bool((noise_var < 0).any()) or not bool(torch.isfinite(noise_var).all()):
        raise ValueError(f"{fn}: noise_var must be finite and >= 0")
    p = 1 + 2 * d + d * d
    m = s.n_bins
    var_delta, var_rate = bin_noise(samples, s, noise_var)

    def correction(gram: Tensor, sel) -> Tensor:
        return eiv_correction(gram, var_delta[sel], var_rate[sel])

    def row_correction(xw: Tensor, beta: Tensor, sel) -> Tensor:
        return eiv_row_correction(xw, beta, var_delta[sel], var_rate[sel])

    free = ridge_exemptions(d, ridge_connection, s.r.device)
    sol = _wls.solve(s, design_blocks, p, fn=fn, delta_max=delta_max, ridge=ridge, min_samples=None,
                     max_condition=None, on_ill_conditioned=on_ill_conditioned,
                     correction=correction, unpenalised=free)
    kappa = overlap_inflation(bins, samples.h, samples.kernel).to(sol.se).reshape(-1, 1, 1)
    se = sol.se * kappa.sqrt()  # (B·M, P, K)
    cov = None
    if joint_covariance:
        # b̂'s columns δ and the direct estimate's δ̇⊗δ (connection_design's order)
        columns = torch.cat([torch.arange(1, 1 + d, device=s.r.device),
                             torch.arange(1 + 2 * d, p, device=s.r.device)])
        corr = _wls.sandwich_correlation(s, design_blocks, sol, columns, delta_max=delta_max,
                                         correction=correction, unpenalised=free)
        se_c = se[:, columns].mT  # (B·M, K, c)
        cov = corr.unsqueeze(1) * (se_c.unsqueeze(-1) * se_c.unsqueeze(-2))
        cov = cov.reshape(s.batch_shape + (m,) + cov.shape[1:])
    influence = None
    if cycles is not None:
        if (not isinstance(cycles, Tensor) or cycles.shape != samples.phase.shape
                or cycles.dtype != torch.int64):
            raise ValueError(f"{fn}: cycles must be an int64 tensor of the samples' phase shape "
                             f"{tuple(samples.phase.shape)}, got "
                             f"{getattr(cycles, 'shape', type(cycles).__name__)}")
        n_c = int(cycles.max()) + 1 if cycles.numel() else 1
        # a bin's rows are all its own element's: the elements' cycle numbers need no offset
        flat = cycles.clamp_min(0).reshape(-1).to(s.rows.device)
        a_cols = torch.arange(1 + d, 1 + 2 * d, device=s.r.device)
        shares = _wls.cluster_scores(s, design_blocks, sol, a_cols, flat, n_c, delta_max=delta_max,
                                     correction=correction, row_correction=row_correction,
                                     unpenalised=free)  # (B·M, C, 3, d)
        influence = shares.permute(0, 2, 3, 1).reshape(s.batch_shape + (m, 3, d, n_c))
    sol = dataclasses.replace(sol, se=se).unflatten(s.batch_shape, m)
    return dataclasses.replace(fit_from_solution(sol, d), cov_b_dA=cov, influence_A=influence)


def sampling_factor(influence: Tensor, se: Tensor) -> Tensor:
    """A factor ``(..., M, 3, d, R)`` of ``Â``'s sampling covariance across entries and bins
    with the cycles' shares' correlation and the diagonal ``se²``: ``influence (..., M, 3, d,
    C)`` (``ConnectionFit.influence_A``) with each entry's row scaled to its standard error
    ``se (..., M, 3, d)``, compressed by an SVD to the ``R ≤ C`` directions whose variance
    exceeds ``1e-14`` of the largest. Entries without a finite standard error or any share
    get zeros (they are then drawn on their own, from ``se``).

    The standard errors are the fit's (the solver's, calibrated against the swimmer, and
    what the bands show); the shares give what they cannot: how the errors of one bin's
    entries, and of different bins, move together."""
    norm = influence.square().nansum(-1).sqrt()
    ok = torch.isfinite(se) & (norm > 0) & torch.isfinite(norm)
    scale = torch.where(ok, se / torch.where(ok, norm, 1.0), 0.0)
    factor = torch.nan_to_num(influence) * scale.unsqueeze(-1)
    flat = factor.flatten(-4, -2)  # (..., E, C)
    u, sv, _ = _linalg.svd(flat, "the bands' error factor")
    kept = sv > 1e-7 * sv[..., :1]
    rank = max(int(kept.sum(-1).max()), 1) if kept.numel() else 1
    return (u[..., :rank] * sv[..., None, :rank]).unflatten(-2, factor.shape[-4:-1])


def bin_noise(samples: IntervalSamples, s: _wls.BinnedSamples, noise_var: Tensor
               ) -> tuple[Tensor, Tensor]:
    """The noise variances ``(B·M, d)`` of ``δ`` and ``δ̇`` in every bin of the prepared
    interval samples ``s`` (:func:`noise_aware_regression`'s), from the joints' measurement
    noise ``noise_var (..., d)`` and the interval filter's gains."""
    d, m = s.r.shape[-1], s.n_bins
    batch = tuple(s.batch_shape)
    var = noise_var.to(s.r).expand(batch + (d,))
    var_bins = var.unsqueeze(-2).expand(batch + (m, d)).reshape(-1, d)
    g_delta, g_rate = samples.noise_gains()
    return var_bins * g_delta, var_bins * g_rate


def flagged_fit(args: tuple, opts: dict) -> tuple[ConnectionFit, Tensor]:
    """:func:`noise_aware_regression` ``(*args, **opts)`` with the bins it cannot fit left NaN
    (no warning, whatever ``on_ill_conditioned``) and ``(...)`` whether each batch element has
    such a bin. An element without one gets what ``opts`` would give it, bit for bit."""
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", IllConditionedBinWarning)
        fit = noise_aware_regression(*args, **{**opts, "on_ill_conditioned": "warn"})
    p = fit.coef.shape[-2]
    return fit, _wls.unfittable(fit.n_samples, fit.condition, p, fit.coef.dtype).any(-1)


def take_fit(fit: ConnectionFit, sel: Tensor) -> ConnectionFit:
    """Batch elements ``sel`` of a fit with one batch dim."""
    return dataclasses.replace(fit, **{f.name: getattr(fit, f.name)[sel]
                                       for f in dataclasses.fields(fit)
                                       if getattr(fit, f.name) is not None})


def scatter_fits(parts, n: int, batch: tuple) -> ConnectionFit:
    """One fit ``(*batch, M, ·)`` from fits of subsets ``(len(idx), M, ·)`` of ``n`` elements.
    A field that only some parts carry (``cov_b_dA``: only groups with detected noise) is NaN
    for the elements of the others; None where no part carries it."""
    out = {}
    for f in dataclasses.fields(ConnectionFit):
        given = [(idx, getattr(fit, f.name)) for idx, fit in parts
                 if getattr(fit, f.name) is not None]
        if not given:
            out[f.name] = None
            continue
        ref = given[0][1]
        full = ref.new_full((n,) + ref.shape[1:], 0 if len(given) == len(parts) else math.nan)
        for idx, value in given:
            full[idx] = value
        out[f.name] = full.reshape(batch + ref.shape[1:])
    return ConnectionFit(**out)
