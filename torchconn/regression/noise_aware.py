"""Noise-aware connection regression: filtered raw differences with an errors-in-variables fix.

The smoothed regression (:func:`~torchconn.regression.connection_regression` on a Kalman
smoother's output) smooths the noisy pose channels, which carry the target ``ξ``, harder than
the shape channels, which carry the regressors ``δ̇``; that removes the body's response to the
very shape jitter that identifies ``A`` and shrinks ``Â`` towards 0 under motion-capture noise.
Here target and regressors see the same linear filter over ``h`` samples and nothing else is
smoothed: with weights ``u_j`` on the one-sample intervals (:func:`interval_weights`; a
triangle by default, the plain mean over the interval as ``"box"``),

- ``ξ_k = Σ_j u_j log(g_{k+j−1}⁻¹ g_{k+j}) / Δt``, a weighted mean body velocity;
- ``ṙ_k = Σ_j u_j (r_{k+j} − r_{k+j−1}) / Δt``, the same mean of the shape velocity, and
  ``r̄_k = Σ_j u_j (r_{k+j−1} + r_{k+j}) / 2``, its mid-point shape (Stratonovich's rule);
- the phase at the interval's middle.

On the samples the filter is ``ṙ_k = Σ_j a_j r_{k+j} / Δt`` and ``r̄_k = Σ_j b_j r_{k+j}``, so
independent Gaussian noise of variance ``σ_i²`` on ``r_i`` puts ``σ_i² Σ b_j²`` into ``r̄_i``
and ``σ_i² Σ a_j² / Δt²`` into ``ṙ_i`` (:func:`interval_noise_gains`; the box's sharp edges
give ``2σ²/(hΔt)²``, the triangle ``≈ 16σ²/((h+1)³Δt²)``), uncorrelated with each other
(``Σ a_j b_j = 0`` for every filter) and with the pose noise in ``ξ``. Its expected
contribution to each bin's normal matrix ``XᵀWX`` for the design ``[1, δ, δ̇, δ̇⊗δ]`` is known
in closed form from ``XᵀWX`` itself (:func:`eiv_correction`) and is subtracted (errors in
variables; the right-hand side needs no correction). Consecutive rows overlap, so the
solver's standard errors are inflated by the rows' correlation (:func:`overlap_inflation`).
The per-channel noise is estimated from the data (:func:`estimate_noise`); a pooled fit
chooses the interval and the bins' width by an estimate of ``Â``'s mean squared error. Where
the data are too few for the correction to pay (it removes most of the normal matrix and
amplifies the noise), the estimate falls back towards the smoothed regression's
(:func:`blend_fits`).
"""

from __future__ import annotations

import dataclasses
import math
import warnings
from dataclasses import dataclass
from typing import ClassVar, Literal

import torch
from torch import Tensor, nn

from .. import _linalg
from .._options import option
from ..phase.fourier import FourierSeries, fit_fourier
from ..phase.limit_cycle import phase_rate
from ..phase.smoothing import unwrap
from ..physics import se2
from ..trajectory import Trajectory, over_spans, pool_batch, span_bounds
from . import _wls
from ._wls import IllConditionedBinWarning
from .binning import BinIndex, assign_bins
from .connection import (
    ConnectionFit,
    _blocks,
    _connection_fit,
    connection_regression,
    ridge_exemptions,
)
from .tied import _lag_correlations, _window_correlation, cycle_tangent, tie_connection_derivative
from .tube import TubeRegression, _auto_window, _auto_windows

__all__ = ["NoiseEstimate", "estimate_noise", "interval_samples", "IntervalSamples",
           "interval_weights", "interval_noise_gains", "overlap_inflation",
           "eiv_correction", "noise_aware_regression", "blend_fits", "NoiseAwareRegression", "interval_view",
           "noise_ratio", "velocity_interval_for", "bin_bias_correction",
           "derivative_bias_correction", "derivative_bias_allowance", "phase_noise_floor",
           "normal_increments", "normal_span"]

#: the noise fit's spectrum: the mean of this many sine tapers' periodograms (Riedel and
#: Sidorenko's multitaper). A gait's strong low harmonics leak into the band through a plain
#: periodogram's sidelobes (on the 9-link reference gait at 64 samples per cycle, more than the
#: rise ω = 0.002 makes); five tapers keep the leakage local and the band average as precise
#: as a plain periodogram's
_TAPERS = 5
#: the band above this frequency (cycles per sample) is always fitted; below it the band grows
#: downwards in steps of _BAND_STEP while each step agrees with the line fitted above it
_TOP_BAND = 0.25
_BAND_STEP = 0.0125
#: lowest frequency the band may reach (below it the shape offset's slow relaxation and the
#: gait's first harmonics dominate)
_LOWEST_FREQUENCY = 0.025
#: a step joins the band while its mean is within this many standard errors of the line
#: fitted above it, in every channel and in the mean over the element's channels.
#: Contamination (the gait's harmonics spread by phase noise) is an excess at low
#: frequencies; a step that deviates by chance and is left out biases the fit, so the
#: threshold trades the two: on random walks observed with white noise (640-3780 samples)
#: 3 overestimated σ² by up to 13 %, 3.5 by up to 8-11 % and 4 by 3 %, while on the 9-link
#: reference gait at 64 samples per cycle (seeds 0-1, 4 x 30 cycles) per-channel tests alone
#: let in enough contamination to find 0-0.8 of ω ≤ 0.005; with the test of the channels'
#: mean it found 0.83-0.97
_BAND_Z = 3.5
#: the standard error of σ² treats the multitaper ordinates of the band as independent
#: periodogram ordinates; with the band chosen from the same data the spread of
#: (σ̂² − σ²)/SE was 1.07-1.15 on random walks with white noise (200 records each), so the
#: standard errors are widened by this factor
_SE_FACTOR = 1.1


@dataclass(frozen=True)
class NoiseEstimate:
    """Per-channel noise of recordings, from the spectrum of their increments.

    Attributes:
        measurement: ``(..., C)`` standard deviation of the white measurement noise
            (motion-capture noise ω), 0 where the fit finds none.
        process: ``(..., C)`` the increments' process-noise floor per sample (the standard
            deviation of a one-sample increment of the driving noise: ``η √Δt`` for a shape
            offset of the paper's SDE; a joint whose gait moves with the phase noise also gets
            ``η √Δt |γ'(φ)|``, root mean square over the cycle).
        variance_se: ``(..., C)`` standard error of ``measurement²`` (from the fit's
            information, widened by the missing fraction of the increments; ``inf`` for a
            channel with fewer than 16 present increments).
        band_low: ``(..., C)`` lowest frequency (cycles per sample) of the band fitted.
        variance: ``(..., C)`` the fitted ``σ²`` before clamping (negative where the data show
            less than no noise by chance; unbiased, so averages over trials stay unbiased).
        correlation: ``(..., C, C)`` correlation of the channels' ``σ̂²`` (they share the
            swimmer's phase noise); None: independent channels.
    """

    measurement: Tensor
    process: Tensor
    variance_se: Tensor
    band_low: Tensor | None = None
    variance: Tensor | None = None
    correlation: Tensor | None = None

    def pooled_variance(self, n_batch_dims: int, *, min_z: float = 2.0,
                        channels: bool = False, correlated: bool = True) -> Tensor:
        """Measurement variance ``(C,)``-shaped after averaging the leading ``n_batch_dims``
        dims (trials of one rig), set to 0 where it is not ``min_z`` standard errors above 0
        (clean data: the estimate is then only the periodogram's scatter). ``channels``: one
        level for all channels as well (their mean, tested as a whole, broadcast to ``C``):
        joints tracked by one rig share its noise, and a per-channel test keeps the estimates
        of weakly resolved channels that came out high (measured: one 9-link trial at
        ω = 0.002, two of eight joints kept at 1.75-1.95 ω)."""
        mean, se = self.pooled_mean(n_batch_dims, channels=channels, correlated=correlated)
        return torch.where(mean > min_z * se, mean, torch.zeros_like(mean))

    def pooled_mean(self, n_batch_dims: int, *, channels: bool = False,
                    correlated: bool = True) -> tuple[Tensor, Tensor]:
        """The unclamped mean of ``σ²`` over the leading ``n_batch_dims`` dims (and the
        channels when ``channels``) and its standard error, both ``(C,)``-shaped as
        :meth:`pooled_variance` (which tests the one against the other). The channels of one
        element are correlated by :attr:`correlation` unless ``correlated=False`` (the
        channels taken as independent, the previous standard error)."""
        var = self.measurement.square() if self.variance is None else self.variance
        dims = tuple(range(n_batch_dims)) + ((var.ndim - 1,) if channels else ())
        if not dims:
            return var, self.variance_se
        count = math.prod(var.shape[d] for d in dims)
        mean = var.mean(dims, keepdim=True)
        if channels and correlated and self.correlation is not None:
            se = self.variance_se
            # Σ_c Σ_c' se_c ρ_cc' se_c' per element (an infinite se gets ρ = 0 off the diagonal)
            finite = torch.isfinite(se)
            s = torch.where(finite, se, 0.0)
            cross = (s.unsqueeze(-1) * self.correlation * s.unsqueeze(-2)).sum((-1, -2))
            cross = torch.where(finite.all(-1), cross, math.inf)
            if n_batch_dims:
                cross = cross.sum(dims[:-1], keepdim=True)
            se = cross.unsqueeze(-1).sqrt() / count
        else:
            se = self.variance_se.square().sum(dims, keepdim=True).sqrt() / count
        shape = var.shape[n_batch_dims:]
        return (mean.reshape(mean.shape[n_batch_dims:]).expand(shape),
                se.reshape(se.shape[n_batch_dims:]).expand(shape))


def estimate_noise(x: Tensor, *, band: tuple[float, float] | None = None,
                   angular: Tensor | None = None, cycle: FourierSeries | None = None,
                   samples_per_cycle: Tensor | float | None = None,
                   floor: Literal["flat", "gait", "low_rate", "normal"] = "flat",
                   phase: Tensor | None = None) -> NoiseEstimate:
    """Measurement noise of every channel of ``x (..., T, C)``, separated from process noise.

    The increments ``u_k = x_{k+1} − x_k`` of a signal driven by white process noise (variance
    ``q²`` per sample) and observed with white measurement noise of variance ``σ²`` have the
    spectrum ``S(f) = q² + 4 sin²(πf) σ²`` away from the signal's own harmonics (``f`` in
    cycles per sample): the process noise is flat, the measurement noise rises towards
    Nyquist. ``S`` is estimated by a multitaper spectrum of the increments (:data:`_TAPERS`
    sine tapers, which keep the gait's strong harmonics from leaking across the band) and
    ``(q², σ²)`` are fitted to it by Whittle's likelihood (iteratively reweighted least squares,
    each ordinate's variance ``∝ S(f)²``). A plain variance of differences would count the
    process noise as measurement noise.

    The band is chosen per batch element: ``[0.25, 0.5]`` always, extended down in steps of
    0.0125 (to 0.025 at the lowest) while each step's mean agrees with the line fitted above
    it (within 3.5 standard errors, in each channel and in the mean over the channels): a
    gait's harmonics, spread by phase noise, raise the low frequencies and stop the band
    there. Every batch element is estimated on its own (the result does not depend on the
    other elements).

    Args:
        x: ``(..., T, C)`` recordings; NaN drop-outs allowed (the spectrum is taken with the
            gaps bridged by straight lines and its expectation counts the present increments
            only; with 5 % of the samples missing at random ``σ̂²`` came out about 6 % low on
            random walks observed with white noise).
        band: ``(f_lo, f_hi)`` to fit that band exactly, ``0 < f_lo < f_hi ≤ 0.5``; None
            (default): chosen from the data as above (``floor="normal"``: ``[0.1, 0.5]``).
        angular: optional ``(C,)`` bool, channels whose increments are wrapped to ``(−π, π]``
            (a heading recorded wrapped).
        cycle: optional :class:`~torchconn.phase.fourier.FourierSeries` of the gait each
            channel follows, ``γ(φ)`` with values ``(C,)`` and coefficients broadcastable to
            ``(..., 2K+1, C)``, with ``samples_per_cycle`` (float or ``(...)``): the
            ordinates of the top band near the gait's harmonics are left out of the fit
            (:func:`_off_harmonics`; at 32 or fewer samples per cycle they fall there); with
            ``floor="gait"`` the process floor is not flat but :func:`phase_noise_floor`'s
            shape (the gait's harmonics spread by phase noise as large as the channels' own;
            measured at 64 samples per cycle on the 3-link reference gait, a flat floor found
            0.46 of ω = 0.002), and the result's ``correlation`` holds the channels' shared
            phase noise (:func:`_channel_correlation`) for :meth:`NoiseEstimate.pooled_mean`.
        floor: with a ``cycle``, ``"flat"`` (default, as ``NoiseAwareRegression``'s
            ``noise_floor``) keeps the process floor flat and uses the cycle only for
            ``correlation``; ``"gait"`` shapes the floor as above; ``"low_rate"`` shapes it
            only for the batch elements whose gait's harmonics reach the top band (where
            :func:`_off_harmonics` leaves ordinates out: at 32 or fewer samples per cycle for
            an order-8 cycle, where the lines' tails fill the band) and keeps the others'
            flat, bit for bit. ``"normal"`` (needs ``phase``): the increments projected out of
            the span of the cycle's first derivatives (:func:`normal_increments`), fitted
            with a flat floor: the
            phase noise, which moves every channel along the cycle's tangent, is projected
            out, and with it the lines' tilt of the band (README "Noise estimates"); the band
            is fixed, ``[0.1, 0.5]`` unless ``band`` is given (:data:`_NORMAL_BAND_LOW`). The
            channels then share one measurement variance (a rig's: the projection mixes them),
            and ``correlation`` is the projected channels' (:func:`_normal_correlation`).
            With two channels (:func:`normal_span` 0) it is ``"flat"``, bit for bit.
        phase: ``(..., T)`` phase of every sample in the ``cycle``'s coordinate (unwrapped or
            wrapped; NaN where unknown), for ``floor="normal"``.

    Returns:
        :class:`NoiseEstimate` with ``(..., C)`` standard deviations (clamped at 0).

    Each batch element is estimated over its own span, from its first to its last sample with
    any finite channel (trials of different lengths on one NaN-padded grid), as it would be
    alone.
    """
    if not isinstance(x, Tensor) or not x.is_floating_point() or x.ndim < 2:
        raise TypeError("estimate_noise: x must be a floating-point tensor (..., T, C)")
    options = dict(band=band, angular=angular, floor=floor)
    batch, (T, C) = x.shape[:-2], x.shape[-2:]
    flat = x.reshape(-1, T, C)

    def rows_of(v: Tensor, rows: Tensor, trailing: int) -> Tensor:  # v's batch dims broadcast
        v = v.expand(batch + v.shape[v.ndim - trailing:])
        return v.reshape((-1,) + v.shape[len(batch):])[rows]

    def part(rows: Tensor, a: int, b: int) -> NoiseEstimate:
        spc = samples_per_cycle
        if isinstance(spc, Tensor) and spc.ndim:
            spc = rows_of(spc, rows, 0)
        return _estimate_noise(
            flat[rows, a:b],
            cycle=None if cycle is None else FourierSeries(rows_of(cycle.coeffs, rows, 2), 1),
            samples_per_cycle=spc,
            phase=None if phase is None else rows_of(phase, rows, 1)[:, a:b], **options)

    split = over_spans(torch.isfinite(flat).any(-1), part)
    if split is None:
        return _estimate_noise(x, cycle=cycle, samples_per_cycle=samples_per_cycle,
                               phase=phase, **options)
    return NoiseEstimate(**{f.name: None if getattr(split, f.name) is None else
                            getattr(split, f.name).reshape(batch + getattr(split, f.name).shape[1:])
                            for f in dataclasses.fields(NoiseEstimate)})


