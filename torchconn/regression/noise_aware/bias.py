"""Bias corrections of a noise-aware fit: the bins' and the velocity filter's bias of ``Â`` and
of ``∂Â/∂r``, computed from the fitted smooth model, and the allowances for the tube's
second-order bias and the sampling interval's.
"""

from __future__ import annotations

import dataclasses
import math
import warnings
from dataclasses import dataclass

import torch
from torch import Tensor

from ...noise.intervals import IntervalSamples, interval_samples, interval_weights, pooled_view
from ...noise.spectrum import bridge_gaps
from ...phase.fourier import FourierSeries, fit_fourier
from ...trajectory import Trajectory, pool_batch
from .. import _wls
from .._wls import IllConditionedBinWarning
from ..binning import BinIndex, assign_bins
from ..connection import ConnectionFit, connection_regression, design_blocks, ridge_exemptions
from ..tied import cycle_tangent, tie_connection_derivative
from .shrink import harmonic_noise

__all__ = ["offset_bias", "resolved_bias", "interval_bias", "OneSampleOffsets",
           "one_sample_offsets", "cycle_series", "bin_bias_correction",
           "derivative_bias_correction", "derivative_bias_allowance", "RESIDUAL_BIAS_FRACTION"]


def offset_bias(samples: IntervalSamples, bins: BinIndex, gamma_m: Tensor,
                gamma_dot_m: Tensor, *, first: ConnectionFit | None = None,
                estimate: Tensor | None = None, delta_max: float | None = None,
                ridge: float = 0.0, on_ill_conditioned: str = "raise",
                ridge_connection: bool = True) -> tuple[Tensor, Tensor]:
    """The tube's second-order bias of ``Â`` ``(..., M, 3, d)`` and its sampling variance (same
    shape), estimated as the change of each bin's ``Â`` when the second-order terms of the
    offsets, ``δ⊗δ`` and ``δ̇⊗δ⊗δ`` (:func:`_second_order_blocks`), are fitted too, with the
    sign of a bias (first-order fit minus second-order fit; plain least squares on the same
    samples, bins and weights; NaN where a bin cannot fit them). The two fits are nested, so
    the change's variance is the difference of theirs (the solver's, rows independent; below
    0 where the first-order fit's residual holds the misfit the second order removes).

    ``A(γ + δ) ṙ`` carries ``½ (δᵀ ∂²A δ) δ̇``, whose correlation with ``δ̇`` the first-order
    model loads onto ``Â``: ``Â`` is ``A`` averaged over the tube, ``A + ½ ∂²A : E[δδᵀ]``, not
    ``A`` on the cycle. Without noise correction: the change is for recordings without
    detected measurement noise, where this bias is not small against the noise. ``first``:
    the first-order fit of the same samples and bins, where the caller has it (computed here
    otherwise). ``estimate``: ``(..., M, 3, d)`` the ``Â`` whose bias is
    wanted where it is not that fit's (a delivered ``Â``, which the bins' bias correction and
    the blend have moved from the plain fit): the change is then ``estimate`` minus the
    second-order fit, the variance as above (the moves are functions of the fitted model,
    not of the rows' noise)."""
    fn = "offset_bias"
    s = _wls.prepare(fn, samples.r, samples.r_dot, samples.xi, "xi", 3, bins, gamma_m,
                     gamma_dot_m)
    d = s.r.shape[-1]
    p, q = 1 + 2 * d + d * d, d * (d + 1) // 2
    free = ridge_exemptions(d, ridge_connection, s.r.device)
    wide = None if free is None else torch.cat([free, free.new_zeros(q + d * q)])
    kw = dict(fn=fn, delta_max=delta_max, ridge=ridge, min_samples=None, max_condition=None)
    if first is None:
        first = connection_regression(samples.r, samples.r_dot, samples.xi, bins, gamma_m,
                                      gamma_dot_m, delta_max=delta_max, ridge=ridge,
                                      on_ill_conditioned=on_ill_conditioned,
                                      ridge_connection=ridge_connection)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", IllConditionedBinWarning)
        second = _wls.solve(s, _second_order_blocks, p + q + d * q, on_ill_conditioned="warn",
                            unpenalised=wide, **kw)
    shape = s.batch_shape + (s.n_bins, 3, d)
    cols = slice(1 + d, 1 + 2 * d)
    a_second = second.coef[:, cols].mT.reshape(shape)
    se_second = second.se[:, cols].mT.reshape(shape)
    # nested fits: the change's variance is the difference of theirs
    change = (first.A if estimate is None else estimate) - a_second
    return change, se_second.square() - first.se_A.square()


