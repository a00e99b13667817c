"""Measurement noise of recorded channels, from the spectrum of their increments.

The increments of a signal driven by white process noise and observed with white measurement
noise have the spectrum ``S(f) = q² + 4 sin²(πf) σ²`` away from the signal's own harmonics:
the process noise is flat, the measurement noise rises towards Nyquist. :func:`estimate_noise`
fits ``(q², σ²)`` to a multitaper spectrum of the increments over a band chosen per channel
(:class:`NoiseEstimate`); :func:`phase_noise_floor` and :func:`normal_increments` model or
remove the part of the process floor that a gait's phase noise adds.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass
from typing import Literal

import torch
from torch import Tensor, nn

from ..phase.fourier import FourierSeries
from ..physics import se2
from ..trajectory import over_spans

__all__ = ["NoiseEstimate", "estimate_noise", "phase_noise_floor", "normal_increments",
           "normal_span", "bridge_gaps", "KERNEL_CHUNK"]


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
#: threshold trades the two; the test of the channels' mean stops the band sooner on a gait's
#: harmonics, which raise every joint a little
_BAND_Z = 3.5


#: the standard error of σ² treats the multitaper ordinates of the band as independent
#: periodogram ordinates; the band is chosen from the same data, so the standard errors are
#: widened by this factor
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
        of weakly resolved channels that came out high."""
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
                   floor: Literal["flat", "low_rate", "normal"] = "flat",
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
            (:func:`_off_harmonics`; at 32 or fewer samples per cycle they fall there), and
            the result's ``correlation`` holds the channels' shared phase noise
            (:func:`_channel_correlation`) for :meth:`NoiseEstimate.pooled_mean`.
        floor: with a ``cycle``, ``"flat"`` (default, as ``NoiseAwareRegression``'s
            ``noise_floor``) keeps the process floor flat and uses the cycle only for
            ``correlation``; ``"low_rate"`` gives the batch elements whose gait's harmonics
            reach the top band (where :func:`_off_harmonics` leaves ordinates out: at 32 or
            fewer samples per cycle for an order-8 cycle, where the lines' tails fill the
            band) :func:`phase_noise_floor`'s shape of the process floor (the gait's
            harmonics spread by phase noise as large as the channels' own) and keeps the
            others' flat, bit for bit. ``"normal"`` (needs ``phase``): the increments projected out of
            the span of the cycle's first derivatives (:func:`normal_increments`), fitted
            with a flat floor: the
            phase noise, which moves every channel along the cycle's tangent, is projected
            out, and with it the lines' tilt of the band; the band
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
        bridged = torch.diff(bridge_gaps(x), dim=-2)
        if angular is not None:
            bridged = torch.where(angular.to(x.device), se2.wrap_angle(bridged), bridged)
    if floor not in ("flat", "low_rate", "normal"):
        raise ValueError(f"estimate_noise: floor must be 'flat', 'low_rate' or 'normal', "
                         f"got {floor!r}")
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
        shape = (cycle, samples_per_cycle) if floor == "low_rate" else None
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
    estimates correlate by ``⟨C_cc'²⟩ / √(⟨C_cc²⟩ ⟨C_c'c'²⟩)`` (means over the cycle)."""
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
#: band); with ``γ', …, γ^(J)`` out the error enters at order ``e^J``
_NORMAL_SPAN = 4


#: the normal projection's band (cycles per sample; to Nyquist), fixed: the band rule's own
#: selection (a step that deviates low by chance is kept, one that deviates high stops the
#: band) biases σ̂² high on the projected channels, whose floor is flat to the band's edge;
#: above 0.1 the phase estimate's errors left after the projection are small against the
#: measurement noise's rise
_NORMAL_BAND_LOW = 0.1


#: harmonics of the fitted cycle whose power (summed over the channels) is below this
#: fraction of the cycle's do not shape the frame: they are the fit's estimation noise
#: (fractions of 10⁻⁵ on circles), which the derivatives amplify by ``k^j`` into directions
#: that follow the data's own deviations
_FRAME_POWER = 1e-3


#: a derivative whose part outside the span already taken is below this fraction of it (a
#: planar gait's third) adds no direction, only rounding: none is projected out there
_NEW_DIRECTION = 1e-2


def normal_span(d: int) -> int:
    """How many derivatives ``γ', …, γ^(J)`` of the cycle :func:`normal_increments` projects
    out of ``d`` channels: ``J = min(4, d // 2)``, 0 for ``d ≤ 2``: with two channels the
    one normal left carries the phase estimate's own errors, and :func:`estimate_noise` keeps
    the flat floor."""
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
    phase = bridge_gaps(phase.to(u).unsqueeze(-1)).squeeze(-1)
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
    padded = nn.functional.pad(phi, (0, -n % KERNEL_CHUNK))
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


def bridge_gaps(x: Tensor) -> Tensor:
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
                        shape: tuple[FourierSeries, Tensor | float] | None = None,
                        weights: tuple[Tensor, Tensor] | None = None) -> _Spectrum:
    """:class:`_Spectrum` of increments ``u (..., n, C)`` (NaN where missing); ``shape``:
    None (a flat process floor) or ``(cycle, samples_per_cycle)`` for
    :func:`phase_noise_floor`'s floor for the batch elements whose gait's harmonics reach the
    top band (:func:`_off_harmonics`; flat for the others).

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
        cycle, per_cycle = shape
        gait = phase_noise_floor(f, cycle, per_cycle, n=n)  # (..., F, C)
        # (..., 1, 1): a harmonic in the top band (ordinates left out there)
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
                              (0, -n_harmonics % KERNEL_CHUNK))
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
    does. Not left out: the lines' phase-noise tails beside the cores, which at few samples
    per cycle read as noise or drive ``σ̂²`` below 0 (``floor="low_rate"`` models them).
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


#: torch's CPU elementwise kernels work in chunks of this many values (two AVX-512 vectors of
#: float32) and round the remainder at a tensor's end differently (sin, atan2, ...)
KERNEL_CHUNK = 32