def _estimate_noise(x: Tensor, *, band, angular, cycle, samples_per_cycle, floor, phase
                    ) -> NoiseEstimate:
    """:func:`estimate_noise` of ``x (..., T, C)`` over the whole of ``T``."""
    if band is not None:
        lo, hi = band
        if not 0 < lo < hi <= 0.5:
            raise ValueError(f"estimate_noise: band must satisfy 0 < f_lo < f_hi <= 0.5 (cycles "
                             f"per sample), got {band!r}")
    n = x.shape[-2] - 1
    if n < 16:
        raise ValueError(f"estimate_noise: need at least 17 samples along T, got {n + 1}")
    u = torch.diff(x, dim=-2)
    if angular is not None:
        u = torch.where(angular.to(x.device), se2.wrap_angle(u), u)
    bridged = None
    if not bool(torch.isfinite(x).all()):
        bridged = torch.diff(_bridge_gaps(x), dim=-2)
        if angular is not None:
            bridged = torch.where(angular.to(x.device), se2.wrap_angle(bridged), bridged)
    if floor not in ("gait", "flat", "low_rate", "normal"):
        raise ValueError(f"estimate_noise: floor must be 'gait', 'flat', 'low_rate' or "
                         f"'normal', got {floor!r}")
    if floor == "normal" and (cycle is None or phase is None):
        raise ValueError("estimate_noise: floor='normal' projects the increments on the "
                         "cycle's normal space at every sample's phase: pass cycle= (with "
                         "samples_per_cycle=) and phase= ((..., T) like x without its channels)")
    shape = None
    if cycle is not None:
        if samples_per_cycle is None:
            raise ValueError("estimate_noise: a cycle needs its samples_per_cycle (float or "
                             "(...) tensor) to place the gait's harmonics in the spectrum")
        if cycle.value_ndim != 1 or cycle.coeffs.shape[-1] != x.shape[-1]:
            raise ValueError(f"estimate_noise: cycle must be a FourierSeries with values "
                             f"(C,) = ({x.shape[-1]},) like x's channels, got value shape "
                             f"{tuple(cycle.value_shape)}")
        shape = None if floor in ("flat", "normal") else (cycle, samples_per_cycle,
                                                           floor == "low_rate")
    weights = None
    if floor == "normal" and normal_span(x.shape[-1]) == 0:
        floor = "flat"  # two channels: nothing to project on (normal_span)
    if floor == "normal":
        if not isinstance(phase, Tensor) or tuple(phase.shape) != tuple(x.shape[:-1]):
            raise ValueError(f"estimate_noise: phase must be a tensor (..., T) = "
                             f"{tuple(x.shape[:-1])} like x without its channels, got "
                             f"{tuple(phase.shape) if isinstance(phase, Tensor) else type(phase).__name__}")
        u, frame = _project_normal(u, phase, cycle)
        if bridged is not None:
            bridged = bridged - (frame * (frame * bridged.unsqueeze(-2)).sum(-1, keepdim=True)
                                 ).sum(-2)
        weights = _normal_weights(frame)
    spec = _increment_spectrum(u, bridged, shape, weights)
    f = spec.f
    keep = None
    if cycle is not None:
        keep = _off_harmonics(f, cycle, samples_per_cycle, n)
        spec = dataclasses.replace(spec, power=spec.power * keep, x0=spec.x0 * keep,
                                   x1=spec.x1 * keep)
    if band is None and floor == "normal":
        band = (_NORMAL_BAND_LOW, 0.5)
    if band is not None:
        inside = (f >= band[0]) & (f <= band[1]) & (f > 0)
        if int(inside.sum()) < 4:
            raise ValueError(f"estimate_noise: the band {band} holds fewer than 4 frequencies "
                             f"of a {n + 1}-sample record")
        sel = inside[:, None].to(x.dtype).expand(spec.power.shape)
        low = torch.full(spec.power.shape[:-2] + spec.power.shape[-1:], float(band[0]),
                         dtype=x.dtype, device=x.device)
    else:
        sel, low = _choose_band(spec, f)
    if keep is not None:
        sel = sel * keep
    weight = torch.ones_like(spec.power)
    for _ in range(_WHITTLE_ITERATIONS):
        line = _fit_line(spec, sel, weight)
        weight = 1 / line.model.square()
    line = _fit_line(spec, sel, weight)
    # the ordinates of a record with gaps are fewer independent values than their count: the
    # variance grows as the present fraction of the increments falls
    present = torch.isfinite(u).sum(-2)
    coverage = present.to(x.dtype) / n
    usable = (torch.isfinite(line.var_se) & (line.var_se > 0) & (present >= _MIN_INCREMENTS))
    sigma2 = torch.where(usable, line.sigma2, 0.0)
    q2 = torch.where(usable, line.q2, 0.0)
    se = torch.where(usable, _SE_FACTOR * line.var_se
                     * math.sqrt(spec.density) / coverage.clamp_min(1e-12).sqrt(), math.inf)
    return NoiseEstimate(measurement=sigma2.clamp_min(0).sqrt(), process=q2.clamp_min(0).sqrt(),
                         variance_se=se, band_low=low, variance=sigma2,
                         correlation=None if cycle is None else (
                             _normal_correlation(cycle, usable) if floor == "normal"
                             else _channel_correlation(cycle, q2, sigma2, usable)
                         ).expand(sigma2.shape + sigma2.shape[-1:]))


def _channel_correlation(cycle: FourierSeries, q2: Tensor, sigma2: Tensor,
                         usable: Tensor) -> Tensor:
    """``(..., C, C)`` correlation of the channels' ``σ̂²`` when they follow the gait
    ``cycle`` with phase noise (identity where a channel is not usable).

    The joints share the swimmer's phase noise: a joint's increment carries ``γ_c'(φ) dW_φ``
    besides its own ``dW_c`` (the same ``η``, :func:`phase_noise_floor`), so the increments'
    covariance at phase ``φ`` is ``C(φ) = q²_0 (I + γ'γ'ᵀ) + 2 diag(σ²)`` (``q²_0`` the shape
    offset's own floor, ``σ²`` the measurement noise at lag 0). A band estimate of ``σ²`` is a
    quadratic form in the increments with a kernel short beside the cycle, so two channels'
    estimates correlate by ``⟨C_cc'²⟩ / √(⟨C_cc²⟩ ⟨C_c'c'²⟩)`` (means over the cycle). Measured
    on clean 3-link reference-gait recordings: the two joints' estimates correlated by 0.36
    (this formula: 0.32), and their mean, tested with independent standard errors, was called
    noise in 15 % of 4 × 30-cycle recordings (its z had spread 1.25)."""
    phi = torch.arange(_CORRELATION_GRID, dtype=q2.dtype, device=q2.device) * (
        2 * math.pi / _CORRELATION_GRID)
    slope = cycle.derivative()(phi).to(q2)  # γ'(φ), (..., P, C)
    far = 1 + slope.square().mean(-2)  # (..., C): the floor far from the lines over q²_0
    q2_0 = (q2.clamp_min(0) / far).unsqueeze(-2)  # (..., 1, C)
    carried = q2_0.sqrt() * slope  # (..., P, C): the phase noise each joint carries
    own = q2_0 + 2 * sigma2.clamp_min(0).unsqueeze(-2)  # (..., 1, C)
    cov = (carried.unsqueeze(-1) * carried.unsqueeze(-2)
           + torch.diag_embed(own.expand(carried.shape)))  # (..., P, C, C)
    second = cov.square().mean(-3)  # (..., C, C)
    scale = second.diagonal(dim1=-2, dim2=-1).clamp_min(1e-300).sqrt()
    corr = second / (scale.unsqueeze(-1) * scale.unsqueeze(-2))
    both = usable.unsqueeze(-1) & usable.unsqueeze(-2)
    eye = torch.eye(corr.shape[-1], dtype=torch.bool, device=corr.device)
    return torch.where(eye, 1.0, torch.where(both, corr, 0.0))


#: the normal projection (:func:`normal_increments`) takes out the span of the cycle's first
#: ``J = min(_NORMAL_SPAN, d // 2)`` derivatives. A phase error ``e`` moves a sample along the
#: cycle by ``γ'e − γ''e²/2 + …`` seen from the estimated point: the tangent alone
#: leaves ``e γ''`` (the curvature times the error, which the error's diffusion spreads over the
#: band); with ``γ', …, γ^(J)`` out the error enters at order ``e^J``. Tuned on the 9-link
#: reference gait at 64 samples per cycle (seeds 80-89, ω = 0.002): the band's contamination
#: per unit of ω² at 0.15-0.25 cycles per sample 7.6 / 2.0 / 0.34 / 0.06 for J = 1 / 2 / 3 / 4,
#: σ̂²/ω² −0.92 / 0.13 / 0.82 / 1.18 (J = 6: 1.28, fewer channels left)
_NORMAL_SPAN = 4
#: the normal projection's band (cycles per sample; to Nyquist), fixed: the band rule's own
#: selection (a step that deviates low by chance is kept, one that deviates high stops the
#: band) raised σ̂² by about 0.1 ω² on the projected channels, whose floor is flat to the band's
#: edge (9-link circle and reference gait at 64 samples per cycle, seeds 80-99, clean: pooled
#: recordings called noisy 15 of 80 with the rule, 2 with [0.1, 0.5]; 0.05: 8). Above 0.1 the
#: phase estimate's errors left after the projection stay below 3 % of ω = 0.002's rise there
_NORMAL_BAND_LOW = 0.1
#: harmonics of the fitted cycle whose power (summed over the channels) is below this
#: fraction of the cycle's do not shape the frame: they are the fit's estimation noise
#: (circles: ≤ 3·10⁻⁵, pooled 4 x 30 cycles), which the derivatives amplify by ``k^j`` into
#: directions that follow the data's own deviations (9-link circle: σ̂²/ω² 1.23 with them,
#: 1.12 without; its true-phase value 1.12). The 9-link reference gait carries 1.7·10⁻³ and more
#: at harmonics 1-5
_FRAME_POWER = 1e-3
#: a derivative whose part outside the span already taken is below this fraction of it (a
#: planar gait's third) adds no direction, only rounding: none is projected out there
_NEW_DIRECTION = 1e-2