def resolved_bias(change: Tensor, var: Tensor) -> Tensor:
    """An estimated bias ``change (..., M, a, b)`` of a connection's entries shrunk by how far
    it stands out of its own sampling noise ``var`` (same shape): times
    ``w = clamp(1 − Σ var / Σ change², 0, 1)``, the sums over the bins and entries of each
    batch element, as :func:`blend_fits` (a bias allowance drawn whole would otherwise carry
    its noise into the standard errors as if it were bias); NaN
    (bins that could not be fitted) count as 0."""
    change, var = torch.nan_to_num(change), torch.nan_to_num(var).clamp_min(0)
    dims = (-3, -2, -1)  # the bins and a connection's two entry dims
    d2 = change.square().sum(dims, keepdim=True)
    noise = var.sum(dims, keepdim=True)
    w = torch.where(d2 > 0, (1 - noise / d2.clamp_min(1e-300)).clamp(0, 1), 0.0)
    return w * change


def interval_bias(traj: Trajectory, samples: IntervalSamples, bins: BinIndex, n_bins: int,
                  window: float, kernel: str, gamma_m: Tensor, gamma_dot_m: Tensor, *,
                  full: ConnectionFit | None = None, **opts) -> tuple[Tensor, Tensor]:
    """The sampling interval's bias of a pooled fit's ``Â`` ``(M, 3, d)`` and its sampling
    variance (same shape), by Richardson extrapolation: the bins' plain regression of
    ``samples`` (``traj``'s trials pooled at interval ``h``, binned as ``bins``) and of the
    same trials recorded at twice the interval (every other sample, the same ``h`` and bins of
    half-width ``window``, ``kernel``): a bias
    ``c Δt²`` makes their difference ``3 c Δt²``, and a third of it is returned (NaN where a
    bin of the thinned recording cannot be fitted), with the variance of that third (the
    thinned samples are half of the others: nearly nested fits).

    Without noise a fit's ``Â`` is off by ``a + c Δt²``: one-sample differences and
    logarithms of a path that curves within the sample. ``full``: the plain fit of ``samples`` in ``bins``
    where the caller has it (computed here otherwise); ``opts``: the solver's options."""
    half = Trajectory(t=traj.t[::2], pose=traj.pose[..., ::2, :],
                      r=traj.r[..., ::2, :]).with_fields(phase=traj.phase[..., ::2])
    thin = pooled_view(half, samples.h, samples.kernel)
    thin_bins = assign_bins(thin.phase, n_bins, window=window, kernel=kernel)
    if full is None:
        full = connection_regression(samples.r, samples.r_dot, samples.xi, bins, gamma_m,
                                     gamma_dot_m, **opts)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", IllConditionedBinWarning)
        coarse = connection_regression(thin.r, thin.r_dot, thin.xi, thin_bins, gamma_m,
                                       gamma_dot_m, **{**opts, "on_ill_conditioned": "warn"})
    # the thinned recording's samples are half of the full one's: nearly nested fits
    return (coarse.A - full.A) / 3, (coarse.se_A.square() - full.se_A.square()) / 9


def _second_order_blocks(delta: Tensor, delta_dot: Tensor, row_scale: Tensor) -> list[Tensor]:
    """The column blocks of ``row_scale · [1, δ, δ̇, δ̇⊗δ, δ⊗δ, δ̇⊗δ⊗δ]`` (``δ⊗δ`` its ``d(d+1)/2``
    distinct products ``δ_i δ_j``, ``i ≤ j``)."""
    d = delta.shape[-1]
    iu, ju = torch.triu_indices(d, d, device=delta.device)
    square = row_scale * delta[..., iu] * delta[..., ju]
    cubic = (delta_dot.unsqueeze(-1) * square.unsqueeze(-2)).flatten(-2)
    return design_blocks(delta, delta_dot, row_scale) + [square, cubic]


