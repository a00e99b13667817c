"""``∂Â/∂r`` tied to the terms that identify most of it far better.

A bin's regression (:func:`~torchconn.regression.connection_regression`, the noise-aware
one alike) estimates ``∂A/∂r`` directly from its ``δ̇⊗δ`` columns, the weakest of the design.
Two better-identified estimates hold contractions of it: the offset term ``b̂ =
∂A/∂r γ̇`` (on the velocity index) and, along the cycle, the phase derivative of ``Â``
(``dÂ/dφ = ∂A/∂r γ'``, the chain rule, on the position index). :func:`tie_connection_derivative`
combines the three by generalised least squares per bin (docs/validation/ holds its accuracy
under noise).
"""

from __future__ import annotations

import dataclasses
import math

import torch
from torch import Tensor

from ..phase.fourier import fit_fourier
from .binning import kernel_weight
from .connection import ConnectionFit

__all__ = ["tie_connection_derivative", "phase_derivative_operator", "cycle_tangent",
           "window_correlation", "lag_correlations"]


def window_correlation(window: float, kernel: str, device=None) -> tuple[Tensor, Tensor]:
    """Integer lags ``s (L,)`` (bin spacings, ``|s| ≤ ⌈2·window⌉``) and the correlation
    ``ρ(s) (L,)`` of the estimation errors of two bins ``s`` spacings apart: the overlap of
    their windows, ``∫K(x)K(x − s)dx / ∫K²`` (float64)."""
    opts = dict(dtype=torch.float64, device=device)
    grid = torch.linspace(-window, window, 801, **opts)
    kern = kernel_weight(grid.abs() / window, kernel)
    step = float(grid[1] - grid[0])
    lags = torch.arange(-math.ceil(2 * window), math.ceil(2 * window) + 1, **opts)
    # a shift beyond the grid (the last lag, ⌈2w⌉ > 2w for a width that is not a whole or
    # half spacing) has no overlap; clamped, its slices are empty
    shift = torch.round(lags / step).long().clamp(-len(kern), len(kern))
    norm = float(kern.square().sum())
    rho = torch.stack([(kern[max(0, int(j)):len(kern) + min(0, int(j))]
                        * kern[max(0, -int(j)):len(kern) - max(0, int(j))]).sum()
                       for j in shift]) / norm
    return lags, rho


def phase_derivative_operator(n_bins: int, order: int, *, dtype=torch.float64,
                              device=None) -> Tensor:
    """``D (M, M)``: the phase derivative at the bin centres ``φ_m = 2πm/M`` of the order-
    ``order`` least-squares Fourier series through one value per bin (``D[m, n]``: the
    weight of bin ``n``'s value in the derivative at centre ``m``), as the model's series
    (:func:`~torchconn.phase.fit_fourier`) give it."""
    centres = torch.arange(n_bins, dtype=dtype, device=device) * (2 * math.pi / n_bins)
    eye = torch.eye(n_bins, dtype=dtype, device=device)
    return fit_fourier(centres, eye, order, value_ndim=1).derivative()(centres)


def lag_correlations(window: Tensor, kernel: str, *, dtype=torch.float64, device=None
                      ) -> tuple[list[int], Tensor]:
    """Integer lags ``(L,)`` (bin spacings, symmetric about 0) and the correlation ``ρ (..., L)``
    of two bins' estimation errors at each lag (:func:`window_correlation`) for bins of
    half-width ``window (...)`` (0 beyond a window's own reach)."""
    widths = window.to(torch.float64)
    reach = math.ceil(2 * float(widths.max()))
    lags = list(range(-reach, reach + 1))
    rho = torch.zeros(widths.shape + (len(lags),), dtype=dtype, device=device)
    for w in torch.unique(widths).tolist():  # few distinct windows
        own, values = window_correlation(w, kernel, device)
        row = torch.zeros(len(lags), dtype=dtype, device=device)
        row[[lag + reach for lag in own.long().tolist()]] = values.to(dtype)
        rho[widths.to(rho.device) == w] = row
    return lags, rho


