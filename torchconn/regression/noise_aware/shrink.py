"""Shrinkage of a noise-corrected fit: towards the smoothed fit where the data cannot tell them
apart (:func:`blend_fits`), and of ``Â``'s Fourier series harmonic by harmonic
(:func:`shrink_series`), with ``ĉ, b̂`` re-estimated to the shrunk ``Â`` (:func:`offsets_at`).
"""

from __future__ import annotations

import dataclasses
import math

import torch
from torch import Tensor

from ...noise.intervals import IntervalSamples
from .. import _wls
from ..binning import BinIndex
from ..connection import ConnectionFit, design_blocks, ridge_exemptions
from ..tied import lag_correlations, window_correlation
from .eiv import bin_noise, eiv_correction

__all__ = ["blend_fits", "offset_gain", "offsets_at", "harmonic_noise", "shrink_series",
           "rescaled_covariance"]


def offset_gain(fit: ConnectionFit, samples: IntervalSamples, bins: BinIndex, gamma_m: Tensor,
                gamma_dot_m: Tensor, noise_var: Tensor, *, delta_max: float | None = None,
                ridge_connection: bool = True) -> Tensor:
    """How a bin's ``ĉ`` and ``b̂`` move when its ``Â`` is set to another value and held
    there, ``ĉ, b̂`` re-estimated (and ``∂Â/∂r`` held too): ``G (..., M, 1 + d, d)`` with
    ``[ĉ; b̂ᵀ] + G ΔÂᵀ`` the least-squares solution of the bin's regression at ``Â + ΔÂ``
    (rows ``c, b_·j``, columns the joints; the same for the three outputs).

    ``fit`` is :func:`noise_aware_regression`'s fit of ``samples`` in ``bins`` with the
    noise ``noise_var (..., d)`` (the other arguments as there; its ridge and its share of the
    noise correction, ``fit.ridge`` and ``fit.eiv_scale``, are taken from it): ``G`` comes from
    the same normal equations, corrected for the noise (:func:`~torchconn.regression._wls.
    held_gain`), not from a second fit. NaN where the bin's coefficients are."""
    fn = "offset_gain"
    s = _wls.prepare(fn, samples.r, samples.r_dot, samples.xi, "xi", 3, bins, gamma_m,
                     gamma_dot_m)
    d = s.r.shape[-1]
    var_delta, var_rate = bin_noise(samples, s, noise_var)

    def correction(gram: Tensor, sel) -> Tensor:
        return eiv_correction(gram, var_delta[sel], var_rate[sel])

    flat = _wls.Solution(*(x.reshape((-1,) + x.shape[len(s.batch_shape) + 1:]) for x in (
        fit.coef, fit.se_coef, fit.n_samples, fit.residual_rms, fit.condition, fit.ridge,
        fit.eiv_scale)))
    gain = _wls.held_gain(s, design_blocks, flat, 1 + d, slice(1 + d, 1 + 2 * d),
                          delta_max=delta_max, correction=correction,
                          unpenalised=ridge_exemptions(d, ridge_connection, s.r.device))
    return gain.reshape(s.batch_shape + (s.n_bins, 1 + d, d))


def offsets_at(fit: ConnectionFit, delta_a: Tensor) -> tuple[Tensor, Tensor]:
    """``ĉ (..., M, 3)`` and ``b̂ (..., M, 3, d)`` of ``fit`` re-estimated with each bin's
    ``Â`` moved by ``delta_a (..., M, 3, d)`` and held (``fit.offset_gain``,
    :func:`offset_gain`)."""
    change = fit.offset_gain @ delta_a.mT  # (..., M, 1 + d, 3)
    return fit.c + change[..., 0, :], fit.b + change[..., 1:, :].mT