@dataclass(frozen=True)
class OneSampleOffsets:
    """The one-sample intervals of a trajectory ``(..., T − 1, ·)`` against its cycle: the
    mid-point phase ``φ_j``, the offset ``r_j − γ(φ_j)`` split into ``along (..., T − 1, 1)``
    (in units of the cycle's tangent ``γ'(φ_j)``) and ``across (..., T − 1, d)``, and the
    one-sample shape velocity ``r_dot``."""

    phase: Tensor
    along: Tensor
    across: Tensor
    r_dot: Tensor


def one_sample_offsets(traj: Trajectory, gamma_m: Tensor) -> OneSampleOffsets:
    """:class:`OneSampleOffsets` of ``traj`` around the cycle through ``gamma_m (..., M, d)``
    (its values at the bin centres; interpolated by its Fourier series of the highest order
    the centres carry). Gaps in ``r`` are bridged by straight lines (:func:`bridge_gaps`): the
    box filter's rows need only their two ends, so their model target must span missing
    samples too (the triangle's rows need every sample and are unaffected)."""
    cycle = cycle_series(gamma_m)
    one = interval_samples(traj.pose, bridge_gaps(traj.r), traj.phase, traj.dt, 1)
    offset = one.r - cycle(one.phase)
    tangent = cycle.derivative()(one.phase)
    along = (tangent * offset).sum(-1, keepdim=True) / tangent.square().sum(-1, keepdim=True)
    return OneSampleOffsets(phase=one.phase, along=along, across=offset - along * tangent,
                             r_dot=one.r_dot)