def normal_span(d: int) -> int:
    """How many derivatives ``γ', …, γ^(J)`` of the cycle :func:`normal_increments` projects
    out of ``d`` channels: ``J = min(4, d // 2)``, 0 for ``d ≤ 2``: with two channels the
    one normal left carries the phase estimate's own errors (measured on the 3-link at 64
    samples per cycle: σ̂² 0.6 ω² = 0.002² too high on clean circles, and the reference gait's
    band cut at 0.15 cycles per sample), and :func:`estimate_noise` keeps the flat floor."""
    return min(_NORMAL_SPAN, d // 2) if d > 2 else 0


def normal_increments(x: Tensor, phase: Tensor, cycle: FourierSeries) -> Tensor:
    """Increments ``(..., T − 1, C)`` of recordings ``x (..., T, C)`` that follow the gait
    ``cycle`` (values ``(C,)``), projected out of the span of the cycle's first ``J``
    derivatives (:func:`normal_span`) at each interval's middle phase ``(φ_k + φ_{k+1})/2``
    (``phase (..., T)``, the cycle's coordinate; a phase gap is bridged by a straight line):
    ``P_k (x_{k+1} − x_k)``, ``P_k = I − Σ_j t_j t_jᵀ`` for the orthonormalised derivatives
    ``t_j`` (:data:`_FRAME_POWER`, :data:`_NEW_DIRECTION`).

    A channel ``x = γ(φ) + δ + ε`` moves along ``γ'`` with the phase noise; projected, the
    increments keep the offset's ``Δδ`` and the measurement noise, whose spectra stay those
    of white and MA(1) noise however ``P`` turns (its weights are known:
    :func:`_normal_weights`), and lose the phase noise and the phase estimate's errors up to
    order ``e^J``. ``J = 0`` (``d ≤ 2``): nothing is projected."""
    return _project_normal(torch.diff(x, dim=-2), phase, cycle)[0]


def _project_normal(u: Tensor, phase: Tensor, cycle: FourierSeries) -> tuple[Tensor, Tensor]:
    """Increments ``u (..., n, C)`` projected as :func:`normal_increments` (NaN where the
    phase is unknown) and the frame projected out, ``(..., n, J, C)``."""
    phase = _bridge_gaps(phase.to(u).unsqueeze(-1)).squeeze(-1)
    step = torch.remainder(phase[..., 1:] - phase[..., :-1] + math.pi, 2 * math.pi) - math.pi
    mid = phase[..., :-1] + step / 2  # (..., n)
    frame = _normal_frame(cycle, mid, normal_span(u.shape[-1]))
    projected = u - (frame * (frame * u.unsqueeze(-2)).sum(-1, keepdim=True)).sum(-2)
    return torch.where(torch.isfinite(mid).unsqueeze(-1), projected, math.nan), frame


def _normal_frame(cycle: FourierSeries, phi: Tensor, span: int) -> Tensor:
    """Orthonormalised derivatives ``γ', …, γ^(span)`` of the cycle's carried harmonics
    (:data:`_FRAME_POWER`) at phases ``phi (..., n)``: ``(..., n, span, C)``, a row 0 where it
    adds no direction (:data:`_NEW_DIRECTION`) or the phase is unknown."""
    coeffs = cycle.coeffs.to(phi)
    power = (coeffs[..., 1::2, :].square() + coeffs[..., 2::2, :].square()).sum(-1, keepdim=True)
    carried = (power >= _FRAME_POWER * power.sum(-2, keepdim=True)).to(phi.dtype)  # (..., K, 1)
    keep = torch.cat([torch.ones_like(carried[..., :1, :]),
                      carried.repeat_interleave(2, dim=-2)], -2)
    shape = FourierSeries(coeffs * keep, value_ndim=1)
    frame: list[Tensor] = []
    for j in range(1, span + 1):
        v = _series_at(shape.derivative(j), phi)  # (..., n, C)
        whole = v.square().sum(-1, keepdim=True).sqrt()
        for w in frame:
            v = v - w * (w * v).sum(-1, keepdim=True)
        norm = v.square().sum(-1, keepdim=True).sqrt()
        new = torch.isfinite(norm) & (norm > _NEW_DIRECTION * whole)
        frame.append(torch.where(new, v / torch.where(new, norm, 1.0), 0.0))
    if not frame:
        return phi.new_zeros(phi.shape + (0, coeffs.shape[-1]))
    return torch.stack(frame, -2)


def _series_at(series: FourierSeries, phi: Tensor) -> Tensor:
    """``series (values (C,))`` at phases ``phi (..., n)`` -> ``(..., n, C)``, by elementwise
    sums over the harmonics on a time axis padded to whole kernel chunks (a matrix product,
    or a sin over a batch's unpadded rows, rounds an element's values with its batch)."""
    n = phi.shape[-1]
    padded = nn.functional.pad(phi, (0, -n % _KERNEL_CHUNK))
    coeffs = series.coeffs.to(phi)  # (..., 2K+1, C)
    out = coeffs[..., 0:1, :]
    for j in range(1, series.order + 1):
        kphi = (j * padded).unsqueeze(-1)
        out = (out + torch.cos(kphi) * coeffs[..., 2 * j - 1:2 * j, :]
               + torch.sin(kphi) * coeffs[..., 2 * j:2 * j + 1, :])
    return out[..., :n, :]


def _normal_weights(frame: Tensor) -> tuple[Tensor, Tensor]:
    """The projected increments' variance and lag-1 covariance per unit of white noise:
    ``P_ii`` at every increment ``(..., n, C)`` and ``(P_k P_{k+1})_ii`` for every pair of
    neighbours ``(..., n − 1, C)``, ``P = I − Σ_j t_j t_jᵀ`` for the frame ``t (..., n, J, C)``."""
    t0, t1 = frame[..., :-1, :, :], frame[..., 1:, :, :]
    cross = (t0.unsqueeze(-2) * t1.unsqueeze(-3)).sum(-1, keepdim=True)  # (..., n-1, J, J, 1)
    lag1 = (1 - t0.square().sum(-2) - t1.square().sum(-2)
            + (t0.unsqueeze(-2) * t1.unsqueeze(-3) * cross).sum((-2, -3)))
    return 1 - frame.square().sum(-2), lag1


def _normal_correlation(cycle: FourierSeries, usable: Tensor) -> Tensor:
    """``(..., C, C)`` correlation of the normal-projected channels' ``σ̂²``
    (:func:`normal_increments`): their increments' covariance is ``P(φ)`` times one level
    (white offset and measurement noise alike), so, as in :func:`_channel_correlation`, two
    channels' estimates correlate by ``⟨P_cc'²⟩ / √(⟨P_cc²⟩ ⟨P_c'c'²⟩)`` over the cycle."""
    d = usable.shape[-1]
    phi = torch.arange(_CORRELATION_GRID, dtype=cycle.coeffs.dtype, device=usable.device) * (
        2 * math.pi / _CORRELATION_GRID)
    frame = _normal_frame(cycle, phi, normal_span(d))  # (..., P, J, C)
    eye = torch.eye(d, dtype=phi.dtype, device=phi.device)
    proj = eye - (frame.unsqueeze(-1) * frame.unsqueeze(-2)).sum(-3)  # (..., P, C, C)
    second = proj.square().mean(-3)
    scale = second.diagonal(dim1=-2, dim2=-1).clamp_min(1e-300).sqrt()
    corr = second / (scale.unsqueeze(-1) * scale.unsqueeze(-2))
    both = usable.unsqueeze(-1) & usable.unsqueeze(-2)
    return torch.where(eye.bool(), 1.0, torch.where(both, corr, 0.0))


#: standard errors the joints' mean noise variance must stand above 0 for
#: :meth:`NoiseAwareRegression.noise_setup` to correct for it (README "Noise estimates")
_NOISE_MIN_Z = 2.0

#: phases over the cycle at which :func:`_channel_correlation` averages
_CORRELATION_GRID = 128


#: a harmonic of the cycle whose power (summed over the channels) is at most this fraction of
#: the cycle's is not carried (:func:`_off_harmonics`): rounding level, far below any line
_CARRIED_POWER = 1e-20

#: fewest present increments for a channel's estimate (fewer: no estimate, ``variance_se``
#: infinite, as for a record shorter than 17 samples)
_MIN_INCREMENTS = 16
#: reweighting passes of the Whittle fit (from the unweighted line; it settles in two or three)
_WHITTLE_ITERATIONS = 3


@dataclass(frozen=True)
class _Spectrum:
    """Multitaper spectrum ``power (..., F, C)`` of zero-filled increments and the columns
    ``x0, x1 (..., F, C)`` of its expectation ``q² x0 + σ² x1`` for the record's own gaps."""

    power: Tensor
    x0: Tensor  # s0 · the floor's shape, s0 = Σ a_t² (taper times mask, mean over tapers)
    x1: Tensor  # 2 s0 − 2 s1 cos 2πf, s1 = Σ a_t a_{t+1}
    f: Tensor  # (F,) frequencies, cycles per sample
    density: float  # ordinates per independent ordinate (the FFT length over the record's)


def _bridge_gaps(x: Tensor) -> Tensor:
    """``x (..., T, C)`` with interior NaN runs filled by straight lines between their
    neighbours (leading and trailing runs stay NaN)."""
    ok = torch.isfinite(x)
    idx = torch.arange(x.shape[-2], device=x.device)[:, None].expand(x.shape)
    prev = torch.where(ok, idx, -1).cummax(-2).values
    nxt = torch.where(ok, idx, x.shape[-2]).flip(-2).cummin(-2).values.flip(-2)
    inside = ~ok & (prev >= 0) & (nxt < x.shape[-2])
    x0 = torch.gather(torch.where(ok, x, 0.0), -2, prev.clamp_min(0))
    x1 = torch.gather(torch.where(ok, x, 0.0), -2, nxt.clamp_max(x.shape[-2] - 1))
    frac = (idx - prev).to(x.dtype) / (nxt - prev).clamp_min(1).to(x.dtype)
    return torch.where(inside, x0 + frac * (x1 - x0), x)


def _increment_spectrum(u: Tensor, bridged: Tensor | None = None,
                        shape: tuple[FourierSeries, Tensor | float, bool] | None = None,
                        weights: tuple[Tensor, Tensor] | None = None) -> _Spectrum:
    """:class:`_Spectrum` of increments ``u (..., n, C)`` (NaN where missing); ``shape``:
    None (a flat process floor) or ``(cycle, samples_per_cycle, low_rate)`` for
    :func:`phase_noise_floor`'s floor (with ``low_rate`` only for the batch elements whose
    gait's harmonics reach the top band, :func:`_off_harmonics`; flat for the others).

    Zeros in place of missing increments would spread the gait's strong lines over the whole
    spectrum (a random mask leaks a line's power everywhere), so the spectrum is taken of
    ``bridged``, the increments of the recording with its gaps bridged by straight lines (the
    signal goes on, the noise does not), while the expectation below counts only the present
    increments of ``u``.

    With the taper ``a_t = w_t m_t`` (taper times the 0/1 mask of present increments), white
    process increments (lag-0 covariance ``q²``) and the measurement noise's MA(1) increments
    (``2σ²`` at lag 0, ``−σ²`` at lag 1) give ``E|Σ a_t u_t e^{−2πift}|² = (q² + 2σ²) Σ a_t²
    − 2σ² cos(2πf) Σ a_t a_{t+1}`` exactly, whatever the gaps. ``weights``: the increments'
    white variance ``w_t (..., n, C)`` and lag-1 covariance ``v_t (..., n − 1, C)`` per unit
    of each noise where they vary along the record (:func:`_normal_weights`): then ``Σ a_t²``
    becomes ``Σ a_t² w_t`` and ``Σ a_t a_{t+1}`` becomes ``Σ a_t a_{t+1} v_t``.
    """
    n = u.shape[-2]
    present = torch.isfinite(u)
    m = present.to(u.dtype)
    source = u if bridged is None else bridged
    usable = torch.isfinite(source)
    filled = torch.where(usable, source, 0.0)
    mean = filled.sum(-2, keepdim=True) / usable.sum(-2, keepdim=True).clamp_min(1)
    filled = torch.where(usable, filled - mean, 0.0)
    t = torch.arange(1, n + 1, dtype=u.dtype, device=u.device)
    j = torch.arange(1, _TAPERS + 1, dtype=u.dtype, device=u.device)[:, None]
    tapers = (math.sqrt(2 / (n + 1)) * torch.sin(math.pi * j * t / (n + 1)))[:, :, None]
    # time last and a length of small primes (the tapers end at 0, so zeros may follow):
    # an FFT of 1919 = 19·101 samples along a middle dim took 6 times as long
    n_fft = _fft_length(n)
    tapered = (tapers * filled.unsqueeze(-3)).transpose(-1, -2)
    power = torch.fft.rfft(tapered, n=n_fft, dim=-1).abs().square().mean(-3).transpose(-1, -2)
    a = tapers * m.unsqueeze(-3)  # (..., K, n, C)
    w0, w1 = (1.0, 1.0) if weights is None else (w.unsqueeze(-3) for w in weights)
    s0 = (a.square() * w0).sum(-2).mean(-2).unsqueeze(-2)  # (..., 1, C)
    s1 = (a[..., :-1, :] * a[..., 1:, :] * w1).sum(-2).mean(-2).unsqueeze(-2)
    f = torch.fft.rfftfreq(n_fft, dtype=u.dtype, device=u.device)
    cos = torch.cos(2 * math.pi * f)[:, None]
    floor = s0
    if shape is not None:
        cycle, per_cycle, low_rate = shape
        gait = phase_noise_floor(f, cycle, per_cycle, n=n)  # (..., F, C)
        if low_rate:  # (..., 1, 1): a harmonic in the top band (ordinates left out there)
            reach = (_off_harmonics(f, cycle, per_cycle, n) == 0).any(-2, keepdim=True)
            gait = torch.where(reach, gait, 1.0)
        floor = s0 * gait
    x0, x1 = torch.broadcast_tensors(floor, 2 * s0 - 2 * cos * s1)
    return _Spectrum(power=power, x0=x0.expand(power.shape), x1=x1.expand(power.shape),
                     f=f, density=n_fft / n)


def phase_noise_floor(f: Tensor, cycle: FourierSeries, samples_per_cycle: Tensor | float, *,
                      n: int) -> Tensor:
    """The shape ``(..., F, C)`` of the increments' process floor at frequencies ``f (F,)``
    (cycles per sample) for channels that follow the gait ``cycle`` (a
    :class:`~torchconn.phase.fourier.FourierSeries`, values ``(C,)``) with phase noise, 1 far
    from the gait's harmonics.

    A channel ``r = γ(φ) + δ`` whose phase and offset are random walks of the same variance
    ``q²`` per sample (the paper's SDE, one ``η`` for both) has increments whose spectrum is
    ``q² (1 + Σ_k k² |c_k|² sin²(πf) / sin²(π(f − k/N)))`` over the harmonics ``k = ±1, ±2,
    …`` of ``γ`` (complex coefficients ``c_k``, ``N`` samples per cycle): each harmonic is a
    line broadened by the phase diffusion, and its tails in the increments rise towards the
    line. Far from every line it is ``q² (1 + ⟨γ'²⟩)``, the floor this shape is divided by.
    ``n`` (the record's increments) sets the multitaper's bandwidth, which bounds the lines'
    cores (the band excludes them: they are not modelled).
    """
    coeffs = cycle.coeffs.to(f)
    a, b = coeffs[..., 1::2, :], coeffs[..., 2::2, :]  # (..., K, C)
    n_harmonics = a.shape[-2]
    k = torch.arange(1, n_harmonics + 1, dtype=f.dtype, device=f.device)
    weight = k[:, None].square() * (a.square() + b.square()) / 4  # k² |c_k|², (..., K, C)
    per_cycle = torch.as_tensor(samples_per_cycle, dtype=f.dtype, device=f.device)
    # sin, cos of each element's π k/N on rows padded to whole kernel chunks (they round a
    # tensor's last partial chunk differently: an element's floor must not depend on its
    # batch); the rest is + − × ÷ on them and on batch-free sin, cos of π f
    theta = nn.functional.pad(math.pi * k / per_cycle[..., None],
                              (0, -n_harmonics % _KERNEL_CHUNK))
    sin_k, cos_k = torch.sin(theta), torch.cos(theta)  # (..., K padded)
    sin_f, cos_f = torch.sin(math.pi * f), torch.cos(math.pi * f)  # (F,)
    width = math.sin(math.pi * (_TAPERS + 1) / (2 * n)) ** 2
    total, far = 1.0, 1.0
    for j in range(n_harmonics):  # sin²(π(f ∓ k/N)) by the angle-difference formula
        s, c = sin_k[..., j, None], cos_k[..., j, None]
        tails = sum(sin_f.square() / ((sin_f * c - sign * cos_f * s).square() + width)
                    for sign in (1, -1))  # (..., F)
        total = total + tails.unsqueeze(-1) * weight[..., j, None, :]
        far = far + 2 * weight[..., j, None, :]
    return total / far


def _off_harmonics(f: Tensor, cycle: FourierSeries, samples_per_cycle: Tensor | float,
                   n: int) -> Tensor:
    """``(..., F, 1)``: 0 at the ordinates of the top band (``f ≥`` :data:`_TOP_BAND`) within
    the tapers' half bandwidth ``(K + 1) / (2 (n + 1))`` of a harmonic ``k/N`` the gait
    carries (``N = samples_per_cycle``; folded into ``[0, 0.5]`` where it lies past Nyquist),
    1 elsewhere. The harmonics carried are those of the ``cycle`` (values ``(C,)``) whose
    power summed over the channels is above :data:`_CARRIED_POWER` of the cycle's (the
    limit cycle's order, 8 by default: the cycle through the bins carries the higher ones at
    rounding level only).

    Below about 32 samples per cycle the gait's harmonics fall into the top band, where the
    noise fit takes their power for noise: a line near Nyquist rises there as ``σ²``'s column
    does (3-link reference gait at 10 samples per cycle, clean: σ̂ 0.12 rad, Â 38 % off; fixed
    here). Not fixed: the lines' phase-noise tails beside the cores, which at 8 samples per
    cycle still read as noise and at 12-20 drive ``σ̂²`` below 0 (ω = 0.005: none detected;
    ``floor="low_rate"`` models them, but on the 3-link reference gait ω = 0.005 is then only
    0.2-0.5 standard errors of ``σ̂²`` in 3 × 20 cycles: README "Few samples per cycle").
    At 32 or more samples per cycle an order-8 cycle's harmonics stay at or below 0.25 (at 64
    or more below it: nothing is left out)."""
    coeffs = cycle.coeffs.to(f)
    power = (coeffs[..., 1::2, :].square() + coeffs[..., 2::2, :].square()).sum(-1)  # (..., K)
    carried = power > _CARRIED_POWER * power.sum(-1, keepdim=True)
    per_cycle = torch.as_tensor(samples_per_cycle, dtype=f.dtype, device=f.device)
    k = torch.arange(1, power.shape[-1] + 1, dtype=f.dtype, device=f.device)
    line = torch.remainder(k / per_cycle[..., None], 1.0)  # (..., K)
    line = torch.minimum(line, 1 - line)
    half_width = (_TAPERS + 1) / (2 * (n + 1))
    near = (f[:, None] - line.unsqueeze(-2)).abs() <= half_width  # (..., F, K)
    near = (near & carried.unsqueeze(-2)).any(-1)  # (..., F)
    return (~(near & (f >= _TOP_BAND))).to(f.dtype).unsqueeze(-1)


def _fft_length(n: int) -> int:
    """The smallest length ``≥ n`` whose prime factors are 2, 3 and 5."""
    m = n
    while True:
        k = m
        for prime in (2, 3, 5):
            while k % prime == 0:
                k //= prime
        if k == 1:
            return m
        m += 1


@dataclass(frozen=True)
class _Line:
    """A fitted ``q² x0 + σ² x1`` (``(..., C)`` each), its model ``(..., F, C)`` and the
    covariance of ``(q², σ²)``."""

    q2: Tensor
    sigma2: Tensor
    model: Tensor
    cov: tuple[Tensor, Tensor, Tensor]  # (q², q²), (q², σ²), (σ², σ²)

    @property
    def var_se(self) -> Tensor:
        return self.cov[2].clamp_min(0).sqrt()


def _fit_line(spec: _Spectrum, sel: Tensor, weight: Tensor) -> _Line:
    """Weighted least squares of ``spec.power`` on ``[x0, x1]`` over the ordinates ``sel``
    ``(..., F, C)`` (0/1), with the covariance of independent ordinates of variance
    ``model²`` (the sandwich; ``weight = 1/model²`` makes it the inverse information)."""
    x0, x1, p = spec.x0, spec.x1, spec.power
    w = sel * weight
    a, b, d = (w * x0 * x0).sum(-2), (w * x0 * x1).sum(-2), (w * x1 * x1).sum(-2)
    r0, r1 = (w * x0 * p).sum(-2), (w * x1 * p).sum(-2)
    q2, s2, det = _solve_2x2(a, b, d, r0, r1)
    model = q2.unsqueeze(-2) * x0 + s2.unsqueeze(-2) * x1
    # a fitted line that dips towards 0 somewhere would give those ordinates all the weight
    mean = (sel * p).sum(-2, keepdim=True) / sel.sum(-2, keepdim=True).clamp_min(1)
    model = torch.maximum(model, 0.1 * mean)
    v = w * weight * model.square()
    e00, e01, e11 = (v * x0 * x0).sum(-2), (v * x0 * x1).sum(-2), (v * x1 * x1).sum(-2)
    return _Line(q2=q2, sigma2=s2, model=model,
                 cov=_sandwich_2x2(a, b, d, det, e00, e01, e11))


def _solve_2x2(a: Tensor, b: Tensor, d: Tensor, r0: Tensor, r1: Tensor
               ) -> tuple[Tensor, Tensor, Tensor]:
    """``(q², σ²)`` of the normal equations ``[[a, b], [b, d]] (q², σ²) = (r0, r1)`` and their
    determinant (NaN where it is not positive); all ``(..., C)``."""
    det = a * d - b * b
    det = torch.where(det > 0, det, math.nan)
    return (d * r0 - b * r1) / det, (a * r1 - b * r0) / det, det


def _sandwich_2x2(a: Tensor, b: Tensor, d: Tensor, det: Tensor, e00: Tensor, e01: Tensor,
                  e11: Tensor) -> tuple[Tensor, Tensor, Tensor]:
    """Covariance ``(q², q²), (q², σ²), (σ², σ²)`` of :func:`_solve_2x2`'s solution: the
    sandwich ``I⁻¹ E I⁻¹`` of the normal matrix ``I = [[a, b], [b, d]]`` and the ordinates'
    ``E = [[e00, e01], [e01, e11]]``."""
    i00, i01, i11 = d / det, -b / det, a / det
    return (i00 * i00 * e00 + 2 * i00 * i01 * e01 + i01 * i01 * e11,
            i00 * i01 * e00 + (i00 * i11 + i01 * i01) * e01 + i01 * i11 * e11,
            i01 * i01 * e00 + 2 * i01 * i11 * e01 + i11 * i11 * e11)


def _choose_band(spec: _Spectrum, f: Tensor) -> tuple[Tensor, Tensor]:
    """Ordinates ``(..., F, C)`` (0/1) of the band of every channel and its low edge
    ``(..., C)``: the top band, grown downwards step by step while each step's mean agrees
    with the unweighted line fitted above it (the line's own uncertainty included).

    Every sum the fits need is a sum over each step of a product of the columns ``x0, x1``
    and the power (:func:`_step_sums`): the scan runs on ``(..., steps, C)`` sums, not on the
    spectrum.
    """
    dtype, power = spec.power.dtype, spec.power
    n_steps = int(round((_TOP_BAND - _LOWEST_FREQUENCY) / _BAND_STEP))
    edges = _TOP_BAND - _BAND_STEP * torch.arange(n_steps + 1, dtype=dtype, device=f.device)
    # group 0: the top band; group i: [edge_i, edge_{i-1})
    group = torch.stack([(f >= edges[0]) & (f > 0)]
                        + [(f >= edges[i]) & (f < edges[i - 1]) & (f > 0)
                           for i in range(1, n_steps + 1)]).to(dtype)  # (G, F)
    counts = group.sum(-1)
    sums = _step_sums(group, spec.x0, spec.x1, power)  # {(i, j, p): (..., G, C)}
    running = {key: value[..., 0, :] for key, value in sums.items()}
    growing = torch.ones_like(running[0, 0, 0], dtype=torch.bool)
    low = torch.full_like(running[0, 0, 0], _TOP_BAND)
    for g in range(1, n_steps + 1):  # a few frequency steps, each batched over all channels
        count = counts[g]
        if count == 0:
            continue
        a, bb, d = running[2, 0, 0], running[1, 1, 0], running[0, 2, 0]
        q2, s2, det = _solve_2x2(a, bb, d, running[1, 0, 1], running[0, 1, 1])

        # Σ x0^i x1^j (q² x0 + σ² x1)² for (i, j) = (2, 0), (1, 1), (0, 2)
        e00, e01, e11 = (q2 * q2 * running[i + 2, j, 0] + 2 * q2 * s2 * running[i + 1, j + 1, 0]
                         + s2 * s2 * running[i, j + 2, 0] for i, j in ((2, 0), (1, 1), (0, 2)))
        c00, c01, c11 = _sandwich_2x2(a, bb, d, det, e00, e01, e11)
        m0, m1 = sums[1, 0, 0][..., g, :] / count, sums[0, 1, 0][..., g, :] / count
        expected = q2 * m0 + s2 * m1
        observed = sums[0, 0, 1][..., g, :] / count
        spread = spec.density * (expected.square() / count + m0 * m0 * c00 + 2 * m0 * m1 * c01
                                 + m1 * m1 * c11)
        z = (observed - expected) / spread.clamp_min(1e-300).sqrt()
        # each channel, and the element's channels together: the gait's harmonics raise
        # every joint a little, which the mean of the channels' z shows sooner
        finite = torch.isfinite(z)
        n_finite = finite.sum(-1, keepdim=True).clamp_min(1)
        joint = torch.where(finite, z, 0.0).sum(-1, keepdim=True) / n_finite.sqrt()
        growing = growing & (z.abs() < _BAND_Z) & (joint.abs() < _BAND_Z)
        grow = growing.to(dtype)
        running = {key: running[key] + grow * sums[key][..., g, :] for key in running}
        low = torch.where(growing, edges[g], low)
    sel = ((f[:, None] >= low.unsqueeze(-2)) & (f[:, None] > 0)).to(dtype)
    return sel, low


def _step_sums(group: Tensor, x0: Tensor, x1: Tensor, power: Tensor) -> dict:
    """``Σ x0^i x1^j p^k`` over each step's ordinates (``group (G, F)``, 0/1) for the
    products the band scan needs: ``{(i, j, k): (..., G, C)}`` from ``(..., F, C)`` columns
    (``i + j`` up to 4 with ``k = 0``, up to 1 with ``k = 1``)."""
    keys = [(i, m - i, 0) for m in range(5) for i in range(m + 1)]
    keys += [(0, 0, 1), (1, 0, 1), (0, 1, 1)]
    return {(i, j, k): torch.einsum("gf,...fc->...gc", group,
                                    x0**i * x1**j * (power if k else 1))
            for i, j, k in keys}


#: shapes of the velocity filter over an interval (:func:`interval_weights`)
VELOCITY_KERNELS = ("box", "triangle")
#: the filter of :func:`interval_samples` (and so of :class:`NoiseAwareRegression`): measured
#: on seed 5 (3-/5-link circle, 3-link reference and 5-link wave gaits, pooled 4 x 30 cycles,
#: ω = 0.005-0.01, the best of intervals 8-24 and windows 2-4 for each) the triangle's Â error
#: was 0.61-0.90 times the box's (5-link circle ω = 0.01: 10.6 % vs 17.3 %); a Hann window was
#: no better than the triangle (0.97-1.08 times)
VELOCITY_KERNEL = "triangle"


def interval_weights(h: int, kernel: str = VELOCITY_KERNEL, *, dtype=torch.float64,
                     device=None) -> Tensor:
    """Weights ``u (h,)`` (sum 1) of the ``h`` one-sample intervals in a velocity filter.

    ``"box"``: ``1/h`` (the mean over the interval); ``"triangle"``: ``∝ 1 − |x|`` at the
    intervals' centres ``x ∈ (−1, 1)``. A filter's output is ``Σ_j u_j v_j`` of the one-sample
    velocities ``v_j``; on the samples it is ``Σ_j a_j x_j / Δt`` with ``a_j = u_j − u_{j+1}``,
    so white measurement noise of variance ``σ²`` enters with ``σ² Σ a_j² / Δt²``: ``2σ²/h²``
    for the box (its sharp edges), ``≈ 16σ²/(h+1)³`` for the triangle.
    """
    return torch.tensor(_weights(h, kernel), dtype=dtype, device=device)


def _weights(h: int, kernel: str) -> list[float]:
    """:func:`interval_weights` as numbers (the filter's constants need no device)."""
    if kernel not in VELOCITY_KERNELS:
        raise ValueError(f"velocity kernel must be one of {VELOCITY_KERNELS}, got {kernel!r}")
    u = [1.0 if kernel == "box" else 1 - abs(2 * j - h - 1) / (h + 1) for j in range(1, h + 1)]
    total = sum(u)
    return [v / total for v in u]


def _filter_taps(h: int, kernel: str) -> tuple[list[float], list[float]]:
    """The sample taps ``a (h + 1)`` of the velocity filter and ``b (h + 1)`` of its mid-point
    shape: ``a_j = u_j − u_{j+1}``, ``b_j = (u_j + u_{j+1}) / 2`` with ``u_0 = u_{h+1} = 0``."""
    u = [0.0, *_weights(h, kernel), 0.0]
    return ([u[j] - u[j + 1] for j in range(h + 1)],
            [(u[j] + u[j + 1]) / 2 for j in range(h + 1)])


def _autocorrelation(x: list[float], lag: int) -> float:
    """``Σ_i x_i x_{i+lag}``."""
    return sum(x[i] * x[i + lag] for i in range(len(x) - lag))


@dataclass(frozen=True)
class IntervalSamples:
    """Samples filtered over intervals of ``h`` recorded samples (``N = T − h`` intervals).

    With the filter's weights ``u_j`` (:func:`interval_weights`) on the one-sample intervals
    ``[t_{k+j−1}, t_{k+j}]``, ``j = 1…h``:

    Attributes:
        phase: ``(..., N)`` phase at each interval's middle.
        r: ``(..., N, d)`` the weighted mean of the one-sample mid-points ``Σ u_j (r_{k+j−1} +
            r_{k+j})/2`` (box: ``(r_k + r_{k+h}) / 2``).
        r_dot: ``(..., N, d)`` weighted mean shape velocity ``Σ u_j (r_{k+j} − r_{k+j−1})/Δt``
            (box: ``(r_{k+h} − r_k) / (hΔt)``).
        xi: ``(..., N, 3)`` weighted mean body velocity ``Σ u_j log(g_{k+j−1}⁻¹ g_{k+j})/Δt``
            (box: ``log(g_k⁻¹ g_{k+h}) / (hΔt)``).
        h: the interval in samples; dt: the sampling interval; kernel: the filter's shape.
    """

    phase: Tensor
    r: Tensor
    r_dot: Tensor
    xi: Tensor
    h: int
    dt: float
    kernel: str = VELOCITY_KERNEL

    def noise_gains(self) -> tuple[float, float]:
        """Factors ``(g_r, g_ṙ)`` by which a joint angle's white measurement-noise variance
        enters ``r`` and ``r_dot``. The two noises are uncorrelated for every filter:
        ``Σ a_j b_j = Σ (u_j² − u_{j+1}²)/2 = 0``."""
        return interval_noise_gains(self.h, self.dt, self.kernel)


def interval_noise_gains(h: int, dt: float, kernel: str = VELOCITY_KERNEL
                         ) -> tuple[float, float]:
    """``(Σ b_j², Σ a_j² / Δt²)``: the noise gains of :class:`IntervalSamples` (box: ``1/2`` and
    ``2/(hΔt)²``, the end points' mean and difference)."""
    if kernel == "box" or h == 1:
        return 0.5, 2 / (h * dt) ** 2
    a, b = _filter_taps(h, kernel)
    return _autocorrelation(b, 0), _autocorrelation(a, 0) / dt**2


def interval_samples(pose: Tensor, r: Tensor, phase: Tensor, dt: float, h: int,
                     kernel: str = VELOCITY_KERNEL) -> IntervalSamples:
    """Target and regressors filtered identically over ``h`` samples (nothing else smoothed).

    Args:
        pose: ``(..., T, 3)``; r: ``(..., T, d)``; phase: ``(..., T)`` (unwrapped or wrapped);
            dt: sampling interval; h: interval in samples, ``1 ≤ h < T``; kernel: the filter
            (:func:`interval_weights`; at ``h = 1`` every filter is the one-sample difference).

    Returns:
        :class:`IntervalSamples` ``(..., T − h, ·)``.
    """
    T = r.shape[-2]
    if isinstance(h, bool) or not isinstance(h, int) or not 1 <= h < T:
        raise ValueError(f"velocity interval h must be an integer in [1, {T - 1}], got {h!r}")
    if kernel not in VELOCITY_KERNELS:
        raise ValueError(f"velocity kernel must be one of {VELOCITY_KERNELS}, got {kernel!r}")
    span = h * dt
    step = se2.wrap_angle(phase[..., h:] - phase[..., :-h])
    mid_phase = phase[..., :-h] + step / 2
    if kernel == "box" or h == 1:
        return IntervalSamples(
            phase=mid_phase,
            r=(r[..., h:, :] + r[..., :-h, :]) / 2,
            r_dot=(r[..., h:, :] - r[..., :-h, :]) / span,
            xi=se2.log(se2.relative(pose[..., :-h, :], pose[..., h:, :])) / span,
            h=h, dt=float(dt), kernel=kernel,
        )
    u = interval_weights(h, kernel, dtype=r.dtype, device=r.device)

    def filtered(x: Tensor) -> Tensor:  # one-sample values (..., T − 1, C) -> (..., T − h, C)
        return x.unfold(-2, h, 1) @ u

    one_step = se2.log(se2.relative(pose[..., :-1, :], pose[..., 1:, :])) / dt
    return IntervalSamples(
        phase=mid_phase, r=filtered((r[..., 1:, :] + r[..., :-1, :]) / 2),
        r_dot=filtered(torch.diff(r, dim=-2) / dt), xi=filtered(one_step),
        h=h, dt=float(dt), kernel=kernel,
    )


def overlap_inflation(bins: BinIndex, h: int, kernel: str = VELOCITY_KERNEL) -> Tensor:
    """Factor ``κ (..., M)`` by which the rows' overlap inflates each bin's coefficient
    variance over the solver's, which treats the rows as independent.

    A filter over ``h`` samples makes the measurement-noise part of consecutive rows
    correlated: its autocovariance at lag ``l`` is ``∝ ρ_a(l) = Σ a_j a_{j+l}``, the
    regressors' (process) part's ``∝ ρ_u(l) = Σ u_j u_{j+l}``. A bin's weighted rows
    ``w_k`` then have ``κ = 1 + 2 Σ_{l≥1} [ρ_u(l) ρ_a(l) / (ρ_u(0) ρ_a(0))] c(l)`` with
    ``c(l) = Σ_k w_k w_{k+l} / Σ_k w_k²`` (the bin's own run of consecutive rows). For the box
    ``ρ_a`` vanishes at every lag ``0 < l < h`` and ``ρ_u(h) = 0``, so ``κ = 1``; the triangle
    at ``h = 8-24`` gives 2.4-7. Measured against the swimmer's exact connection (seed 5,
    3-/5-link, ω = 0.005-0.01, ``h`` 8-24, windows 1-4) the squared errors are 0.75-1.3 times
    the variance with ``κ`` where the bias is small (2-9 times without).
    """
    batch = tuple(bins.batch_shape)
    m = bins.n_bins
    if kernel == "box" or h == 1:
        return bins.weight.new_ones(batch + (m,))
    u, (a, _) = _weights(h, kernel), _filter_taps(h, kernel)
    lags = range(1, h)
    norm0 = _autocorrelation(u, 0) * _autocorrelation(a, 0)
    rho = [_autocorrelation(u, lag) * _autocorrelation(a, lag) / norm0 for lag in lags]
    w = bins.weight.reshape(-1, bins.max_count)
    dense = w.new_zeros(w.shape[0], bins.n_points)
    dense.scatter_add_(1, bins.index.reshape(w.shape).to(w.device), w)
    norm = dense.square().sum(-1).clamp_min(1e-300)
    kappa = torch.ones_like(norm)
    for lag, r in zip(lags, rho, strict=True):
        if r != 0:
            kappa = kappa + 2 * r * (dense[:, :-lag] * dense[:, lag:]).sum(-1) / norm
    return kappa.clamp_min(1e-3).reshape(batch + (m,))


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
    joint_covariance: Literal["solver", "robust"] | None = None,
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
            ``∂Â/∂r`` (``cov_b_dA``, for the tie): ``"solver"`` the sandwich whose diagonal
            gives the standard errors (:func:`~torchconn.regression._wls.sandwich_correlation`
            times them, overlap inflation included); ``"robust"`` from the rows' own scores
            (:func:`~torchconn.regression._wls.score_covariance`: heteroscedastic, with the
            correction's share of each row, :func:`eiv_row_correction`, and rows up to ``h``
            samples apart correlated; no overlap inflation, which it replaces). The fit's
            other fields are the same bit for bit.
        cycles: ``(..., N)`` int64, the whole cycle each sample belongs to (e.g.
            :func:`interval_cycles`), numbered from 0 within the batch element: also each
            cycle's share of the error of ``Â`` (``influence_A``, ``(..., M, 3, d, C)``,
            :func:`~torchconn.regression._wls.cluster_scores` with the rows' noise
            correction): rows of one cycle are correlated (the filter's overlap, the phase
            noise) and one cycle's rows fall in every bin, so its shares carry the
            correlation of ``Â`` across entries and bins. The fit's other fields are the same
            bit for bit.

    Returns:
        :class:`~torchconn.regression.ConnectionFit`. The standard errors are the solver's
        (rows independent) times ``√κ`` for the rows' overlap (:func:`overlap_inflation`; 1
        for the box filter, whose errors measured 0.9-1.1 times its squared standard errors).
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
    var_delta, var_rate = _bin_noise(samples, s, noise_var)

    def correction(gram: Tensor, sel) -> Tensor:
        return eiv_correction(gram, var_delta[sel], var_rate[sel])

    def row_correction(xw: Tensor, beta: Tensor, sel) -> Tensor:
        return eiv_row_correction(xw, beta, var_delta[sel], var_rate[sel])

    free = ridge_exemptions(d, ridge_connection, s.r.device)
    sol = _wls.solve(s, _blocks, p, fn=fn, delta_max=delta_max, ridge=ridge, min_samples=None,
                     max_condition=None, on_ill_conditioned=on_ill_conditioned,
                     correction=correction, unpenalised=free)
    kappa = overlap_inflation(bins, samples.h, samples.kernel).to(sol.se).reshape(-1, 1, 1)
    se = sol.se * kappa.sqrt()  # (B·M, P, K)
    cov = None
    if joint_covariance is not None:
        # b̂'s columns δ and the direct estimate's δ̇⊗δ (connection_design's order)
        columns = torch.cat([torch.arange(1, 1 + d, device=s.r.device),
                             torch.arange(1 + 2 * d, p, device=s.r.device)])
        if joint_covariance == "solver":
            corr = _wls.sandwich_correlation(s, _blocks, sol, columns, delta_max=delta_max,
                                             correction=correction, unpenalised=free)
            se_c = se[:, columns].mT  # (B·M, K, c)
            cov = corr.unsqueeze(1) * (se_c.unsqueeze(-1) * se_c.unsqueeze(-2))
        elif joint_covariance == "robust":
            cov = _wls.score_covariance(s, _blocks, sol, columns, lags=samples.h,
                                        delta_max=delta_max, correction=correction,
                                        row_correction=row_correction, unpenalised=free)
        else:
            raise ValueError(f"{fn}: joint_covariance must be None, 'solver' or 'robust', got "
                             f"{joint_covariance!r}")
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
        shares = _wls.cluster_scores(s, _blocks, sol, a_cols, flat, n_c, delta_max=delta_max,
                                     correction=correction, row_correction=row_correction,
                                     unpenalised=free)  # (B·M, C, 3, d)
        influence = shares.permute(0, 2, 3, 1).reshape(s.batch_shape + (m, 3, d, n_c))
    sol = dataclasses.replace(sol, se=se).unflatten(s.batch_shape, m)
    return dataclasses.replace(_connection_fit(sol, d), cov_b_dA=cov, influence_A=influence)


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
    ``A`` on the cycle (as ``M̂``, README "Is the cost standard error honest?"). Without noise
    correction: the change is for recordings without detected measurement noise, where this
    bias is not small against the noise (the 3-link's ``x`` displacement 1.6 % short, 6× its
    scatter). ``first``: the first-order fit of the same samples and bins, where the caller
    has it (computed here otherwise). ``estimate``: ``(..., M, 3, d)`` the ``Â`` whose bias is
    wanted where it is not that fit's (a delivered ``Â``, which the bins' bias correction and
    the blend have moved from the plain fit): the change is then ``estimate`` minus the
    second-order fit, the variance as above (the moves are functions of the fitted model,
    not of the rows' noise). Measured from the plain fit instead, the clean 5-link's
    allowance counted the bins' bias that :func:`bin_bias_correction` had already removed
    (README "The bias allowance measured from the delivered ``Â``")."""
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


def _resolved(change: Tensor, var: Tensor) -> Tensor:
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

    Without noise the 3-link reference gait's ``x`` displacement is off by ``a + c Δt²``
    (−3.38 / −1.70 / −1.03 / −0.86 ×10⁻³ at 32 / 64 / 128 / 256 samples per cycle, README
    "Is the displacement standard error honest?"): one-sample differences and logarithms of
    a path that curves within the sample. ``full``: the plain fit of ``samples`` in ``bins``
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
    return _blocks(delta, delta_dot, row_scale) + [square, cubic]


def interval_cycles(phase: Tensor, h: int, *, pool: bool = False) -> Tensor:
    """The whole cycle of each interval sample ``(..., T − h)`` (int64) of a recording of
    ``phase (..., T)`` (unwrapped, or wrapped: it is unwrapped here): that of the interval's
    first sample, ``⌊(φ_k − φ_0) / 2π⌋`` (``φ_0`` the element's first finite phase), numbered
    from 0 per batch element, or with ``pool`` through the elements in turn (the trials of a
    pooled fit: ``(N·(T − h),)``, in the order of :func:`~torchconn.trajectory.pool_batch`)."""
    ph = unwrap(phase)
    first = ph.gather(-1, span_bounds(torch.isfinite(ph))[0].unsqueeze(-1))
    cyc = torch.floor((ph[..., :-h] - first) / (2 * math.pi))
    cyc = torch.nan_to_num(cyc, nan=0.0).clamp_min(0).to(torch.int64)
    if not pool:
        return cyc
    cyc = cyc.reshape(-1, cyc.shape[-1])
    count = cyc.amax(-1) + 1
    return (cyc + (torch.cumsum(count, 0) - count)[:, None]).reshape(-1)


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


def _bin_noise(samples: IntervalSamples, s: _wls.BinnedSamples, noise_var: Tensor
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
    var_delta, var_rate = _bin_noise(samples, s, noise_var)

    def correction(gram: Tensor, sel) -> Tensor:
        return eiv_correction(gram, var_delta[sel], var_rate[sel])

    flat = _wls.Solution(*(x.reshape((-1,) + x.shape[len(s.batch_shape) + 1:]) for x in (
        fit.coef, fit.se_coef, fit.n_samples, fit.residual_rms, fit.condition, fit.ridge,
        fit.eiv_scale)))
    gain = _wls.held_gain(s, _blocks, flat, 1 + d, slice(1 + d, 1 + 2 * d),
                          delta_max=delta_max, correction=correction,
                          unpenalised=ridge_exemptions(d, ridge_connection, s.r.device))
    return gain.reshape(s.batch_shape + (s.n_bins, 1 + d, d))


def offsets_at(fit: ConnectionFit, delta_a: Tensor) -> tuple[Tensor, Tensor]:
    """``ĉ (..., M, 3)`` and ``b̂ (..., M, 3, d)`` of ``fit`` re-estimated with each bin's
    ``Â`` moved by ``delta_a (..., M, 3, d)`` and held (``fit.offset_gain``,
    :func:`offset_gain`)."""
    change = fit.offset_gain @ delta_a.mT  # (..., M, 1 + d, 3)
    return fit.c + change[..., 0, :], fit.b + change[..., 1:, :].mT


@dataclass(frozen=True)
class _OneSampleOffsets:
    """The one-sample intervals of a trajectory ``(..., T − 1, ·)`` against its cycle: the
    mid-point phase ``φ_j``, the offset ``r_j − γ(φ_j)`` split into ``along (..., T − 1, 1)``
    (in units of the cycle's tangent ``γ'(φ_j)``) and ``across (..., T − 1, d)``, and the
    one-sample shape velocity ``r_dot``."""

    phase: Tensor
    along: Tensor
    across: Tensor
    r_dot: Tensor


def _one_sample_offsets(traj: Trajectory, gamma_m: Tensor) -> _OneSampleOffsets:
    """:class:`_OneSampleOffsets` of ``traj`` around the cycle through ``gamma_m (..., M, d)``
    (its values at the bin centres; interpolated by its Fourier series of the highest order
    the centres carry). Gaps in ``r`` are bridged by straight lines (:func:`_bridge_gaps`): the
    box filter's rows need only their two ends, so their model target must span missing
    samples too (the triangle's rows need every sample and are unaffected)."""
    cycle = _cycle_series(gamma_m)
    one = interval_samples(traj.pose, _bridge_gaps(traj.r), traj.phase, traj.dt, 1)
    offset = one.r - cycle(one.phase)
    tangent = cycle.derivative()(one.phase)
    along = (tangent * offset).sum(-1, keepdim=True) / tangent.square().sum(-1, keepdim=True)
    return _OneSampleOffsets(phase=one.phase, along=along, across=offset - along * tangent,
                             r_dot=one.r_dot)


def _cycle_series(gamma_m: Tensor) -> FourierSeries:
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


def _model_target(one: _OneSampleOffsets, h: int, kernel: str, a_series,
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


def _harmonic_noise(series, se: Tensor, window: float | Tensor, kernel: str, *,
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
        lag_list, rho = _lag_correlations(window, kernel, device=se.device)
        lags, rho = torch.tensor(lag_list, **opts), rho.unsqueeze(-2)  # (..., 1, L)
    else:
        lags, rho = _window_correlation(window, kernel, se.device)
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


def _resolved_harmonics(series, se: Tensor, bins: BinIndex) -> Tensor:
    """Mask ``(..., 2K+1, 1, …)`` of the harmonics of ``series`` (:func:`_harmonic_noise`)
    that stand out of its noise: the mean always, harmonic ``k`` when its power exceeds
    :data:`_BIAS_HARMONIC_Z` ``· max(1, (k / _BIAS_HARMONIC_SCALE)²)`` times its noise."""
    power, noise = _harmonic_noise(series, se, bins.window, bins.kernel)
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
                        offsets: _OneSampleOffsets | None = None, **opts
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
        offsets: ``traj``'s one-sample offsets from the cycle (:func:`_one_sample_offsets`;
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
    one = _one_sample_offsets(traj, gamma_m) if offsets is None else offsets
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
    power, noise = _harmonic_noise(a_series, fit.se_A, bins.window, bins.kernel)
    gain = (_harmonic_noise(fit_fourier(centres, estimate - observed, order, value_ndim=2),
                            fit.se_A, bins.window, bins.kernel)[0] / power.clamp_min(1e-300)).sqrt()
    weight = torch.where(torch.arange(order + 1, device=power.device) > 0, m / 2, m)
    added = (weight * noise * (2 * gain + gain.square()) * (power > 0)).sum(-1)
    return dataclasses.replace(fit, A=estimate), added


@dataclass(frozen=True)
class _Search:
    """One filter's search of the pooled choice (``NoiseAwareRegression._search``).

    Attributes:
        fit: the chosen candidate's fit; None where no candidate can be fitted, or none beats
            the search's bound.
        view, h, window: its pooled interval samples, interval and bin half-width (with no
            fit: those at the shortest interval tried).
        mse: its estimated MSE, at least its variance (inf with no fit).
        table: ``[h, window, MSE]`` of every candidate that can be fitted, in the order
            tried (those in ``skipped`` with their variance, a lower bound of the MSE).
        skipped: ``[h, window]`` of the candidates whose bias correction was skipped.
    """

    fit: ConnectionFit | None
    view: IntervalSamples
    h: int
    window: float
    mse: float
    table: list
    skipped: list


def _least_score(order: list, lower: dict, score, *, bound: float = math.inf,
                 prune: bool = True) -> tuple:
    """The first candidate in ``order`` of least ``score(key) -> (fit, score)``, scoring as
    few as the lower bounds ``lower[key] <= score`` allow (branch and bound).

    The candidates are scored in increasing bound (ties in ``order``) until the next bound
    exceeds the least score found, or equals it and comes later in ``order``: none of the
    rest can be first of least score. NaN scores count as ``inf``; a candidate must score
    below ``bound`` (on a tie the bound wins). ``prune=False`` scores every candidate, in
    ``order``.

    Returns the chosen key (None where none scores below a finite ``bound``; where every
    score is ``inf``, the first scored) and ``{key: (fit, score)}`` of those scored, in the
    order scored.
    """
    rank = {key: i for i, key in enumerate(order)}
    queue = sorted(order, key=lambda key: lower[key]) if prune else list(order)
    done, best, least = {}, None, (bound, -1)
    for key in queue:
        if prune and (lower[key], rank[key]) > least:
            break
        fit, value = done[key] = score(key)
        if (math.inf if math.isnan(value) else value, rank[key]) < least:
            best, least = key, (value, rank[key])
    if best is None and done and math.isinf(bound):
        best = min(done, key=rank.__getitem__)
    return best, done


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
                 offsets: _OneSampleOffsets, opts: dict):
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
                               offsets: _OneSampleOffsets | None = None,
                               correlation: bool = False, **opts
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
        is the tie's (widened where the sources disagree) with :data:`_RESIDUAL_BIAS_FRACTION`
        times the correction's square added: the bias taken to remain.
    """
    steps = _BIAS_STEPS if steps is None else steps
    one = _one_sample_offsets(traj, gamma_m) if offsets is None else offsets
    tie = dict(order=order, window=bins.window, kernel=bins.kernel, consistency=False)
    first = tied = tie_connection_derivative(fit, gamma_m, gamma_dot_m, **tie)
    bias = _DerivativeBias(fit, samples, bins, gamma_m, gamma_dot_m, order=order, pool=pool,
                           offsets=one, opts=opts)
    for _ in range(steps):
        bias_dA, bias_b = bias(tied)
        corrected = dataclasses.replace(fit, dA=fit.dA - bias_dA, b=fit.b - bias_b)
        tied = tie_connection_derivative(corrected, gamma_m, gamma_dot_m, **tie)
    tied = tie_connection_derivative(corrected, gamma_m, gamma_dot_m,
                                     **{**tie, "consistency": True}, correlation=correlation)
    shift = tied.dA - first.dA
    # the bias left after the correction, taken as the part of its square the pooled choice
    # assumes (_RESIDUAL_BIAS_FRACTION; without it the squared errors were 2-4.8 times the
    # squared standard errors at ω = 0 on seeds 5-6, with it 0.3-1.8)
    se = (tied.se_dA.square() + _RESIDUAL_BIAS_FRACTION * shift.square()).sqrt()
    return dataclasses.replace(fit, dA=tied.dA, se_dA=se, corr_dA=tied.corr_dA), shift


def derivative_bias_allowance(fit: ConnectionFit, traj: Trajectory, samples: IntervalSamples,
                              bins: BinIndex, gamma_m: Tensor, gamma_dot_m: Tensor, *,
                              order: int, pool: bool,
                              offsets: _OneSampleOffsets | None = None,
                              joint_weights: bool = False, correlation: bool = False, **opts
                              ) -> tuple[ConnectionFit, tuple[Tensor, Tensor]]:
    """The tied ``∂Â/∂r`` (:func:`tie_connection_derivative`) with the bins' bias of its
    sources allowed for in their variances instead of removed (for data with measurement
    noise, where :func:`derivative_bias_correction` is not applied).

    Under noise ``b̂`` keeps part of the bins' bias (the chosen filter spans up to a quarter
    cycle and the windows widen): on the 3-link reference gait at ω = 0.005-0.01 its squared
    errors were 3.2-5.2 times its squared standard errors, two thirds of that a bias across
    seeds, while its errors' correlation with the direct estimate's was 0.13-0.31 (Monte
    Carlo over seeds 20-31; README, the tied ``∂Â/∂r``). The bias of ``b̂`` and of the
    direct estimate is computed once from the smooth model (:class:`_DerivativeBias`, about
    the uncorrected tie), and :data:`_RESIDUAL_BIAS_FRACTION` times its square is added to
    their variances before they are tied (the bias taken to remain, as the pooled choice
    assumes for ``Â``): these weigh the sources. The tie's bands take the direct estimate's
    variance with the full square instead (:data:`_DIRECT_BIAS_SHARE`, on the joint
    covariance, which the tie's sandwich uses; the tied ``∂Â/∂r`` itself is unchanged):
    across the same seeds the model's bias of the direct estimate was under-predicted
    (the actual squared bias 1.15 / 0.65 times the modelled one at ω = 0.01 / 0.005 on the
    reference gait, b̂'s 0.62 / 0.49), and only the direct estimate holds the across-cycle
    entries. (With ``joint_weights`` the joint covariance also weighs them; without
    ``fit.cov_b_dA`` the bands are the weights' own.)

    Args: as :func:`derivative_bias_correction` (no ``steps``); ``joint_weights`` as in
        :func:`tie_connection_derivative` (with ``fit.cov_b_dA``, to which the bias's share
        is added too).

    Returns:
        the fit with ``dA`` and ``se_dA`` tied (other fields unchanged, ``b̂``'s standard
        errors included), and the bias ``(dA (..., M, 3, d, d), b (..., M, 3, d))`` allowed
        for.
    """
    one = _one_sample_offsets(traj, gamma_m) if offsets is None else offsets
    tie = dict(order=order, window=bins.window, kernel=bins.kernel, joint_weights=joint_weights)
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
            [_RESIDUAL_BIAS_FRACTION * bias[1].square(),
             _DIRECT_BIAS_SHARE * bias[0].square().flatten(-2)], -1))
    widened = dataclasses.replace(
        fit, se_dA=(fit.se_dA.square() + _RESIDUAL_BIAS_FRACTION * bias[0].square()).sqrt(),
        se_b=(fit.se_b.square() + _RESIDUAL_BIAS_FRACTION * bias[1].square()).sqrt(),
        cov_b_dA=cov)
    tied = tie_connection_derivative(widened, gamma_m, gamma_dot_m, **tie,
                                     correlation=correlation)
    return dataclasses.replace(fit, dA=tied.dA, se_dA=tied.se_dA, corr_dA=tied.corr_dA), bias


# ------------------------------------------------------------------------ the regression stage
#: the velocity interval is the shortest at which the joint-angle noise adds at most this
#: fraction of the process noise's variance to a filtered shape velocity
#: (:func:`velocity_interval_for`); the pooled fit then chooses between it and longer ones
_INTERVAL_NOISE_FRACTION = 0.05
#: longest velocity interval, as a fraction of a cycle. The triangle filter's error grows
#: more slowly with the interval than the box's; seed 5 (pooled, ω = 0.01) chose 24-32 of 126
#: samples per cycle
_MAX_INTERVAL_CYCLES = 1 / 4
#: where no bin width can be fitted at an interval (the pooled reference, or an unpooled
#: element's own), the interval is divided by this (:func:`_shorter_interval`) until one can
_FALLBACK_INTERVAL_DIVISOR = 1.5
#: the pooled fit's candidate bin half-widths (bin spacings)
_CANDIDATE_WINDOWS = (1.0, 2.0, 3.0, 4.0)
#: every pair of these multiples of ``h0`` and the windows above is a candidate, scored ``V +
#: V⁺ + λ‖B‖²`` with ``λ = _RESIDUAL_BIAS_FRACTION`` (``V⁺`` added later, on seeds 5-8; see
#: ``_chosen_fit``). Set on seeds 5 and 6 (3-/5-link circle, 3-link reference, 5-link smaller
#: circle, ω = 0.002; intervals 2-24 and windows 1-4): λ = 0.5 and 1 chose fits whose mean Â
#: error was 2.30 and 2.33 % (the best of the grid: 2.23 %), λ = 0.1-0.25 2.90-2.94 % (wide
#: windows on the curved gait), λ = 2 2.55 %, λ = 0 (variance alone) 4.08 %; the correction
#: made longer intervals pay on the 5-link (h = 16-24 at ω = 0.002)
_CORRECTED_INTERVAL_MULTIPLES = (1.5, 2.0, 3.0, 4.0, 6.0)
_RESIDUAL_BIAS_FRACTION = 0.5
#: the share of the direct ``∂Â/∂r``'s squared modelled bias (:class:`_DerivativeBias`) that
#: the tie's bands take as remaining (:func:`derivative_bias_allowance`; its weights take
#: ``_RESIDUAL_BIAS_FRACTION``). A Monte Carlo over seeds 20-31 (3-link reference gait,
#: pooled 4 x 30) put the actual squared bias of the direct estimate (its mean error over the
#: seeds against the exact Jacobian) at 1.15 / 0.65 times the modelled one at ω = 0.01 /
#: 0.005 (b̂'s at 0.62 / 0.49, so half stays for b̂); no other value was tried
_DIRECT_BIAS_SHARE = 1.0
#: unpooled elements (no choice yet) widen their bins with the noise: by this many bin spacings
#: per unit of the noise ratio (see noise_ratio), up to _MAX_NOISE_WINDOW spacings
_WINDOW_PER_NOISE_RATIO = 20.0
_MAX_NOISE_WINDOW = 3.0
#: :func:`blend_fits` keeps the corrected estimate only where it differs from the smoothed one
#: by more than this many times its own variance. Re-set on seed 5 after the standard errors
#: were calibrated for the rows' overlap (:func:`overlap_inflation`), one model per trial
#: (3 trials x 30 cycles, 64 samples per cycle, 3-/5-/9-link circle and reference gaits,
#: ω = 0.002-0.01, 18 cells; mean Â error): 1.5 was never worse than the smoothed estimate and
#: better than 2 in 11 cells (3-link circle ω = 0.01: 24.0 % against 28.4 %, the smoothed 37.7
#: %), equal in the rest; 1 (the plain Stein rule) was better still in 14 cells but worse than
#: the smoothed estimate in one (9-link reference ω = 0.005: 34.2 % against 33.3 %)
_BLEND_VARIANCE_FACTOR = 1.5


#: the bias correction's model (:func:`bin_bias_correction`): the Fourier order of its
#: ``Â`` and ``∂Â/∂r`` and the fixed-point steps. Set on seed 5 (3-link reference gait,
#: pooled 4 x 30 cycles, ω = 0 and 0.002, intervals 1-24, windows 1-4): order 12 (the fit's
#: own) diverged at ω = 0.002 (its phase derivative amplifies the noisy high harmonics),
#: 4 and 6 converged (ω = 0.002, h = 8, window 2: 3.63 -> 2.80 % with 6); a second step
#: gains most of what the fixed point gains (ω = 0: 2.92 -> 1.51 -> 0.98 % ... 0.72 % at
#: four) and more steps diverge where the bias is large (windows of 4 spacings)
_BIAS_ORDER = 6
_BIAS_STEPS = 2
#: a harmonic of ``Â`` enters the bias correction's model when its coefficients' squares
#: exceed this many times their noise expectation (:func:`_resolved_harmonics`): correcting a
#: harmonic the data do not resolve amplifies its noise (the bins damp it, the correction
#: undoes the damping) and removes next to no bias
_BIAS_HARMONIC_Z = 4.0
#: ... and harmonics above this one need (k / _BIAS_HARMONIC_SCALE)² times more: the model
#: enters the correction through its phase derivative (harmonic k weighted by k), and a noisy
#: high harmonic, amplified so, spoils the correction of the low ones. Seeds 5-8, 3-link
#: reference gait, pooled: with the same threshold for all harmonics the correction made
#: ω = 0.005 worse than none (7.16 % against 6.72 %, mean; ω = 0.002: 2.76 % against 4.03 %);
#: with this scale 2 it gave 5.37 % at ω = 0.005 and 3.18 % at ω = 0.002 (3: 5.0 % at 0.002);
#: ω = 0.01 10.1 % either way (none: 11.8 %)
_BIAS_HARMONIC_SCALE = 2.0
#: a pooled fit's series of ``Â`` shrinks harmonic ``k`` by ``max(0, 1 − c · noise_k /
#: power_k)`` with this ``c`` (``NoiseAwareRegression._a_series``; ``noise_k`` the bins'
#: noise expectation, :func:`_harmonic_noise`). Under noise the bins' errors are mostly
#: variance, and a harmonic near its noise adds more of it than of the connection; ``c = 1`` is
#: the estimated Wiener factor. Set on seeds 5-8 (3-/5-link circle and 0.7-circle or reference
#: gaits, pooled 4 x 30 cycles, ω = 0-0.01, 64 cells; sum of the mean Â errors, all harmonics
#: 72.2 %): c = 1 59.4 % and c = 0.5 62.3 % (worse than all harmonics in 3 / 2 cells, by at most
#: 0.006 points), keeping the harmonics above 1 / 1.5 / 2 times their noise 67.7 / 62.9 / 60.0 %.
#: It gains most on short recordings, and the convergence slope of ``Â``'s error with cycles
#: (3-link circle, ω = 0.002, seeds 0-1, 10 / 30 / 90 cycles; issue 12 asks ≤ −0.35) was −0.43
#: with all harmonics, −0.34 with c = 1, −0.32 keeping those above 2, −0.37 with c = 0.5.
#: The factor was one per harmonic (power and noise summed over all entries) until the pooled
#: 9-link's displacement over a cycle was found 1.5-2.6x further off with it than with the
#: plain series; it is now one per harmonic and row of ``Â`` (same c, not re-tuned; README)
_SERIES_SHRINK = 0.5


@dataclass(frozen=True)
class _Chosen:
    """What the tie of ``∂Â/∂r`` needs of the corrected fit: the bins' half-width (a number,
    or ``(...)`` per unpooled element) and, for a pooled fit, the chosen candidate's interval
    samples, the one-sample offsets its bias correction modelled (None without it), whether
    no measurement noise was detected and the joints' measurement-noise variance ``(d,)`` (pooled) it
    was corrected for (to run its regression again for the joint covariance of ``b̂`` and
    ``∂Â/∂r``, and for ``Â``'s sampling factor, :meth:`NoiseAwareRegression._rerun_chosen`)."""

    windows: float | Tensor
    view: IntervalSamples | None = None
    offsets: _OneSampleOffsets | None = None
    noise_free: bool = False
    noise_var: Tensor | None = None


@dataclass(frozen=True, kw_only=True)
class NoiseAwareRegression(TubeRegression):
    """:class:`~torchconn.regression.tube.TubeRegression` with the connection regressed on raw
    interval differences and corrected for the joint angles' measurement noise.

    Body and shape velocities are differences of the recorded poses and joint angles filtered
    alike over ``velocity_interval`` samples (:func:`interval_samples`), so target and
    regressors see the same operation and nothing else is smoothed; each joint's noise is
    estimated from the spectrum of its increments (:func:`estimate_noise`) and removed from
    every bin's normal equations
    (:func:`eiv_correction`). The smoothed state serves the phase and the limit cycle, and
    :class:`TubeRegression`'s smoothed regression is the fallback: where the data cannot tell
    the corrected estimate from the smoothed one (little data, many joints, much noise: the
    correction then removes most of the normal matrix and mostly adds variance), the result
    is shrunk towards the smoothed estimate (:func:`blend_fits`; the weights of the corrected
    estimate are ``model.meta["corrected_weight"]``). The metric is fitted as by
    :class:`TubeRegression`. It is :class:`~torchconn.regression.ConnectionEstimator`'s
    default regression (settings table ``method = "noise_aware"``). Unpooled, a trial's
    noise estimate, interval and windows do not depend on the other trials of the batch, and
    its coefficients only through the solver's rounding, as :class:`TubeRegression`'s (bit for
    bit on the 3-link; to 1e-13 on the 9-link, where MKL's kernels round with the memory
    alignment of the bins' matrices unless ``MKL_CBWR=AUTO`` is set).

    Attributes (besides :class:`TubeRegression`'s):
        velocity_interval: samples the velocity filter spans; None chooses it from the noise
            (:func:`velocity_interval_for`), and a pooled fit then also tries longer ones.
            With ``window=None`` a pooled fit chooses the bins' width too, by the estimated
            error of ``Â`` (``meta["interval_window_scores"]``); unpooled elements widen it
            with the noise. Where the bins cannot all be fitted at the chosen interval, a
            shorter one is taken (``meta["velocity_interval"]`` is the one used); a pooled fit
            on data with missing samples also tries the box filter
            (``meta["velocity_kernel"]``).
        noise_band_low: lowest frequency (cycles per sample) of the noise fit; None: chosen
            per batch element and joint from the data (:func:`estimate_noise`).
        noise_floor: the noise fit's process floor: ``"flat"`` (default), or ``"low_rate"``:
            the fitted cycle's harmonics spread by phase noise (:func:`phase_noise_floor`)
            where``"low_rate"``: ``"gait"`` where the gait's harmonics reach
            the noise fit's top band (32 or fewer samples per cycle; their phase-noise tails
            fill it and drive the flat floor's ``σ̂²`` below 0), ``"flat"`` elsewhere, bit for
            bit (README "Few samples per cycle"). ``"normal"``: the joint increments projected
            out of the fitted cycle's first derivatives at each sample's phase
            (:func:`normal_increments`), which takes out the phase noise and the phase
            estimate's errors, fitted over ``[0.1, 0.5]`` cycles per sample with a flat floor;
            with two joints (the 3-link) ``"flat"`` bit for bit. Held out at 64 samples per
            cycle, ω = 0.002 (seeds 100-119): the 9-link reference gait's ``ω̂`` within 20 % in
            20 of 20 pooled recordings (flat: 11), and clean recordings called noisy 3 of 320
            against 12 (5-/9-link, seeds 60-79; README "Noise estimates"). Either way the test
            for noise of the joints' mean takes their shared phase noise into account
            (:attr:`NoiseEstimate.correlation`, from the fitted cycle).

    The corrected fit is always shrunk towards the smoothed one (:func:`blend_fits`), a
    pooled fit's ``Â`` corrected for the bins' bias (:func:`bin_bias_correction`), ``∂Â/∂r``
    tied (:func:`~torchconn.regression.tie_connection_derivative`; a pooled fit's corrected
    for, or under noise allowing for, the bins' bias, with ``b̂`` and the direct estimate's
    joint covariance in the bands), a pooled fit's series of ``Â`` shrunk harmonic by
    harmonic with ``ĉ, b̂`` re-estimated to it, and a pooled fit keeps ``Â``'s sampling factor
    and, without detected noise, its bias allowance (docs/validation/deleted-options.md lists
    the variants these replaced and what was measured).
    """

    velocity_interval: int | None = option(None, ge=1)
    noise_band_low: float | None = option(None, gt=0, le=0.45)
    noise_floor: Literal["flat", "low_rate", "normal"] = "flat"
    #: test hook: correct every candidate of the pooled choice instead of branch and bound
    #: (the same choice and fit bit for bit; ``meta["interval_window_scores"]`` then holds
    #: every candidate's MSE)
    _full_search: ClassVar[bool] = False

    def _corrected_fit(self, traj, pool, samples, gamma_m, gamma_dot_m, opts, bins_for):
        """Unpooled batch elements may carry different noise (a sweep's noise levels), so each
        gets its own interval and window; elements sharing both are regressed together (one
        call per distinct pair, not per trial)."""
        d, n_bins = traj.shape_dim, self.n_bins
        var, ratio, h = self.noise_setup(traj, pool, gamma_m)
        if pool:
            fit, view, window, scores, skipped, offsets = self._chosen_fit(
                traj, var, ratio, int(h), gamma_m, gamma_dot_m, opts)
            meta = {"velocity_interval": view.h, "velocity_kernel": view.kernel,
                    "noise_ratio": float(ratio), "noise_r": var.sqrt().tolist(),
                    "interval_window_scores": scores, "interval_window_bounds": skipped}
            return fit, window, meta, _Chosen(window, view, offsets,
                                              noise_free=not bool((var > 0).any()),
                                              noise_var=var)
        # b̂ and ∂Â/∂r's joint covariance, for the tie: only for groups with detected noise
        # (elsewhere the tie takes the two as independent, and _scatter_fits leaves it NaN)
        joint = {"joint_covariance": "solver"}
        batch = tuple(traj.batch_shape)
        n, m = math.prod(batch), n_bins
        flat = _flatten_batch(traj)
        h_flat, ratio_flat = h.reshape(-1), ratio.reshape(-1)
        windows = self.element_windows(flat.phase, d, ratio_flat)
        groups, inverse = torch.unique(torch.stack([h_flat.to(windows), windows], -1), dim=0,
                                       return_inverse=True)
        g_m = gamma_m.expand(batch + (m, d)).reshape(n, m, d)
        g_dot = gamma_dot_m.expand(batch + (m, d)).reshape(n, m, d)
        var_flat = var.reshape(n, d)
        by_h = _intervals_by_h(flat, h_flat, traj.dt)
        parts, h_flat = [], h_flat.clone()
        pending = torch.ones(n, dtype=torch.bool, device=h_flat.device)
        while bool(pending.any()):
            # an element whose bins cannot all be fitted at its chosen interval (too few
            # independent rows for the overlapping filter) tries a shorter one
            # (_shorter_interval); at h = 1, or a given velocity_interval, on_ill_conditioned
            # applies
            keys = torch.stack([h_flat.to(windows), windows], -1)
            groups, inverse = torch.unique(keys[pending], dim=0, return_inverse=True)
            todo = torch.nonzero(pending).flatten()
            for g, (hg, wg) in enumerate(groups.tolist()):
                hg = int(hg)
                idx = todo[inverse == g]
                if hg not in by_h:
                    shorter = torch.tensor([hg], device=h_flat.device)
                    by_h.update(_intervals_by_h(flat, shorter, traj.dt))
                iv = _take_intervals(by_h[hg], idx)
                bins = assign_bins(iv.phase, n_bins, window=wg, kernel=self.kernel)
                args = (iv, bins, g_m[idx], g_dot[idx], var_flat[idx])
                group_opts = {**opts, **joint} if bool((var_flat[idx] > 0).any()) else opts
                if hg == 1 or self.velocity_interval:  # nothing shorter to try
                    fit = noise_aware_regression(*args, **group_opts)
                    parts.append((idx, self._with_offset_gain(fit, args, opts, pool)))
                    pending[idx] = False
                    continue
                fit, bad = _flagged_fit(args, group_opts)
                fit = self._with_offset_gain(fit, args, opts, pool)
                parts.append((idx[~bad], _take_fit(fit, ~bad)))
                pending[idx[~bad]] = False
                h_flat[idx[bad]] = _shorter_interval(hg)
        h = h_flat.reshape(batch)
        meta = {"velocity_interval": h.tolist(), "velocity_kernel": VELOCITY_KERNEL,
                "noise_ratio": ratio.tolist(), "noise_r": var.sqrt().tolist(),
                "windows": windows.reshape(batch).tolist()}
        fit = _scatter_fits(parts, n, batch)
        if fit.cov_b_dA is not None:  # only under detected noise (NaN: the tie takes the
            # two as independent where none was, as in a clean element of a noisy group)
            clean = ~(var > 0).any(-1).reshape(batch + (1, 1, 1, 1))
            fit = dataclasses.replace(fit, cov_b_dA=fit.cov_b_dA.masked_fill(clean, torch.nan))
        return fit, float(windows.max()), meta, _Chosen(windows.reshape(batch))

    def _chosen_fit(self, traj: Trajectory, var: Tensor, ratio: Tensor, h0: int,
                    gamma_m: Tensor, gamma_dot_m: Tensor, opts: dict):
        """The pooled corrected fit at the velocity interval, bin width and filter of least
        estimated mean squared error of ``Â``.

        Longer intervals and wider bins lower the variance and add bias (they average ``A``
        over more of the cycle). Every candidate's bias (:func:`bin_bias_correction`) is
        estimated and removed, and ``MSE_c ≈ V_c + V⁺_c + λ‖B_c‖²``: ``V`` the summed squared
        standard errors of ``Â`` (calibrated for the rows' overlap by
        :func:`overlap_inflation`), ``V⁺`` the variance the correction adds, ``B_c`` the
        correction applied and ``λ =`` :data:`_RESIDUAL_BIAS_FRACTION` the part of its square
        taken to remain (on the 3-link reference gait without noise the correction removed 2/3
        of the bias). The candidates are every pair of the half-widths
        :data:`_CANDIDATE_WINDOWS` (at least the data-size rule's) and the intervals ``h0``
        and ``h0 · _CORRECTED_INTERVAL_MULTIPLES`` (``h0`` the noise rule's,
        :func:`velocity_interval_for`; at most a quarter cycle); the first of least ``MSE`` in
        that order is taken. ``V_c`` comes from the uncorrected fit and ``V⁺``, ``‖B‖²`` are
        ``≥ 0``, so ``V_c`` bounds ``MSE_c`` from below: the candidates are corrected in
        increasing ``V`` until the next ``V`` exceeds the least ``MSE`` found (or equals it
        and comes later in the order), and the rest cannot be chosen (branch and bound; the
        same choice and fit as correcting all, bit for bit).

        ``window`` or ``velocity_interval``, when given, fix theirs. Where no width can be
        fitted at ``h0``, shorter intervals (:func:`_shorter_interval`) are tried first.

        The triangle filter needs all ``h + 1`` samples of an interval, the box only its two
        ends: where missing samples cost the triangle rows the box keeps, the box's search
        (from its own noise rule's interval) runs too and the lower estimated MSE of the two
        is taken (each at least its candidate's variance; on a tie the triangle). The box's
        candidates are then corrected only while their ``V`` is below the triangle's MSE.
        Complete data (no NaN in the poses, shapes or phase) lose no rows to either filter,
        and the rows are not counted.

        Returns the fit, its interval samples (pooled; ``.h`` and ``.kernel`` the chosen
        interval and filter), the window, the candidates' ``[h, window, MSE]`` (a list;
        ``[h, window, MSE, "box"]`` for the box's), the ``[h, window(, "box")]`` of the
        candidates whose correction was skipped (their table entry is ``V``, a lower bound of
        their MSE, and at least the chosen one's) and the one-sample offsets the bias
        correction models.
        """
        kernels = {VELOCITY_KERNEL: int(self.velocity_interval or h0)}
        if VELOCITY_KERNEL != "box" and _has_missing(traj):
            h_box = int(self.velocity_interval or velocity_interval_for(
                ratio, _samples_per_cycle(traj), "box"))
            if _usable_rows(traj, kernels[VELOCITY_KERNEL], VELOCITY_KERNEL) < _usable_rows(
                    traj, kernels[VELOCITY_KERNEL], "box"):
                kernels["box"] = h_box
        offsets = _one_sample_offsets(traj, gamma_m)
        found, bound = {}, math.inf
        for k, h in kernels.items():
            # a later filter is taken only where its MSE is below the earlier ones'
            found[k] = self._search(traj, var, k, h, gamma_m, gamma_dot_m, opts, offsets, bound)
            if found[k].fit is not None:
                bound = min(bound, found[k].mse)
        fitted = {k: f for k, f in found.items() if f.fit is not None}
        if not fitted:  # none can be fitted: on_ill_conditioned decides (e.g. raises)
            f = found[VELOCITY_KERNEL]
            fit = noise_aware_regression(f.view, self._bins(f.view, f.window), gamma_m,
                                         gamma_dot_m, var, **opts)
            return fit, f.view, f.window, [], [], offsets
        kernel = min(fitted, key=lambda k: fitted[k].mse)
        best = fitted[kernel]

        def tagged(rows: list, k: str) -> list:
            return [row + ([] if k == VELOCITY_KERNEL else [k]) for row in rows]

        table = [row for k, f in found.items() for row in tagged(f.table, k)]
        skipped = [row for k, f in found.items() for row in tagged(f.skipped, k)]
        return best.fit, best.view, best.window, table, skipped, offsets

    def _search(self, traj: Trajectory, var: Tensor, kernel: str, h0: int, gamma_m: Tensor,
                gamma_dot_m: Tensor, opts: dict, offsets: _OneSampleOffsets,
                bound: float = math.inf) -> _Search:
        """:meth:`_chosen_fit`'s search for one filter (:class:`_Search`). ``offsets``: the
        one-sample offsets the bias correction models (:func:`_one_sample_offsets`).
        ``bound``: an MSE to beat (another filter's; a candidate whose ``V`` is not below it
        is not corrected, and none beating it gives no fit)."""
        d = traj.shape_dim
        longest = max(2, int(_samples_per_cycle(traj) * _MAX_INTERVAL_CYCLES))
        # per candidate (h, window), in the order tried: the variance V of the uncorrected
        # fit (inf: it cannot be fitted) and the score (once corrected)
        views, fits, variances, scores = {}, {}, {}, {}

        def candidate(h: int, w: float | None) -> tuple[int, float]:
            if h not in views:
                views[h] = pooled_view(traj, h, kernel)
            if w is None:  # the narrowest the data allow
                w = _auto_window(views[h].phase, self.n_bins, 1 + 2 * d + d * d,
                                 self.samples_per_regressor)
            key = (h, float(w))
            if key in variances:
                return key
            fit, bad = _flagged_fit((views[h], self._bins(views[h], key[1]), gamma_m,
                                     gamma_dot_m, var), opts)
            if bool(bad):  # bins too sparse at this width: not a candidate
                variances[key] = scores[key] = math.inf
                return key
            variances[key] = float(fit.se_A.square().nansum())
            fits[key] = fit
            return key

        while True:
            least = candidate(h0, self.window)[1]  # the narrowest window
            widths = [least] if self.window else [max(least, w) for w in _CANDIDATE_WINDOWS]
            first = [candidate(h0, w) for w in widths]
            if any(k in fits for k in first) or h0 == 1 or self.velocity_interval:
                break
            # no width can be fitted at this interval (too few independent rows for the
            # overlapping filter, or rows lost to missing samples)
            h0 = _shorter_interval(h0)
        if not any(k in fits for k in first):
            return _Search(None, views[h0], h0, least, math.inf, [], [])
        intervals = [] if self.velocity_interval else sorted(
            {min(longest, max(1, round(h0 * f)), traj.n_samples - 1)
             for f in _CORRECTED_INTERVAL_MULTIPLES} - {h0})

        def corrected(key: tuple[int, float]) -> tuple[ConnectionFit, float]:
            view = views[key[0]]
            fit, added = bin_bias_correction(
                fits[key], traj, view, self._bins(view, key[1]), gamma_m, gamma_dot_m,
                pool=True, offsets=offsets, **opts)
            bias = float((fit.A - fits[key].A).square().nansum())
            return fit, variances[key] + float(added) + _RESIDUAL_BIAS_FRACTION * bias

        # every pair of interval and width
        order = list(dict.fromkeys(first + [candidate(h, w) for h in intervals
                                            for w in widths]))
        best, done = _least_score([k for k in order if k in fits], variances, corrected,
                                  bound=bound, prune=not self._full_search)
        scores.update({k: score for k, (_, score) in done.items()})
        fit = None if best is None else done[best][0]
        # a candidate not corrected (branch and bound) enters the table with its V
        table = [[h, w, scores.get((h, w), v)] for (h, w), v in variances.items()
                 if math.isfinite(scores.get((h, w), v))]
        skipped = [[h, w] for (h, w) in fits if (h, w) not in scores]
        if best is None:  # no candidate beats the bound
            return _Search(None, views[h0], h0, least, math.inf, table, skipped)
        # against another filter's search (another reference) the estimate is taken at least
        # at the candidate's own variance: a squared bias below 0 is the reference's noise
        mse = max(scores[best], variances[best])
        return _Search(fit, views[best[0]], best[0], best[1], mse, table, skipped)

    def _bins(self, view: IntervalSamples, window: float) -> BinIndex:
        """The bins of pooled interval samples ``view`` at half-width ``window``."""
        return assign_bins(view.phase, self.n_bins, window=window, kernel=self.kernel)

    def _connection_fit(self, traj, pool, samples, gamma_m, gamma_dot_m, opts, bins_for):
        """The corrected fit, shrunk towards the smoothed one (:func:`blend_fits`), with
        ``∂Â/∂r`` tied (:meth:`_tied`) and, pooled, ``Â``'s sampling factor
        (``sampling_factor_A``) and, without detected noise, its bias allowance
        (``bias_allowance_A``)."""
        fit, window, meta, chosen = self._corrected_fit(traj, pool, samples, gamma_m,
                                                        gamma_dot_m, opts, bins_for)
        # (unpooled elements got their joint covariance with their fits)
        joint = chosen.view is not None and not chosen.noise_free
        rerun = None
        if chosen.view is not None:
            fit, rerun = self._rerun_chosen(fit, traj, chosen, gamma_m, gamma_dot_m, opts,
                                            joint)
        if pool:  # (unpooled elements got theirs with their fits)
            fit = self._with_offset_gain(fit, (
                chosen.view, self._bins(chosen.view, chosen.windows), gamma_m, gamma_dot_m,
                chosen.noise_var), opts, pool)
        tube, _, _ = self._smoothed_fit(samples, gamma_m, gamma_dot_m, opts, bins_for)
        fit, weights = blend_fits(tube, fit)
        meta["corrected_weight"] = weights.tolist()
        # the direct estimate stays the coefficient the model predicts with (dA_fit)
        tied, meta["derivative"] = self._tied(fit, traj, chosen, gamma_m, gamma_dot_m, opts)
        fit = dataclasses.replace(tied, dA_direct=fit.dA, cov_b_dA=None)
        if rerun is not None and rerun.influence_A is not None:
            # scaled to the standard errors of the Â delivered
            fit = dataclasses.replace(fit, sampling_factor_A=sampling_factor(
                rerun.influence_A, fit.se_A))
        if chosen.view is not None and chosen.noise_free:
            bins = self._bins(chosen.view, chosen.windows)
            # without noise the rerun is the plain first-order fit both parts start from,
            # standard errors too where the rows' overlap does not inflate them (κ = 1)
            plain = rerun if chosen.view.h == 1 or chosen.view.kernel == "box" else None
            # the bias of the Â delivered: the bins' bias correction and the blend have moved
            # it from the plain fit (by -1.1e-4 of the clean 5-link's x displacement, the
            # part of the second order's change it had already removed)
            tube, tube_var = offset_bias(chosen.view, bins, gamma_m, gamma_dot_m, first=plain,
                                         estimate=fit.A, **opts)
            step, step_var = interval_bias(traj, chosen.view, bins, self.n_bins, chosen.windows,
                                           self.kernel, gamma_m, gamma_dot_m, full=plain,
                                           **opts)
            # one allowance: on the looked-at sets (1000, 3000, 42000, 7000) its effect on
            # the x displacement is 0.88-0.99 of the 3-link's error and 0.23-1.16 of the
            # 5-link's (measured from the plain fit: 0.82-0.91 and 0.92-2.09)
            fit = dataclasses.replace(fit, bias_allowance_A=_resolved(
                torch.nan_to_num(tube) + torch.nan_to_num(step),
                torch.nan_to_num(tube_var) + torch.nan_to_num(step_var)))
        return fit, window, meta

    def _with_offset_gain(self, fit: ConnectionFit, args: tuple, opts: dict, pool: bool
                          ) -> ConnectionFit:
        """``fit`` (:func:`noise_aware_regression` of ``args``: samples, bins, cycle, noise)
        with its :func:`offset_gain` where ``ĉ, b̂`` will be re-estimated to a shrunk ``Â``
        (pooled)."""
        if not pool:
            return fit
        gain = offset_gain(fit, *args, delta_max=opts["delta_max"],
                           ridge_connection=opts["ridge_connection"])
        return dataclasses.replace(fit, offset_gain=gain)

    def _rerun_chosen(self, fit: ConnectionFit, traj: Trajectory, chosen: _Chosen,
                      gamma_m: Tensor, gamma_dot_m: Tensor, opts: dict, joint: bool
                      ) -> tuple[ConnectionFit, ConnectionFit]:
        """The chosen candidate's regression (a pooled corrected fit) run again for what the
        search did not compute (:func:`noise_aware_regression`): with ``joint``, ``fit`` gets
        ``cov_b_dA``, scaled from that regression's standard errors to ``fit``'s (which the
        bias correction of ``Â`` leaves as they are). Returns it and that regression, with
        ``sampling_factor`` holding each whole cycle's share of the error of ``Â``
        (``influence_A``, ``(M, 3, d, C)``)."""
        bins = self._bins(chosen.view, chosen.windows)
        cycles = interval_cycles(traj.phase, chosen.view.h, pool=True)
        raw = noise_aware_regression(
            chosen.view, bins, gamma_m, gamma_dot_m, chosen.noise_var,
            joint_covariance="solver" if joint else None, cycles=cycles, **opts)
        if joint:
            fit = dataclasses.replace(fit, cov_b_dA=_rescaled_covariance(
                raw.cov_b_dA, (raw.se_b, raw.se_dA), (fit.se_b, fit.se_dA)))
        return fit, raw

    def _tied(self, fit: ConnectionFit, traj: Trajectory, chosen: _Chosen, gamma_m: Tensor,
              gamma_dot_m: Tensor, opts: dict) -> tuple[ConnectionFit, str]:
        """``fit`` with ``∂Â/∂r`` tied (:func:`tie_connection_derivative`, each element at its
        own window) and, for a pooled bias-corrected fit of data without detected measurement
        noise, corrected for the bins' bias (:func:`derivative_bias_correction`). Returns the
        fit and how (for ``meta["derivative"]``).

        Not under noise: the correction's regression of the model's body velocity runs on
        the recorded samples without the errors-in-variables fix (the model target carries
        the regressors' own noise, unlike the recorded target), so its ``∂Â/∂r`` is
        attenuated and the correction carries that into the estimate. Measured on seeds 5-6
        (3-/5-link circle and reference gaits, pooled, ω = 0.002-0.01) it was worse than the
        tie alone in 19 of 24 cells (5-link circle ω = 0.01, seed 5: 781 % against 619 %),
        while at ω = 0 it takes the 3-link reference gait from 15 % (tie alone) to 5 %.
        Under noise the same bias is instead allowed for in the tie's weights and bands
        (:func:`derivative_bias_allowance`)."""
        if chosen.view is not None:
            bins = assign_bins(chosen.view.phase, self.n_bins, window=chosen.windows,
                               kernel=self.kernel)
            if chosen.noise_free:
                run, how = derivative_bias_correction, "tied, bias-corrected"
            else:
                run, how = derivative_bias_allowance, "tied, bias allowed for"
            tied, _ = run(fit, traj, chosen.view, bins, gamma_m, gamma_dot_m,
                          order=self.fourier_order, pool=True, offsets=chosen.offsets, **opts)
            return tied, how
        tied = tie_connection_derivative(fit, gamma_m, gamma_dot_m, self.fourier_order,
                                         window=chosen.windows, kernel=self.kernel)
        return tied, "tied"

    def _a_series(self, centres: Tensor, fit: ConnectionFit, window, pool: bool):
        """``Â``'s series, each harmonic of each row shrunk by how far it stands out of the
        bins' noise when pooled, the fit with ``ĉ, b̂`` re-estimated in each bin with ``Â``
        held at the shrunk series (moved by the shrink's change at the bin's centre,
        :func:`offsets_at`), and the meta entries that record it."""
        series, fit, meta = super()._a_series(centres, fit, window, pool)
        if not pool:
            return series, fit, meta
        # each row (x, y, θ) by its own power: one factor for the whole harmonic would shrink
        # the rows where it stands far out of its noise (the fundamental that carries the
        # gait's displacement) as much as those where it is noise (README)
        power, noise = _harmonic_noise(series, fit.se_A, window, self.kernel,
                                       rows=True)  # (..., 3, K + 1)
        factor = (1 - _SERIES_SHRINK * noise / power.clamp_min(1e-300)).clamp(0, 1)
        factor[..., 0] = 1  # the mean
        factor = factor.transpose(-1, -2)  # (..., K + 1, 3)
        coeff_factor = torch.cat([factor[..., :1, :],
                                  factor[..., 1:, :].repeat_interleave(2, -2)], -2)
        shrunk = dataclasses.replace(series, coeffs=series.coeffs * coeff_factor.unsqueeze(-1))
        meta = {"A_harmonic_factors": (torch.round(factor * 1e4) / 1e4).tolist()}  # (..., K + 1, 3)
        if fit.offset_gain is not None:  # (_with_offset_gain)
            c, b = offsets_at(fit, shrunk(centres) - series(centres))  # (..., M, 3, d)
            fit = dataclasses.replace(fit, c=c, b=b)
            meta["offsets_refit"] = True
        return shrunk, fit, meta

    def _window(self, phase: Tensor, d: int, ratio: float) -> float:
        """Bin half-width: the data-size rule, widened with the noise."""
        return max(_auto_window(phase, self.n_bins, 1 + 2 * d + d * d,
                                self.samples_per_regressor),
                   min(1 + _WINDOW_PER_NOISE_RATIO * ratio, _MAX_NOISE_WINDOW))

    def element_windows(self, phase: Tensor, d: int, ratio: Tensor) -> Tensor:
        """Bin half-widths ``(n,)`` of unpooled elements ``phase (n, N)`` with noise ratios
        ``ratio (n,)``: ``window``, or each element's :meth:`_window` (from its own samples
        and noise only), rounded to half bin spacings so that few distinct windows (groups of
        elements regressed together) remain."""
        if self.window:
            widths = torch.full(phase.shape[:1], float(self.window), dtype=torch.float64,
                                device=phase.device)
        else:
            size = _auto_windows(phase, self.n_bins, 1 + 2 * d + d * d,
                                 self.samples_per_regressor)
            noise = (1 + _WINDOW_PER_NOISE_RATIO * ratio.to(size)).clamp_max(_MAX_NOISE_WINDOW)
            widths = torch.maximum(size, noise)
        return torch.round(widths * 2) / 2

    def noise_setup(self, traj: Trajectory, pool: bool, gamma_m: Tensor | None = None):
        """Joint-angle noise variance ``(..., d)``, noise ratio and velocity interval ``(...)``
        (``(d,)`` and scalars when ``pool``: the trials share one rig).

        ``gamma_m``: the limit cycle at the bin centres, ``(..., M, d)`` (``(M, d)`` when
        ``pool``); with ``noise_floor="gait"`` the noise fit's process floor follows the
        gait's harmonics (:func:`phase_noise_floor`); with either floor it correlates the
        joints' estimates (their shared phase noise, :attr:`NoiseEstimate.correlation`) in
        the test of their mean for noise. None: a flat floor, joints taken as independent.

        Unpooled, each batch element's are its own: its samples per cycle (which set the
        longest interval and place the gait's harmonics) come from its own phase rate and its
        noise band from its own data (:func:`estimate_noise`), so a trial's fit does not depend
        on the trials it shares a batch with (a sweep's cells)."""
        per_trial = 2 * math.pi / (phase_rate(traj.phase, traj.dt) * traj.dt)  # (...)
        per_cycle = per_trial.nanmean() if pool else per_trial
        band = None if self.noise_band_low is None else (self.noise_band_low, 0.5)
        cycle = _cycle_series(gamma_m) if gamma_m is not None else None
        # (..., d), each element on its own; the cycle also correlates the joints' estimates
        # (their shared phase noise) for the joint test below, with either floor
        # the normal projection needs the cycle; without one the floor is flat, as "gait"'s
        floor = "flat" if cycle is None and self.noise_floor == "normal" else self.noise_floor
        noise = estimate_noise(traj.r, band=band, cycle=cycle, floor=floor,
                               samples_per_cycle=None if cycle is None else per_trial,
                               phase=traj.phase if floor == "normal" else None)
        n_pool = traj.phase.ndim - 1 if pool else 0
        # one level for all joints of a trial (or of the pooled trials): they share the rig
        var = noise.pooled_variance(n_pool, channels=True, min_z=_NOISE_MIN_Z)
        q2 = noise.process.square()
        q2 = q2.mean(tuple(range(n_pool))) if n_pool else q2
        ratio = noise_ratio(var, q2)
        if self.velocity_interval:
            h = torch.full(ratio.shape, self.velocity_interval, dtype=torch.long, device=ratio.device)
        else:
            h = velocity_interval_for(ratio, per_cycle)
        return var, ratio, h


def blend_fits(smoothed: ConnectionFit, corrected: ConnectionFit, *,
               variance_factor: float = _BLEND_VARIANCE_FACTOR,
               covariance: Literal["shift", "interpolated"] = "shift"
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
    tie's bands use) is rescaled to those standard errors and, with ``covariance="shift"``,
    the shift the shrink makes is allowed for on its diagonal: per entry
    ``(1 − w)² (β̂_c − β̂_s)² · max(1 − (V + V_s) / D², 0)`` (``V_s`` the smoothed estimate's
    ``Σ se_s²``), the shift's square times the block's share of ``D²`` beyond the two
    estimates' noise: ``D² − V − V_s`` estimates the smoothed estimate's squared bias
    ``‖E β̂_s − β‖²``, whose ``1 − w`` share the combination keeps (README "The tied
    ``∂Â/∂r``'s bands at ω = 0.01": the full square, or without ``V_s``, over-widened the
    bands on the 3-link circle). ``"interpolated"``: without it (the previous version).

    Args:
        smoothed, corrected: fits of the same bins, batch dims ``...``.
        variance_factor, covariance: as above.

    Returns:
        the combined :class:`~torchconn.regression.ConnectionFit` (fields other than the four
        blocks, their standard errors and ``cov_b_dA`` are the corrected fit's) and
        ``w (..., 4)`` for ``c, b, A, ∂A/∂r``.
    """
    if covariance not in ("shift", "interpolated"):
        raise ValueError(f"blend_fits: covariance must be 'shift' or 'interpolated', got "
                         f"{covariance!r}")
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
        cov = _rescaled_covariance(cov, (corrected.se_b, corrected.se_dA),
                                   (out["se_b"], out["se_dA"]))
        if covariance == "shift":
            cov = cov + torch.diag_embed(torch.cat([shifts["b"], shifts["dA"].flatten(-2)], -1))
    return dataclasses.replace(corrected, **out, cov_b_dA=cov), torch.stack(weights, -1)


def _rescaled_covariance(cov: Tensor, se_from: tuple[Tensor, Tensor],
                         se_to: tuple[Tensor, Tensor]) -> Tensor:
    """The joint covariance ``cov (..., M, 3, c, c)`` of ``(b̂, ∂Â/∂r)`` (``ConnectionFit.
    cov_b_dA``) rescaled from the standard errors ``se_from`` to ``se_to`` (pairs ``(se_b
    (..., M, 3, d), se_dA (..., M, 3, d, d))``): entry ``(p, q)`` times ``(to_p/from_p)
    (to_q/from_q)`` (1 where ``from`` is 0 or not finite)."""
    old = torch.cat([se_from[0], se_from[1].flatten(-2)], -1)
    new = torch.cat([se_to[0], se_to[1].flatten(-2)], -1)
    ratio = torch.where(torch.isfinite(old) & (old > 0), new / old.clamp_min(1e-300), 1.0)
    return cov * ratio.unsqueeze(-1) * ratio.unsqueeze(-2)


def noise_ratio(var: Tensor, process_var: Tensor) -> Tensor:
    """``2σ²/q²`` ``(...)``: joint-angle measurement-noise variance of a one-sample difference
    over the process noise's (``(..., d)`` each), averaged over the joints (0 on clean data;
    ~0.6 for ω = 0.005 in the paper's SDE at Δt = 0.05)."""
    q2 = process_var.mean(-1)
    return torch.where(q2 > 0, 2 * var.mean(-1) / q2.clamp_min(1e-300), 0.0)


def velocity_interval_for(ratio: Tensor, samples_per_cycle: Tensor | float,
                          kernel: str = VELOCITY_KERNEL) -> Tensor:
    """Samples per difference ``(...)`` of the noise-aware regression, from the noise ratio
    ``(...)`` and the samples per cycle (a number, or ``(...)`` per element).

    The shortest ``h`` at which the joint-angle noise's variance in a filtered shape velocity
    is at most :data:`_INTERVAL_NOISE_FRACTION` of the process noise's: with the filter's taps
    (:func:`interval_weights`) that ratio is ``(ratio / 2) Σ a_j² / Σ u_j²`` (the box's
    ``ratio / h``; the triangle's ``≈ 6 ratio / (h + 1)²``). At least 1, at most
    :data:`_MAX_INTERVAL_CYCLES` of a cycle (but never capped below 2).
    """
    per_cycle = torch.as_tensor(samples_per_cycle, dtype=torch.float64, device=ratio.device)
    longest = torch.floor(per_cycle * _MAX_INTERVAL_CYCLES).clamp_min(2)
    n = int(longest.max())
    gain = torch.tensor([_rate_gain(h, kernel) for h in range(1, n + 1)], dtype=torch.float64,
                        device=ratio.device)
    ok = (ratio.to(gain).unsqueeze(-1) / 2) * gain <= _INTERVAL_NOISE_FRACTION
    h = torch.where(ok.any(-1), ok.to(torch.int64).argmax(-1) + 1, n)
    return torch.minimum(h.to(longest), longest).long()


def _rate_gain(h: int, kernel: str) -> float:
    """``Σ a_j² / Σ u_j²``: a filter's measurement-noise gain in a shape velocity relative to
    its process-noise gain (box: ``2/h``)."""
    if kernel == "box" or h == 1:
        return 2 / h
    a, _ = _filter_taps(h, kernel)
    return _autocorrelation(a, 0) / _autocorrelation(_weights(h, kernel), 0)


def _usable_rows(traj: Trajectory, h: int, kernel: str) -> int:
    """Interval samples of ``traj`` (all trials) with a finite target and regressors."""
    iv = interval_samples(traj.pose, traj.r, traj.phase, traj.dt, h, kernel)
    ok = iv.xi.isfinite().all(-1) & iv.r_dot.isfinite().all(-1) & iv.r.isfinite().all(-1)
    return int((ok & iv.phase.isfinite()).sum())


def _has_missing(traj: Trajectory) -> bool:
    """Whether ``traj``'s poses, shapes or phase miss a sample (NaN). Without, every interval
    of every filter has a finite target and regressors (:func:`_usable_rows` is the same for
    all)."""
    return not all(bool(x.isfinite().all()) for x in (traj.pose, traj.r, traj.phase))


def _shorter_interval(h: int) -> int:
    """The interval tried when the bins cannot be fitted at ``h > 1``: ``h / 1.5`` rounded,
    shorter by at least one sample (16, 11, 7, 5, 3, 2, 1)."""
    return max(1, min(h - 1, round(h / _FALLBACK_INTERVAL_DIVISOR)))


def _flagged_fit(args: tuple, opts: dict) -> tuple[ConnectionFit, Tensor]:
    """:func:`noise_aware_regression` ``(*args, **opts)`` with the bins it cannot fit left NaN
    (no warning, whatever ``on_ill_conditioned``) and ``(...)`` whether each batch element has
    such a bin. An element without one gets what ``opts`` would give it, bit for bit."""
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", IllConditionedBinWarning)
        fit = noise_aware_regression(*args, **{**opts, "on_ill_conditioned": "warn"})
    p = fit.coef.shape[-2]
    return fit, _wls.unfittable(fit.n_samples, fit.condition, p, fit.coef.dtype).any(-1)


def _take_fit(fit: ConnectionFit, sel: Tensor) -> ConnectionFit:
    """Batch elements ``sel`` of a fit with one batch dim."""
    return dataclasses.replace(fit, **{f.name: getattr(fit, f.name)[sel]
                                       for f in dataclasses.fields(fit)
                                       if getattr(fit, f.name) is not None})


def _samples_per_cycle(traj: Trajectory) -> float:
    """Mean samples per cycle of a phased trajectory."""
    return 2 * math.pi / float(phase_rate(traj.phase, traj.dt).nanmean() * traj.dt)


def _flatten_batch(traj: Trajectory) -> Trajectory:
    """``pose, r, phase`` with the batch dims flattened to one: ``(B, T, ·)``."""
    T = traj.n_samples
    return Trajectory(t=traj.t, pose=traj.pose.reshape(-1, T, 3),
                      r=traj.r.reshape(-1, T, traj.shape_dim)).with_fields(
        phase=traj.phase.reshape(-1, T))


#: torch's CPU elementwise kernels work in chunks of this many values (two AVX-512 vectors of
#: float32) and round the remainder at a tensor's end differently (sin, atan2, ...)
_KERNEL_CHUNK = 32


def _intervals_by_h(flat: Trajectory, h: Tensor, dt: float, kernel: str = VELOCITY_KERNEL
                    ) -> dict[int, IntervalSamples]:
    """:func:`interval_samples` ``(n, T − h, ·)`` of every element of a flattened trajectory
    ``(n, T, ·)`` for each distinct interval in ``h (n,)``, each element's values independent
    of the other elements (bit for bit).

    torch's elementwise kernels (sin, atan2, ...) round the values in the last, partial chunk
    of a tensor differently from the rest, so an element's values would depend on where the
    batch ends. Each interval is therefore computed over the whole batch (not over the elements
    that use it) with the time axis NaN-padded to whole chunks: every element then starts on
    a chunk boundary and no tensor ends in a partial chunk."""
    T = flat.n_samples
    out = {}
    for hg in torch.unique(h).tolist():
        pad = -(T - hg) % _KERNEL_CHUNK
        pose, r, phase = (nn.functional.pad(x, (0, 0, 0, pad) if x.ndim == 3 else (0, pad),
                                            value=float("nan"))
                          for x in (flat.pose, flat.r, flat.phase))
        iv = interval_samples(pose, r, phase, dt, hg, kernel)
        out[hg] = _take_intervals(iv, slice(None), T - hg)
    return out


def _take_intervals(iv: IntervalSamples, idx, n: int | None = None) -> IntervalSamples:
    """Batch elements ``idx`` (and the first ``n`` intervals) of flattened interval samples
    ``(n, N, ·)``."""
    return dataclasses.replace(iv, phase=iv.phase[idx, :n], r=iv.r[idx, :n],
                               r_dot=iv.r_dot[idx, :n], xi=iv.xi[idx, :n])


def _scatter_fits(parts, n: int, batch: tuple) -> ConnectionFit:
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


def pooled_view(traj: Trajectory, h: int, kernel: str = VELOCITY_KERNEL) -> IntervalSamples:
    """:func:`interval_view` of every trial at interval ``h``, pooled into one recording
    ``(N·(T − h), ·)`` (:func:`~torchconn.trajectory.pool_batch`)."""
    view = interval_view(traj, h, kernel)
    return dataclasses.replace(view, phase=pool_batch(view.phase, 0), r=pool_batch(view.r, 1),
                               r_dot=pool_batch(view.r_dot, 1), xi=pool_batch(view.xi, 1), h=h)


def interval_view(traj: Trajectory, h, kernel: str = VELOCITY_KERNEL) -> IntervalSamples:
    """:func:`interval_samples` of a trajectory with a per-element interval ``h`` (an int or a
    ``(...)`` tensor): ``(..., T − min h, ·)``, elements with a longer interval padded with NaN
    at the end (``.h`` is the shortest)."""
    h = torch.as_tensor(h, device=traj.pose.device)
    if h.ndim == 0:
        return interval_samples(traj.pose, traj.r, traj.phase, traj.dt, int(h), kernel)
    flat = _flatten_batch(traj)
    h_flat = h.reshape(-1)
    n = traj.n_samples - int(h_flat.min())
    out = None
    for hg, iv in _intervals_by_h(flat, h_flat, traj.dt, kernel).items():
        idx = torch.nonzero(h_flat == hg).flatten()
        vals = [v[idx] for v in (iv.phase, iv.r, iv.r_dot, iv.xi)]
        if out is None:
            out = [v.new_full((h_flat.numel(), n) + v.shape[2:], float("nan")) for v in vals]
        for o, v in zip(out, vals, strict=True):
            o[idx, :v.shape[1]] = v
    batch = tuple(traj.batch_shape)
    phase, r, r_dot, xi = (o.reshape(batch + o.shape[1:]) for o in out)
    return IntervalSamples(phase=phase, r=r, r_dot=r_dot, xi=xi, h=int(h_flat.min()),
                           dt=float(traj.dt), kernel=iv.kernel)