def harmonic_noise(series, se: Tensor, window: float | Tensor, kernel: str, *,
                    rows: bool = False) -> tuple[Tensor, Tensor]:
    """Power and noise ``(..., K + 1)`` of each harmonic of a per-bin estimate's Fourier
    series ``series`` (of ``Â (..., M, 3, d)`` or ``∂Â/∂r``, standard errors ``se``): the
    squares of its coefficients (cosine and sine) summed over the entries, and their
    expectation from the bins' noise alone. ``window``, ``kernel``: the bins' half-width (a
    number, or ``(...)`` per batch element: each element's noise from its own window only)
    and kernel. ``rows``: each row's own (the first value dim: ``x, y, θ`` of ``Â``), summed
    over the entries of the row, ``(..., 3, K + 1)``.

    The bins' errors are taken as ``se`` with the correlation ``ρ(s)`` of two windows ``s``
    spacings apart (``∫K(x)K(x − s)dx / ∫K²`` of the bins' kernel), so harmonic ``k ≥ 1``
    carries ``(4/M) mean(se²) ν_k`` of noise per entry and the mean ``(1/M) mean(se²) ν_0``,
    with ``ν_k = Σ_s ρ(s) cos(2πks/M)``.
    """
    m = se.shape[-1 - series.value_ndim]
    opts = dict(dtype=torch.float64, device=se.device)
    if isinstance(window, Tensor):  # per element: ρ (..., L) over a shared set of lags
        lag_list, rho = lag_correlations(window, kernel, device=se.device)
        lags, rho = torch.tensor(lag_list, **opts), rho.unsqueeze(-2)  # (..., 1, L)
    else:
        lags, rho = window_correlation(window, kernel, se.device)
    k = torch.arange(0, series.order + 1, **opts)
    nu = (rho * torch.cos(2 * math.pi * k[:, None] * lags / m)).sum(-1).clamp_min(0)
    nu = nu * torch.where(k > 0, 4.0, 1.0) / m
    values = tuple(range(-series.value_ndim, 0))
    c = series.coeffs  # (..., 2K+1, *value_shape)
    if rows:
        rest = values[1:]  # the entries of a row
        level = se.square().nanmean(-1 - series.value_ndim)
        level = level.sum(rest) if rest else level  # (..., R)
        square = c.square().sum(rest) if rest else c.square()  # (..., 2K+1, R)
        square = square.movedim(-2, -1)  # (..., R, 2K+1)
        power = torch.cat([square[..., :1], square[..., 1::2] + square[..., 2::2]], -1)
        return power, level.unsqueeze(-1) * nu.unsqueeze(-2).to(power)  # (..., R, K + 1)
    level = se.square().nanmean(-1 - series.value_ndim).sum(values)  # (...)
    power = c.square().sum(values)  # (..., 2K+1)
    power = torch.cat([power[..., :1], power[..., 1::2] + power[..., 2::2]], -1)
    return power, level.unsqueeze(-1) * nu.to(power)


#: :func:`blend_fits` keeps the corrected estimate only where it differs from the smoothed one
#: by more than this many times its own variance (1: the plain Stein rule; more guards
#: against the corrected estimate's heavy tails in nearly noise-dominated bins)
_BLEND_VARIANCE_FACTOR = 1.5


#: a pooled fit's series of ``Â`` shrinks harmonic ``k`` by ``max(0, 1 − c · noise_k /
#: power_k)`` with this ``c`` (``NoiseAwareRegression._a_series``; ``noise_k`` the bins'
#: noise expectation, :func:`harmonic_noise`). Under noise the bins' errors are mostly
#: variance, and a harmonic near its noise adds more of it than of the connection; ``c = 1`` is
#: the estimated Wiener factor. One factor per harmonic and row of ``Â`` (:func:`shrink_series`)
_SERIES_SHRINK = 0.5