def cycle_series(gamma_m: Tensor) -> FourierSeries:
    """The cycle through ``gamma_m (..., M, d)`` (its values at the bin centres) as a Fourier
    series of the highest order the centres carry, by the discrete Fourier sums (each batch
    element's bit for bit on its own: a least-squares fit rounds with the batch)."""
    m = gamma_m.shape[-2]
    phi = torch.arange(m, dtype=gamma_m.dtype, device=gamma_m.device) * (2 * math.pi / m)
    coeffs = [gamma_m.mean(-2)]
    for k in range(1, (m - 1) // 2 + 1):  # batch-free cos, sin
        coeffs += [(gamma_m * torch.cos(k * phi)[:, None]).sum(-2) * (2 / m),
                   (gamma_m * torch.sin(k * phi)[:, None]).sum(-2) * (2 / m)]
    return FourierSeries(torch.stack(coeffs, -2), value_ndim=1)


def _model_target(one: OneSampleOffsets, h: int, kernel: str, a_series,
                  off_cycle: Tensor) -> Tensor:
    """The body velocity a smooth connection model gives the samples, filtered as the data's
    target (:func:`interval_samples`'s ``xi``): ``(..., T − h, 3)``.

    On each one-sample interval ``j`` the model's connection is ``A(φ_j) + A'(φ_j) s_j +
    ∂A/∂r(φ_j)[ε_j]`` (``one``: the offset from the cycle split into ``s_j γ'(φ_j)`` along it
    and ``ε_j`` across; ``off_cycle (..., T − 1, 3, d)`` the last term): along the cycle the
    change of ``A`` is its phase derivative (the chain rule, which a separately fitted
    ``∂A/∂r`` need not obey), off it the fitted ``∂A/∂r``.
    """
    phi = one.phase
    a = a_series(phi) + one.along.unsqueeze(-1) * a_series.derivative()(phi) + off_cycle
    y = (a @ one.r_dot.unsqueeze(-1)).squeeze(-1)
    if h == 1:
        return y
    return y.unfold(-2, h, 1) @ interval_weights(h, kernel, dtype=y.dtype, device=y.device)


def _resolved_harmonics(series, se: Tensor, bins: BinIndex) -> Tensor:
    """Mask ``(..., 2K+1, 1, …)`` of the harmonics of ``series`` (:func:`harmonic_noise`)
    that stand out of its noise: the mean always, harmonic ``k`` when its power exceeds
    :data:`_BIAS_HARMONIC_Z` ``· max(1, (k / _BIAS_HARMONIC_SCALE)²)`` times its noise."""
    power, noise = harmonic_noise(series, se, bins.window, bins.kernel)
    k = torch.arange(power.shape[-1], dtype=power.dtype, device=power.device)
    bar = _BIAS_HARMONIC_Z * (k / _BIAS_HARMONIC_SCALE).square().clamp_min(1)
    resolved = power > bar * noise
    resolved[..., 0] = True
    keep = torch.cat([resolved[..., :1], resolved[..., 1:].repeat_interleave(2, -1)], -1)
    return keep.to(series.coeffs.dtype).reshape(keep.shape + (1,) * series.value_ndim)


def _resolved_series(centres: Tensor, values: Tensor, se: Tensor, bins: BinIndex, order: int,
                     value_ndim: int) -> FourierSeries:
    """The order-``order`` Fourier series through the per-bin ``values`` (standard errors
    ``se``, bins ``bins`` at ``centres``), keeping only the harmonics that stand out of their
    noise (:func:`_resolved_harmonics`): a bias model's smooth part."""
    series = fit_fourier(centres, values, order, value_ndim=value_ndim)
    return dataclasses.replace(series,
                               coeffs=series.coeffs * _resolved_harmonics(series, se, bins))


def bin_bias_correction(fit: ConnectionFit, traj: Trajectory, samples: IntervalSamples,
                        bins: BinIndex, gamma_m: Tensor, gamma_dot_m: Tensor, *,
                        pool: bool, order: int | None = None, steps: int | None = None,
                        offsets: OneSampleOffsets | None = None, **opts
                        ) -> tuple[ConnectionFit, Tensor]:
    """``fit`` with ``Â`` corrected for the bias of the bins and the velocity filter.

    A bin's regression is a first-order model in ``r`` around ``γ_m``, fitted to samples
    spread over a phase window and filtered over ``h`` samples. Where ``A`` changes fast
    along the cycle, both average it over a stretch of the cycle (the window's ``A''w²``
    terms, the filter's ``Σ u_j A(r_j) ṙ_j ≠ A(r̄) ṙ̄``), and the filter's smaller off-cycle
    shape velocities, which identify ``A``, let the on-cycle curvature leak in further (on
    the 3-link reference gait without noise, ``h = 8``, windows of 2 spacings: 2.9 %).
    The bias is a deterministic function of the connection and the samples, so it is computed
    from the fitted model: the same regression (same samples, bins and design, plain least
    squares) is run on the target the smooth model itself gives the samples
    (:func:`_model_target`), and its departure from that model at the bin centres is
    subtracted (a one-step bias correction, iterated ``steps`` times as the fixed point
    ``Â ← Â_obs − (F(Â) − Â)``). The model is the Fourier series of ``Â`` and ``∂Â/∂r``
    of ``order`` (lower than the fit's own: the correction needs the smooth part only, and
    its phase derivative amplifies the noise of higher harmonics).

    Args:
        fit: the regression's fit ``(..., M, ·)`` of ``samples`` in ``bins``.
        traj: the trajectory the samples were filtered from (``pose``, ``r``, ``phase``,
            batch dims ``...``; pooled: the trials that ``samples`` pools).
        samples: :func:`interval_samples` (pooled when ``pool``), ``bins`` their bins.
        gamma_m, gamma_dot_m: ``(..., M, d)`` the cycle and its velocity at the bin centres.
        order, steps: the model's Fourier order and the fixed-point steps (defaults
            :data:`_BIAS_ORDER`, :data:`_BIAS_STEPS`).
        offsets: ``traj``'s one-sample offsets from the cycle (:func:`one_sample_offsets`;
            computed when None; the same for every interval and window).
        opts: the solver's options (``delta_max``, ``ridge``, ``on_ill_conditioned``).

    Returns:
        the fit with ``A`` (per bin) corrected (other fields unchanged), and the variance
        ``(...)`` the correction adds to ``Â`` (summed over the bins and entries, as
        ``se_A²``): the noise of each harmonic of the model grows by ``(1 + r_k)² − 1`` with
        ``r_k`` the correction's size relative to that harmonic.
    """
    order = _BIAS_ORDER if order is None else order
    steps = _BIAS_STEPS if steps is None else steps
    m = bins.n_bins
    centres = torch.arange(m, dtype=fit.A.dtype, device=fit.A.device) * (2 * math.pi / m)
    order = min(order, (m - 1) // 2)
    one = one_sample_offsets(traj, gamma_m) if offsets is None else offsets
    da_series = _resolved_series(centres, fit.dA, fit.se_dA, bins, order, 3)
    off_cycle = torch.einsum("...kij,...j->...ki", da_series(one.phase), one.across)
    observed = fit.A
    keep = _resolved_harmonics(fit_fourier(centres, observed, order, value_ndim=2), fit.se_A,
                               bins)
    estimate = observed
    for _ in range(steps):
        # pooled: the series (no batch dims) act on every trial's samples alike
        a_series = fit_fourier(centres, estimate, order, value_ndim=2)
        a_series = dataclasses.replace(a_series, coeffs=a_series.coeffs * keep)
        y = _model_target(one, samples.h, samples.kernel, a_series, off_cycle)
        if pool:
            y = pool_batch(y, 1)
        model = connection_regression(samples.r, samples.r_dot, y, bins, gamma_m,
                                      gamma_dot_m, standard_errors=False, **opts)
        estimate = observed - (model.A - a_series(centres))
    # the correction's own noise: harmonic k of Â enters it with the gain r_k ≈ |B_k| / |Â_k|
    # (the bias map's damping of that harmonic), so its noise grows by (1 + r_k)² − 1
    power, noise = harmonic_noise(a_series, fit.se_A, bins.window, bins.kernel)
    gain = (harmonic_noise(fit_fourier(centres, estimate - observed, order, value_ndim=2),
                            fit.se_A, bins.window, bins.kernel)[0] / power.clamp_min(1e-300)).sqrt()
    weight = torch.where(torch.arange(order + 1, device=power.device) > 0, m / 2, m)
    added = (weight * noise * (2 * gain + gain.square()) * (power > 0)).sum(-1)
    return dataclasses.replace(fit, A=estimate), added


class _DerivativeBias:
    """The bins' bias of the direct ``∂Â/∂r`` and of ``b̂`` as the smooth model gives it: the
    same regression run on the body velocity the model gives the samples
    (:func:`_model_target`: ``Â`` and its phase derivative along the cycle, a tied ``∂Â/∂r``
    across it), less the model's own values at the bin centres (``D_model = dÂ/dφ ⊗
    γ'/|γ'|² + ∂Â/∂r P⊥``, ``b_model = D_modelᵀγ̇``). The model's series keep only the
    harmonics that stand out of their noise (:func:`_resolved_harmonics`). Arguments as in
    :func:`derivative_bias_correction`; ``Â``'s series and the cycle's projections are built
    once, each call takes the tied fit whose ``∂Â/∂r`` the model uses and returns the bias
    of ``(dA (..., M, 3, d, d), b (..., M, 3, d))``."""

    def __init__(self, fit: ConnectionFit, samples: IntervalSamples, bins: BinIndex,
                 gamma_m: Tensor, gamma_dot_m: Tensor, *, order: int, pool: bool,
                 offsets: OneSampleOffsets, opts: dict):
        m = bins.n_bins
        self.centres = torch.arange(m, dtype=fit.A.dtype, device=fit.A.device) * (2 * math.pi / m)
        tangent = cycle_tangent(gamma_m)
        self.along = tangent / tangent.square().sum(-1, keepdim=True)
        self.across = (torch.eye(tangent.shape[-1], dtype=tangent.dtype, device=tangent.device)
                       - self.along.unsqueeze(-1) * tangent.unsqueeze(-2))  # (..., M, d, d): P⊥
        self.a_series = _resolved_series(self.centres, fit.A, fit.se_A, bins, order, 2)
        self.a_slope = self.a_series.derivative()(self.centres)
        self.samples, self.bins, self.gamma_m, self.gamma_dot_m = samples, bins, gamma_m, gamma_dot_m
        self.order, self.pool, self.one, self.opts = order, pool, offsets, opts

    def __call__(self, tied: ConnectionFit) -> tuple[Tensor, Tensor]:
        centres, one = self.centres, self.one
        da_series = _resolved_series(centres, tied.dA, tied.se_dA, self.bins, self.order, 3)
        off_cycle = torch.einsum("...kij,...j->...ki", da_series(one.phase), one.across)
        y = _model_target(one, self.samples.h, self.samples.kernel, self.a_series, off_cycle)
        if self.pool:
            y = pool_batch(y, 1)
        model = connection_regression(self.samples.r, self.samples.r_dot, y, self.bins,
                                      self.gamma_m, self.gamma_dot_m, standard_errors=False,
                                      **self.opts)
        d_model = (torch.einsum("...mki,...mj->...mkij", self.a_slope, self.along)
                   + torch.einsum("...mkil,...mlj->...mkij", da_series(centres), self.across))
        b_model = torch.einsum("...mkij,...mi->...mkj", d_model, self.gamma_dot_m)
        return model.dA - d_model, model.b - b_model


def derivative_bias_correction(fit: ConnectionFit, traj: Trajectory, samples: IntervalSamples,
                               bins: BinIndex, gamma_m: Tensor, gamma_dot_m: Tensor, *,
                               order: int, pool: bool, steps: int | None = None,
                               offsets: OneSampleOffsets | None = None, **opts
                               ) -> tuple[ConnectionFit, Tensor]:
    """The tied ``∂Â/∂r`` (:func:`tie_connection_derivative`) with the bins' bias removed.

    The direct ``δ̇⊗δ`` estimate and ``b̂`` carry the bias of the bins' phase width (on the
    curved 3-link reference gait without noise the direct estimate is 20 % off where its
    standard errors imply 5 %); as in :func:`bin_bias_correction`, the same regression is run
    on the body velocity the smooth model gives the samples (:func:`_model_target`: ``Â``
    and its phase derivative along the cycle, the tied ``∂Â/∂r`` across it), the departure
    of its ``∂Â/∂r`` and ``b̂`` from the model's own (``D_model = dÂ/dφ ⊗ γ'/|γ'|² + ∂Â/∂r
    P⊥``, ``b_model = D_modelᵀγ̇``) is subtracted from the observed ones, and the result is
    tied again, ``steps`` times (a fixed point). The model's series keep only the harmonics
    that stand out of their noise (:func:`_resolved_harmonics`), so under noise the
    correction fades instead of amplifying it.

    Args:
        fit: the chosen fit (``Â`` already corrected by :func:`bin_bias_correction`).
        traj, samples, bins, gamma_m, gamma_dot_m, pool, offsets, opts: as in
            :func:`bin_bias_correction`.
        order: the Fourier order of the model's series (``Â``'s, for the tie).
        steps: fixed-point steps (default :data:`_BIAS_STEPS`).

    Returns:
        the fit with ``dA`` tied and corrected, and the correction applied to the tied
        ``∂Â/∂r`` ``(..., M, 3, d, d)`` (the difference from the uncorrected tie). ``se_dA``
        is the tie's (widened where the sources disagree) with :data:`RESIDUAL_BIAS_FRACTION`
        times the correction's square added: the bias taken to remain.
    """
    steps = _BIAS_STEPS if steps is None else steps
    one = one_sample_offsets(traj, gamma_m) if offsets is None else offsets
    tie = dict(order=order, window=bins.window, kernel=bins.kernel, consistency=False)
    first = tied = tie_connection_derivative(fit, gamma_m, gamma_dot_m, **tie)
    bias = _DerivativeBias(fit, samples, bins, gamma_m, gamma_dot_m, order=order, pool=pool,
                           offsets=one, opts=opts)
    for _ in range(steps):
        bias_dA, bias_b = bias(tied)
        corrected = dataclasses.replace(fit, dA=fit.dA - bias_dA, b=fit.b - bias_b)
        tied = tie_connection_derivative(corrected, gamma_m, gamma_dot_m, **tie)
    tied = tie_connection_derivative(corrected, gamma_m, gamma_dot_m,
                                     **{**tie, "consistency": True})
    shift = tied.dA - first.dA
    # the bias left after the correction, taken as the part of its square the pooled choice
    # assumes (RESIDUAL_BIAS_FRACTION)
    se = (tied.se_dA.square() + RESIDUAL_BIAS_FRACTION * shift.square()).sqrt()
    return dataclasses.replace(fit, dA=tied.dA, se_dA=se, corr_dA=tied.corr_dA), shift


def derivative_bias_allowance(fit: ConnectionFit, traj: Trajectory, samples: IntervalSamples,
                              bins: BinIndex, gamma_m: Tensor, gamma_dot_m: Tensor, *,
                              order: int, pool: bool,
                              offsets: OneSampleOffsets | None = None, **opts
                              ) -> tuple[ConnectionFit, tuple[Tensor, Tensor]]:
    """The tied ``∂Â/∂r`` (:func:`tie_connection_derivative`) with the bins' bias of its
    sources allowed for in their variances instead of removed (for data with measurement
    noise, where :func:`derivative_bias_correction` is not applied).

    Under noise ``b̂`` keeps part of the bins' bias (the chosen filter spans up to a quarter
    cycle and the windows widen). The bias of ``b̂`` and of the direct estimate is computed
    once from the smooth model (:class:`_DerivativeBias`, about the uncorrected tie), and
    :data:`RESIDUAL_BIAS_FRACTION` times its square is added to their variances before they
    are tied (the bias taken to remain, as the pooled choice assumes for ``Â``): these weigh
    the sources. The tie's bands take the direct estimate's variance with
    :data:`_DIRECT_BIAS_SHARE` times the square instead (on the joint covariance
    ``fit.cov_b_dA``, which the tie's sandwich uses; the tied ``∂Â/∂r`` itself is
    unchanged): only the direct estimate holds the across-cycle entries. Without
    ``fit.cov_b_dA`` the bands are the weights' own.

    Args: as :func:`derivative_bias_correction` (no ``steps``).

    Returns:
        the fit with ``dA`` and ``se_dA`` tied (other fields unchanged, ``b̂``'s standard
        errors included), and the bias ``(dA (..., M, 3, d, d), b (..., M, 3, d))`` allowed
        for.
    """
    one = one_sample_offsets(traj, gamma_m) if offsets is None else offsets
    tie = dict(order=order, window=bins.window, kernel=bins.kernel)
    # the bias model's series keep the harmonics that stand out of the independent tie's
    # standard errors (as before the joint covariance: the same bias, bit for bit)
    first = tie_connection_derivative(dataclasses.replace(fit, cov_b_dA=None), gamma_m,
                                      gamma_dot_m, **tie, consistency=False)
    bias = _DerivativeBias(fit, samples, bins, gamma_m, gamma_dot_m, order=order, pool=pool,
                           offsets=one, opts=opts)(first)
    bias = tuple(torch.where(torch.isfinite(x), x, 0.0) for x in bias)
    cov = fit.cov_b_dA
    if cov is not None:  # the bias's share on the joint covariance's diagonal (the bands)
        cov = cov + torch.diag_embed(torch.cat(
            [RESIDUAL_BIAS_FRACTION * bias[1].square(),
             _DIRECT_BIAS_SHARE * bias[0].square().flatten(-2)], -1))
    widened = dataclasses.replace(
        fit, se_dA=(fit.se_dA.square() + RESIDUAL_BIAS_FRACTION * bias[0].square()).sqrt(),
        se_b=(fit.se_b.square() + RESIDUAL_BIAS_FRACTION * bias[1].square()).sqrt(),
        cov_b_dA=cov)
    tied = tie_connection_derivative(widened, gamma_m, gamma_dot_m, **tie)
    return dataclasses.replace(fit, dA=tied.dA, se_dA=tied.se_dA, corr_dA=tied.corr_dA), bias


#: the part ``λ`` of a bias correction's square taken to remain after it: the pooled choice
#: scores a candidate ``V + V⁺ + λ‖B‖²`` (``NoiseAwareRegression._chosen_fit``), and the
#: tied ``∂Â/∂r``'s standard errors and weights add ``λ`` times the squared correction or
#: modelled bias
RESIDUAL_BIAS_FRACTION = 0.5


#: the share of the direct ``∂Â/∂r``'s squared modelled bias (:class:`_DerivativeBias`) that
#: the tie's bands take as remaining (:func:`derivative_bias_allowance`; its weights take
#: ``RESIDUAL_BIAS_FRACTION``)
_DIRECT_BIAS_SHARE = 1.0


#: the bias correction's model (:func:`bin_bias_correction`): the Fourier order of its
#: ``Â`` and ``∂Â/∂r`` and the fixed-point steps. Lower than the fit's own order: the
#: correction enters through the model's phase derivative, which amplifies noisy high
#: harmonics; more steps diverge where the bias is large (wide windows)
_BIAS_ORDER = 6
_BIAS_STEPS = 2


#: a harmonic of ``Â`` enters the bias correction's model when its coefficients' squares
#: exceed this many times their noise expectation (:func:`_resolved_harmonics`): correcting a
#: harmonic the data do not resolve amplifies its noise (the bins damp it, the correction
#: undoes the damping) and removes next to no bias
_BIAS_HARMONIC_Z = 4.0


#: ... and harmonics above this one need (k / _BIAS_HARMONIC_SCALE)² times more: the model
#: enters the correction through its phase derivative (harmonic k weighted by k), and a noisy
#: high harmonic, amplified so, spoils the correction of the low ones
_BIAS_HARMONIC_SCALE = 2.0