def cycle_tangent(gamma_m: Tensor) -> Tensor:
    """``γ'(φ_m) (..., M, d)``: the phase derivative at the bin centres of the cycle through
    ``gamma_m (..., M, d)`` (its Fourier series of the highest order the centres carry, as
    :func:`~torchconn.regression.noise_aware.bin_bias_correction` interpolates it; each batch
    element's own, bit for bit)."""
    m = gamma_m.shape[-2]
    op = phase_derivative_operator(m, (m - 1) // 2, dtype=gamma_m.dtype, device=gamma_m.device)
    return (op.unsqueeze(-1) * gamma_m.unsqueeze(-3)).sum(-2)


#: significant bits kept of the tie's weights (:func:`_coarse`)
_WEIGHT_BITS = 20


def _coarse(x: Tensor) -> Tensor:
    """``x`` rounded to :data:`_WEIGHT_BITS` significant bits (exactly: frexp, round, ldexp).
    The standard errors round in their last bits with an unpooled batch's padded bin length
    (the solver's row sums); weights built on them, so rounded, give each element the same
    tie alone as beside other trials, bit for bit."""
    mantissa, exponent = torch.frexp(x)
    return torch.ldexp(torch.round(mantissa * 2.0**_WEIGHT_BITS) / 2.0**_WEIGHT_BITS,
                       exponent.to(x.dtype))


def _tie_design(gamma_dot_m: Tensor) -> Tensor:
    """``H (..., M, d + d², d²)``: ``(b̂, vec ∂A/∂r) = H vec ∂A/∂r`` per bin and row, ``b̂_j =
    Σ_i D[i, j] γ̇_i`` over the identity (``vec`` row-major, ``(i, j)``)."""
    d = gamma_dot_m.shape[-1]
    eye = torch.eye(d, dtype=gamma_dot_m.dtype, device=gamma_dot_m.device)
    velocity = (gamma_dot_m[..., :, None, None] * eye).flatten(-3, -2).transpose(-1, -2)
    return torch.cat([velocity, torch.eye(d * d, dtype=eye.dtype, device=eye.device).expand(
        gamma_dot_m.shape[:-1] + (d * d, d * d))], -2)


def tie_connection_derivative(fit: ConnectionFit, gamma_m: Tensor, gamma_dot_m: Tensor,
                              order: int, *, window: float | Tensor, kernel: str,
                              consistency: bool = True, correlation: bool = False
                              ) -> ConnectionFit:
    """``fit`` with ``∂Â/∂r`` tied to the terms that identify most of it far better.

    With ``D = ∂Aᵏ/∂r`` at a bin (``D[i, j] = ∂Aᵏ_i/∂r_j``), the bin's other estimates hold
    two contractions of it: ``b̂ᵏ_j = Σ_i D[i, j] γ̇_i`` (the offset term, on the velocity
    index) and, along the cycle, the phase derivative of the connection ``dÂᵏ_i/dφ =
    Σ_j D[i, j] γ'_j`` (the chain rule, on the position index). Together they fix ``2d − 1``
    of the ``d²`` entries, and the direct estimate (the ``δ̇⊗δ`` rows, the weakest of the
    design) is needed only for the ``(d − 1)²`` across-cycle pairs. Per bin and output row,
    ``D`` is the generalised least-squares solution of the three (direct, ``b̂``, ``dÂ/dφ``)
    with weights their inverse variances; its standard errors are the solution's. ``b̂`` and
    the direct estimate come from one regression, and their errors are correlated: with
    ``fit.cov_b_dA`` (their joint covariance per bin and row) the solution's variance is
    taken under it (the sandwich ``N⁻¹HᵀWΣWHN⁻¹`` of the independent weights ``W``);
    ``dÂ/dφ`` (a series through many bins) is taken as independent of both.

    ``dÂ/dφ`` is the derivative of ``Â``'s order-``order`` Fourier series
    (:func:`phase_derivative_operator`), its variance propagated through that series from the
    bins' standard errors and their correlation (:func:`window_correlation`).

    Args:
        fit: per-bin fit ``(..., M, ·)`` (``cov_b_dA``, where given, ``(..., M, 3, d + d²,
            d + d²)``: where not finite in a bin and row, the solution's own variance is
            used there).
        gamma_m, gamma_dot_m: ``(..., M, d)`` the cycle and ``γ̇ = φ̇ γ'`` at the centres.
        order: the Fourier order of ``Â``'s series.
        window, kernel: the bins' half-width (a number, or ``(...)`` per batch element) and
            weights, for the bins' correlation.
        consistency: widen the standard errors by ``√(χ²/dof)`` (never narrow them) where the
            three sources disagree beyond their standard errors: ``χ²`` of the sources about
            the tied solution summed over the bins and rows of each batch element, ``dof``
            their ``2d`` redundant equations per bin and row (the Birge ratio). The bins' bias
            shows as such a disagreement (the phase derivative of ``Â`` is nearly free of it).
        correlation: also the correlation of the tied entries of each bin and row
            (``corr_dA``, ``(..., M, 3, d², d²)``, ``vec D`` row-major: entry ``i·d + j`` is
            ``D[i, j]``), from the solution's covariance (the sandwich's where it is taken):
            the tie pins ``D γ̇`` and ``D γ'`` far better than the entries one by one, so the
            entries' errors are strongly correlated. Identity where the normal matrix cannot
            be factorised. The tied estimate and its standard errors are the same bit for bit.

    Returns:
        the fit with ``dA`` and ``se_dA`` tied (other fields unchanged). Non-finite estimates
        enter with no weight (an element with a NaN bin of ``Â`` is tied to ``b̂`` alone); a
        bin and row whose normal matrix cannot be factorised keeps the direct estimate.
    """
    d = fit.A.shape[-1]
    opts = dict(dtype=fit.A.dtype, device=fit.A.device)
    slope, var_slope, usable = _phase_slope(fit, order, window, kernel)
    w_d, direct = _inverse_variance(fit.se_dA.square(), fit.dA, True)  # (..., M, 3, d, d)
    w_b, b = _inverse_variance(fit.se_b.square(), fit.b, True)  # (..., M, 3, d)
    w_s, slope = _inverse_variance(var_slope, slope, usable[..., None, None, None])
    tangent = cycle_tangent(gamma_m).expand(gamma_dot_m.shape)
    normal, rhs, slope_normal = _tie_normal_equations(w_d, direct, w_b, b, w_s, slope,
                                                      gamma_dot_m, tangent)
    chol, info = torch.linalg.cholesky_ex(normal)
    good = (info == 0).unsqueeze(-1)
    safe = torch.where(good.unsqueeze(-1), chol, torch.eye(d * d, **opts))
    solution = torch.cholesky_solve(rhs.unsqueeze(-1), safe).squeeze(-1)
    n_inv = torch.cholesky_inverse(safe)
    var = torch.diagonal(n_inv, dim1=-2, dim2=-1)
    cov_full = n_inv if correlation else None  # (..., M, 3, d², d²)
    if fit.cov_b_dA is not None:
        var, cov_full = _sandwich(fit.cov_b_dA, n_inv, var, cov_full, w_b, w_d, slope_normal,
                                  gamma_dot_m)
    if consistency:
        fitted = torch.where(good, solution, 0.0).unflatten(-1, (d, d))
        ratio = _birge_ratio(fitted, (w_d, direct), (w_b, b), (w_s, slope), gamma_dot_m,
                             tangent)
        var = var * ratio.clamp_min(1).reshape(ratio.shape + (1, 1, 1))
    # a normal matrix that cannot be factorised (weights spanning ~1e16) keeps the direct
    # estimate
    shape = fit.dA.shape
    tied = torch.where(good, solution, fit.dA.flatten(-2)).reshape(shape)
    se = torch.where(good, var.clamp_min(0).sqrt(), fit.se_dA.flatten(-2)).reshape(shape)
    corr = None if cov_full is None else _correlation_of(cov_full, good)
    return dataclasses.replace(fit, dA=tied, se_dA=se, corr_dA=corr)


def _phase_slope(fit: ConnectionFit, order: int, window: float | Tensor, kernel: str
                 ) -> tuple[Tensor, Tensor, Tensor]:
    """``dÂ/dφ`` at the bin centres ``(..., M, 3, d)`` (the order-``order`` series'
    derivative, :func:`phase_derivative_operator`), its variance (same shape; the bins'
    standard errors correlated over overlapping windows, :func:`lag_correlations`) and which
    batch elements ``(...)`` have a finite ``Â`` and ``se_A`` in every bin."""
    a, se_a = fit.A, fit.se_A
    m = a.shape[-3]
    opts = dict(dtype=a.dtype, device=a.device)
    op = phase_derivative_operator(m, order, **opts)
    usable = (torch.isfinite(a) & torch.isfinite(se_a)).flatten(-3).all(-1)  # (...)
    a0 = torch.where(usable[..., None, None, None], a, 0.0)
    s0 = torch.where(usable[..., None, None, None], se_a, 0.0)
    # products and sums along fixed dims only (no matrix products, whose rounding follows
    # the batch's size): an unpooled element's tie is its own, bit for bit
    slope = (op[:, :, None, None] * a0.unsqueeze(-4)).sum(-3)  # (..., M, 3, d)
    # var(Σ_n op[m, n] Â_n) = Σ_n Σ_s op[m, n] op[m, n + s] ρ(s) se_n se_{n+s}, per entry
    weighted = op[:, :, None, None] * s0.unsqueeze(-4)  # (..., M, M, 3, d)
    widths = torch.as_tensor(window, dtype=torch.float64, device=a.device)
    lags, rho = lag_correlations(widths.expand(a.shape[:-3]), kernel,
                                  **opts)
    var_slope = torch.zeros_like(slope)
    for i, lag in enumerate(lags):
        var_slope = var_slope + rho[..., i, None, None, None] * (
            weighted * weighted.roll(-lag, -3)).sum(-3)
    return slope, var_slope, usable


def _inverse_variance(var: Tensor, value: Tensor, ok) -> tuple[Tensor, Tensor]:
    """The weight ``1/var`` (rounded, :func:`_coarse`) and ``value``, both 0 where ``ok`` is
    false or either is not finite or ``var`` not positive."""
    ok = ok & torch.isfinite(var) & torch.isfinite(value) & (var > 0)
    return (_coarse(torch.where(ok, 1 / var.clamp_min(1e-300), 0.0)),
            torch.where(ok, value, 0.0))


def _tie_normal_equations(w_d: Tensor, direct: Tensor, w_b: Tensor, b: Tensor, w_s: Tensor,
                          slope: Tensor, gamma_dot_m: Tensor, tangent: Tensor
                          ) -> tuple[Tensor, Tensor, Tensor]:
    """The tie's normal matrix ``N (..., M, 3, d², d²)`` over ``vec D``, its right-hand side
    ``(..., M, 3, d²)``, and the part of ``N`` from the phase derivative ``(..., M, 3, d²,
    d²)``, for the weighted sources (direct, ``b̂``, ``dÂ/dφ``)."""
    d = gamma_dot_m.shape[-1]
    eye = torch.eye(d, dtype=w_d.dtype, device=w_d.device)
    # the normal matrix over vec(D), dims (i, j, i', j'): direct (diagonal), + w_b[j] γ̇_i γ̇_i'
    # [j = j'], + w_s[i] γ'_j γ'_j' [i = i']
    velocity = gamma_dot_m.unsqueeze(-2)  # (..., M, 1, d) against the rows k
    along = tangent.unsqueeze(-2)
    v_i, v_l = gamma_dot_m[..., None, :, None, None, None], gamma_dot_m[..., None, None, None, :, None]
    t_j, t_q = tangent[..., None, None, :, None, None], tangent[..., None, None, None, None, :]
    slope_normal = (w_s[..., None, None, None] * (t_j * t_q) * eye[:, None, :, None]
                    ).flatten(-4, -3).flatten(-2)  # (..., M, 3, d², d²)
    slope_rhs = ((w_s * slope).unsqueeze(-1) * along.unsqueeze(-2)).flatten(-2)
    normal = (torch.diag_embed(w_d.flatten(-2)).unflatten(-1, (d, d)).unflatten(-3, (d, d))
              + w_b[..., None, :, None, None] * (v_i * v_l) * eye[:, None, :]
              ).flatten(-4, -3).flatten(-2) + slope_normal
    rhs = ((w_d * direct) + (w_b * b).unsqueeze(-2) * velocity.unsqueeze(-1)
           ).flatten(-2) + slope_rhs
    return normal, rhs, slope_normal


def _sandwich(cov_b_dA: Tensor, n_inv: Tensor, var: Tensor, cov_full: Tensor | None,
              w_b: Tensor, w_d: Tensor, slope_normal: Tensor, gamma_dot_m: Tensor
              ) -> tuple[Tensor, Tensor | None]:
    """The tied estimate's variance ``(..., M, 3, d²)`` (and, given ``cov_full``, its
    covariance) under the joint covariance ``Σ = cov_b_dA`` of ``b̂`` and the direct
    estimate: ``N⁻¹ (HᵀWΣWH + the slope's part of N) N⁻¹`` with ``W`` the independent
    weights; ``var`` and ``cov_full`` (``N⁻¹``'s) kept where ``Σ`` is not finite."""
    w_ind = torch.cat([w_b, w_d.flatten(-2)], -1)  # (..., M, 3, c)
    cov = _coarse(cov_b_dA)
    finite = torch.isfinite(cov).all(-1).all(-1)
    cov = torch.where(finite[..., None, None], cov, 0.0)
    # as matrix products: the elementwise sums materialised (..., c, c, d²) and
    # (..., d², d², d²) tensors, 0.5 GB per trial on the 9-link (d = 8); only the bands
    # depend on it, and they round with the batch anyway (the solver's row sums)
    g = w_ind.unsqueeze(-1) * _tie_design(gamma_dot_m).unsqueeze(-3)  # WH (..., c, d²)
    meat = g.mT @ (cov @ g) + slope_normal  # (..., M, 3, d², d²)
    var = torch.where(finite.unsqueeze(-1), ((n_inv @ meat) * n_inv).sum(-1), var)
    if cov_full is not None:
        cov_full = torch.where(finite[..., None, None], n_inv @ meat @ n_inv, n_inv)
    return var, cov_full


def _birge_ratio(fitted: Tensor, direct: tuple[Tensor, Tensor], b: tuple[Tensor, Tensor],
                 slope: tuple[Tensor, Tensor], gamma_dot_m: Tensor, tangent: Tensor
                 ) -> Tensor:
    """``χ²/dof`` ``(...)`` of the three sources (each ``(weight, value)``) about the tied
    solution ``fitted (..., M, 3, d, d)``, summed over each batch element's bins and rows
    (1 where there is no redundant equation)."""
    (w_d, direct), (w_b, b), (w_s, slope) = direct, b, slope
    d = fitted.shape[-1]
    velocity, along = gamma_dot_m.unsqueeze(-2), tangent.unsqueeze(-2)
    res_b = b - (fitted * velocity.unsqueeze(-1)).sum(-2)
    chi2 = ((w_d * (direct - fitted).square()).flatten(-2).sum(-1)
            + (w_b * res_b.square()).sum(-1))
    chi2 = chi2 + (w_s * (slope - (fitted * along.unsqueeze(-2)).sum(-1)).square()).sum(-1)
    n_obs = (w_d > 0).flatten(-2).sum(-1) + (w_b > 0).sum(-1) + (w_s > 0).sum(-1)
    dof = (n_obs - d * d).clamp_min(0).sum((-2, -1))
    return torch.where(dof > 0, chi2.sum((-2, -1)) / dof.clamp_min(1), 1.0)


def _correlation_of(cov: Tensor, good: Tensor) -> Tensor:
    """The correlation ``(..., d², d²)`` of covariance ``cov``; the identity where ``good
    (..., 1)`` is false or an entry's variance is not positive (the consistency ratio scales
    the covariance, not its correlation)."""
    n = cov.shape[-1]
    sd = torch.diagonal(cov, dim1=-2, dim2=-1).clamp_min(0).sqrt()
    ok = good.unsqueeze(-1) & (sd > 0).unsqueeze(-1) & (sd > 0).unsqueeze(-2)
    return torch.where(ok, cov / (sd.unsqueeze(-1) * sd.unsqueeze(-2)).clamp_min(1e-300),
                       torch.eye(n, dtype=cov.dtype, device=cov.device))