def blend_fits(smoothed: ConnectionFit, corrected: ConnectionFit, *,
               variance_factor: float = _BLEND_VARIANCE_FACTOR
               ) -> tuple[ConnectionFit, Tensor]:
    """The noise-corrected estimate shrunk towards the smoothed one where the data cannot tell
    them apart (a positive-part Stein combination).

    The corrected estimate ``β̂_c`` is unbiased but its variance ``V`` (the square of its
    standard errors) grows without bound as the noise takes over the regressors; the smoothed
    estimate ``β̂_s`` has a small variance but is shrunk by the noise (attenuation bias). Of the
    combinations ``β̂_s + w (β̂_c − β̂_s)`` the one of least mean squared error has
    ``w = 1 − V / E‖β̂_c − β̂_s‖²`` (when the two errors are independent); with the observed
    ``D² = ‖β̂_c − β̂_s‖²``::

        w = clamp(1 − variance_factor · V / D², 0, 1)

    per batch element and block (``c``, ``b``, ``A``, ``∂A/∂r``; sums over bins and entries):
    1 where the two differ by far more than the corrected estimate's noise (the smoothed one is
    biased), 0 where the difference is within that noise (the correction only adds variance).
    ``variance_factor`` > 1 guards against the heavy tails of the corrected estimate in
    nearly noise-dominated bins, which its standard errors understate (see the module constant).

    The standard errors ``(1 − w) se_s + w se_c`` bound the combination's variance but leave
    out the smoothed estimate's attenuation, of which it keeps a ``1 − w`` share. The joint
    covariance of ``b̂`` and the direct ``∂Â/∂r`` (``corrected.cov_b_dA``, which only the
    tie's bands use) is rescaled to those standard errors, and the shift the shrink makes is
    allowed for on its diagonal: per entry ``(1 − w)² (β̂_c − β̂_s)² · max(1 − (V + V_s) / D²,
    0)`` (``V_s`` the smoothed estimate's ``Σ se_s²``), the shift's square times the block's
    share of ``D²`` beyond the two estimates' noise: ``D² − V − V_s`` estimates the smoothed
    estimate's squared bias ``‖E β̂_s − β‖²``, whose ``1 − w`` share the combination keeps.

    Args:
        smoothed, corrected: fits of the same bins, batch dims ``...``.
        variance_factor: as above.

    Returns:
        the combined :class:`~torchconn.regression.ConnectionFit` (fields other than the four
        blocks, their standard errors and ``cov_b_dA`` are the corrected fit's) and
        ``w (..., 4)`` for ``c, b, A, ∂A/∂r``.
    """
    out, weights, shifts = {}, [], {}
    for name in ("c", "b", "A", "dA"):
        est_s, est_c = getattr(smoothed, name), getattr(corrected, name)
        se_s, se_c = getattr(smoothed, "se_" + name), getattr(corrected, "se_" + name)
        n_tail = est_s.ndim - smoothed.n_samples.ndim + 1  # the bins and the block's entries
        dims = tuple(range(-n_tail, 0))
        diff2 = (est_c - est_s).square()
        d2 = diff2.nansum(dims)
        var = se_c.square().nansum(dims)
        w = torch.where(d2 > 0, (1 - variance_factor * var / d2.clamp_min(1e-300)).clamp(0, 1),
                        0.0)
        wx = w.reshape(w.shape + (1,) * n_tail)
        out[name] = est_s + wx * (est_c - est_s)
        out["se_" + name] = (1 - wx) * se_s + wx * se_c
        weights.append(w)
        # the block's D² − V − V_s: the smoothed estimate's squared bias (its variance is in
        # the standard errors already)
        spread = var + se_s.square().nansum(dims)
        beyond = torch.where(d2 > 0, 1 - spread / d2.clamp_min(1e-300), 0.0).clamp_min(0)
        shift = (1 - wx).square() * diff2 * beyond.reshape(wx.shape)
        shifts[name] = torch.where(torch.isfinite(shift), shift, 0.0)  # (a NaN bin: as before)
    cov = corrected.cov_b_dA
    if cov is not None:
        cov = rescaled_covariance(cov, (corrected.se_b, corrected.se_dA),
                                   (out["se_b"], out["se_dA"]))
        cov = cov + torch.diag_embed(torch.cat([shifts["b"], shifts["dA"].flatten(-2)], -1))
    return dataclasses.replace(corrected, **out, cov_b_dA=cov), torch.stack(weights, -1)


def rescaled_covariance(cov: Tensor, se_from: tuple[Tensor, Tensor],
                         se_to: tuple[Tensor, Tensor]) -> Tensor:
    """The joint covariance ``cov (..., M, 3, c, c)`` of ``(b̂, ∂Â/∂r)`` (``ConnectionFit.
    cov_b_dA``) rescaled from the standard errors ``se_from`` to ``se_to`` (pairs ``(se_b
    (..., M, 3, d), se_dA (..., M, 3, d, d))``): entry ``(p, q)`` times ``(to_p/from_p)
    (to_q/from_q)`` (1 where ``from`` is 0 or not finite)."""
    old = torch.cat([se_from[0], se_from[1].flatten(-2)], -1)
    new = torch.cat([se_to[0], se_to[1].flatten(-2)], -1)
    ratio = torch.where(torch.isfinite(old) & (old > 0), new / old.clamp_min(1e-300), 1.0)
    return cov * ratio.unsqueeze(-1) * ratio.unsqueeze(-2)


def shrink_series(series, se: Tensor, window, kernel: str) -> tuple:
    """``Â``'s Fourier series ``series`` (values ``(3, d)``, per-bin standard errors ``se
    (..., M, 3, d)``, bins of half-width ``window`` and ``kernel``) with each harmonic of each
    row ``x, y, θ`` shrunk by ``max(0, 1 − c · noise / power)`` (:func:`harmonic_noise`,
    ``c =`` :data:`_SERIES_SHRINK`; the mean is kept). Each row by its own power: one factor for
    the whole harmonic would shrink the rows where it stands far out of its noise (the
    fundamental that carries the gait's displacement) as much as those where it is noise.
    Returns the shrunk series and the factors ``(..., K + 1, 3)``."""
    power, noise = harmonic_noise(series, se, window, kernel, rows=True)  # (..., 3, K + 1)
    factor = (1 - _SERIES_SHRINK * noise / power.clamp_min(1e-300)).clamp(0, 1)
    factor[..., 0] = 1  # the mean
    factor = factor.transpose(-1, -2)  # (..., K + 1, 3)
    coeff_factor = torch.cat([factor[..., :1, :],
                              factor[..., 1:, :].repeat_interleave(2, -2)], -2)
    shrunk = dataclasses.replace(series, coeffs=series.coeffs * coeff_factor.unsqueeze(-1))
    return shrunk, factor
