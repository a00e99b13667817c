"""Noise-aware connection regression: raw interval differences with an errors-in-variables fix.

The smoothed regression (:func:`~torchconn.regression.connection_regression` on a Kalman
smoother's output) smooths the noisy pose channels, which carry the target ``ξ``, harder than
the shape channels, which carry the regressors ``δ̇``; that removes the body's response to the
very shape jitter that identifies ``A`` and shrinks ``Â`` towards 0 under motion-capture noise.
Here target and regressors see the same operation -- a difference over one interval of ``h``
samples -- and nothing is smoothed:

- ``ξ_k = log(g_k⁻¹ g_{k+h}) / (hΔt)``, the mean body velocity over ``[t_k, t_{k+h}]``;
- ``ṙ_k = (r_{k+h} − r_k) / (hΔt)``, the mean shape velocity over the same interval, and
  ``r̄_k = (r_k + r_{k+h}) / 2``, its mid-point shape (Stratonovich's mid-point rule);
- the phase at the interval's middle.

Independent Gaussian noise of variance ``σ_i²`` on ``r_i`` puts noise of variance ``σ_i²/2``
into ``r̄_i`` and ``2σ_i²/(hΔt)²`` into ``ṙ_i``, uncorrelated with each other and with the
pose noise in ``ξ``. Its expected contribution to each bin's normal matrix ``XᵀWX`` for the
design ``[1, δ, δ̇, δ̇⊗δ]`` is known in closed form from ``XᵀWX`` itself
(:func:`eiv_correction`) and is subtracted (errors in variables; the right-hand side needs no
correction). The per-channel noise is estimated from the data (:func:`estimate_noise`).
Where the data are too few for the correction to pay (it removes most of the normal matrix and
amplifies the noise), the estimate falls back towards the smoothed regression's
(:func:`blend_fits`).
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass

import torch
from torch import Tensor, nn

from .._options import option
from ..phase.limit_cycle import phase_rate
from ..physics import se2
from ..trajectory import Trajectory, pool_batch
from . import _wls
from .binning import BinIndex, assign_bins
from .connection import ConnectionFit, _blocks, _connection_fit
from .tube import TubeRegression, _auto_window, _auto_windows

__all__ = ["NoiseEstimate", "estimate_noise", "interval_samples", "IntervalSamples",
           "eiv_correction", "noise_aware_regression", "blend_fits", "NoiseAwareRegression", "interval_view",
           "noise_ratio", "velocity_interval_for"]

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
    """

    measurement: Tensor
    process: Tensor
    variance_se: Tensor
    band_low: Tensor | None = None
    variance: Tensor | None = None

    def pooled_variance(self, n_batch_dims: int, *, min_z: float = 2.0) -> Tensor:
        """Measurement variance ``(C,)``-shaped after averaging the leading ``n_batch_dims``
        dims (trials of one rig), set to 0 where it is not ``min_z`` standard errors above 0
        (clean data: the estimate is then only the periodogram's scatter)."""
        dims = tuple(range(n_batch_dims))
        var = self.measurement.square() if self.variance is None else self.variance
        count = math.prod(var.shape[:n_batch_dims])
        mean = var.mean(dims) if dims else var
        se = (self.variance_se.square().sum(dims).sqrt() / count) if dims else self.variance_se
        return torch.where(mean > min_z * se, mean, torch.zeros_like(mean))


def estimate_noise(x: Tensor, *, band: tuple[float, float] | None = None,
                   angular: Tensor | None = None) -> NoiseEstimate:
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
            (default): chosen from the data as above.
        angular: optional ``(C,)`` bool, channels whose increments are wrapped to ``(−π, π]``
            (a heading recorded wrapped).

    Returns:
        :class:`NoiseEstimate` with ``(..., C)`` standard deviations (clamped at 0).
    """
    if not isinstance(x, Tensor) or not x.is_floating_point() or x.ndim < 2:
        raise TypeError("estimate_noise: x must be a floating-point tensor (..., T, C)")
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
    spec = _increment_spectrum(u, bridged)
    f = spec.f
    if band is not None:
        inside = (f >= band[0]) & (f <= band[1]) & (f > 0)
        if int(inside.sum()) < 4:
            raise ValueError(f"estimate_noise: the band {band} holds fewer than 4 frequencies "
                             f"of a {n + 1}-sample record")
        sel = inside[:, None].to(x.dtype).expand(spec.power.shape)
        low = torch.full(spec.power.shape[:-2] + spec.power.shape[-1:], float(band[0]),
                         dtype=x.dtype, device=x.device)
    else:
        sel, low = _choose_band(spec, f, spec.s0, spec.s1)
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
                         variance_se=se, band_low=low, variance=sigma2)


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
    x0: Tensor
    x1: Tensor
    s0: Tensor  # (..., C): x0 = s0, x1 = 2 s0 − 2 s1 cos 2πf
    s1: Tensor
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


def _increment_spectrum(u: Tensor, bridged: Tensor | None = None) -> _Spectrum:
    """:class:`_Spectrum` of increments ``u (..., n, C)`` (NaN where missing).

    Zeros in place of missing increments would spread the gait's strong lines over the whole
    spectrum (a random mask leaks a line's power everywhere), so the spectrum is taken of
    ``bridged``, the increments of the recording with its gaps bridged by straight lines (the
    signal goes on, the noise does not), while the expectation below counts only the present
    increments of ``u``.

    With the taper ``a_t = w_t m_t`` (taper times the 0/1 mask of present increments), white
    process increments (lag-0 covariance ``q²``) and the measurement noise's MA(1) increments
    (``2σ²`` at lag 0, ``−σ²`` at lag 1) give ``E|Σ a_t u_t e^{−2πift}|² = (q² + 2σ²) Σ a_t²
    − 2σ² cos(2πf) Σ a_t a_{t+1}`` exactly, whatever the gaps.
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
    s0 = a.square().sum(-2).mean(-2).unsqueeze(-2)  # (..., 1, C)
    s1 = (a[..., :-1, :] * a[..., 1:, :]).sum(-2).mean(-2).unsqueeze(-2)
    f = torch.fft.rfftfreq(n_fft, dtype=u.dtype, device=u.device)
    cos = torch.cos(2 * math.pi * f)[:, None]
    return _Spectrum(power=power, x0=s0.expand(power.shape), x1=2 * s0 - 2 * cos * s1,
                     s0=s0.squeeze(-2), s1=s1.squeeze(-2), f=f, density=n_fft / n)


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
    det = a * d - b * b
    det = torch.where(det > 0, det, math.nan)
    q2, s2 = (d * r0 - b * r1) / det, (a * r1 - b * r0) / det
    model = q2.unsqueeze(-2) * x0 + s2.unsqueeze(-2) * x1
    # a fitted line that dips towards 0 somewhere would give those ordinates all the weight
    mean = (sel * p).sum(-2, keepdim=True) / sel.sum(-2, keepdim=True).clamp_min(1)
    model = torch.maximum(model, 0.1 * mean)
    v = w * weight * model.square()
    e00, e01, e11 = (v * x0 * x0).sum(-2), (v * x0 * x1).sum(-2), (v * x1 * x1).sum(-2)
    i00, i01, i11 = d / det, -b / det, a / det
    cov = (i00 * i00 * e00 + 2 * i00 * i01 * e01 + i01 * i01 * e11,
           i00 * i01 * e00 + (i00 * i11 + i01 * i01) * e01 + i01 * i11 * e11,
           i01 * i01 * e00 + 2 * i01 * i11 * e01 + i11 * i11 * e11)
    return _Line(q2=q2, sigma2=s2, model=model, cov=cov)


def _choose_band(spec: _Spectrum, f: Tensor, s0: Tensor, s1: Tensor) -> tuple[Tensor, Tensor]:
    """Ordinates ``(..., F, C)`` (0/1) of the band of every channel and its low edge
    ``(..., C)``: the top band, grown downwards step by step while each step's mean agrees
    with the unweighted line fitted above it (the line's own uncertainty included).

    The line's columns are ``x0 = s0`` and ``x1 = 2 s0 − 2 s1 cos 2πf`` (:class:`_Spectrum`),
    so every sum the fits need is a sum of powers of ``cos 2πf`` (batch-free) or of the power
    and the power times ``cos 2πf`` over each step: the scan runs on ``(..., C)`` sums, not
    on the spectrum.
    """
    dtype, power = spec.power.dtype, spec.power
    n_steps = int(round((_TOP_BAND - _LOWEST_FREQUENCY) / _BAND_STEP))
    edges = _TOP_BAND - _BAND_STEP * torch.arange(n_steps + 1, dtype=dtype, device=f.device)
    # group 0: the top band; group i: [edge_i, edge_{i-1})
    group = torch.stack([(f >= edges[0]) & (f > 0)]
                        + [(f >= edges[i]) & (f < edges[i - 1]) & (f > 0)
                           for i in range(1, n_steps + 1)]).to(dtype)  # (G, F)
    c = torch.cos(2 * math.pi * f)
    cos_sums = group @ torch.stack([c**k for k in range(5)], -1)  # (G, 5): Σ cos^k
    p0 = torch.einsum("gf,...fc->...gc", group, power)  # Σ p per group
    p1 = torch.einsum("gf,...fc->...gc", group * c, power)  # Σ p cos
    u0, u1 = 2 * s0, -2 * s1  # x1 = u0 + u1 cos

    ck = [torch.zeros_like(s0) + cos_sums[0, k] for k in range(5)]  # running Σ cos^k, (..., C)
    q0, q1 = p0[..., 0, :], p1[..., 0, :]
    growing = torch.ones_like(s0, dtype=torch.bool)
    low = torch.full_like(s0, _TOP_BAND)
    for g in range(1, n_steps + 1):  # a few frequency steps, each batched over all channels
        count = cos_sums[g, 0]
        if count == 0:
            continue
        a, bb = s0 * s0 * ck[0], s0 * (u0 * ck[0] + u1 * ck[1])
        d = u0 * u0 * ck[0] + 2 * u0 * u1 * ck[1] + u1 * u1 * ck[2]
        r0, r1 = s0 * q0, u0 * q0 + u1 * q1
        det = a * d - bb * bb
        det = torch.where(det > 0, det, math.nan)
        q2, s2 = (d * r0 - bb * r1) / det, (a * r1 - bb * r0) / det
        al, ga = q2 * s0 + s2 * u0, s2 * u1  # the fitted line: al + ga cos
        mk = [al * al * ck[k] + 2 * al * ga * ck[k + 1] + ga * ga * ck[k + 2] for k in range(3)]
        e00 = s0 * s0 * mk[0]
        e01 = s0 * (u0 * mk[0] + u1 * mk[1])
        e11 = u0 * u0 * mk[0] + 2 * u0 * u1 * mk[1] + u1 * u1 * mk[2]
        i00, i01, i11 = d / det, -bb / det, a / det
        c00 = i00 * i00 * e00 + 2 * i00 * i01 * e01 + i01 * i01 * e11
        c01 = i00 * i01 * e00 + (i00 * i11 + i01 * i01) * e01 + i01 * i11 * e11
        c11 = i01 * i01 * e00 + 2 * i01 * i11 * e01 + i11 * i11 * e11
        m0, m1 = s0, u0 + u1 * cos_sums[g, 1] / count
        expected = q2 * m0 + s2 * m1
        observed = p0[..., g, :] / count
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
        ck = [ck[k] + grow * cos_sums[g, k] for k in range(5)]
        q0, q1 = q0 + grow * p0[..., g, :], q1 + grow * p1[..., g, :]
        low = torch.where(growing, edges[g], low)
    sel = ((f[:, None] >= low.unsqueeze(-2)) & (f[:, None] > 0)).to(dtype)
    return sel, low


@dataclass(frozen=True)
class IntervalSamples:
    """Samples on intervals of ``h`` recorded samples (``N = T − h`` intervals).

    Attributes:
        phase: ``(..., N)`` phase at each interval's middle.
        r: ``(..., N, d)`` mid-point shape ``(r_k + r_{k+h}) / 2``.
        r_dot: ``(..., N, d)`` mean shape velocity ``(r_{k+h} − r_k) / (hΔt)``.
        xi: ``(..., N, 3)`` mean body velocity ``log(g_k⁻¹ g_{k+h}) / (hΔt)``.
        h: the interval in samples; dt: the sampling interval.
    """

    phase: Tensor
    r: Tensor
    r_dot: Tensor
    xi: Tensor
    h: int
    dt: float


def interval_samples(pose: Tensor, r: Tensor, phase: Tensor, dt: float, h: int) -> IntervalSamples:
    """Target and regressors from raw differences over ``h`` samples (nothing smoothed).

    Args:
        pose: ``(..., T, 3)``; r: ``(..., T, d)``; phase: ``(..., T)`` (unwrapped or wrapped);
            dt: sampling interval; h: interval in samples, ``1 ≤ h < T``.
    """
    T = r.shape[-2]
    if isinstance(h, bool) or not isinstance(h, int) or not 1 <= h < T:
        raise ValueError(f"velocity interval h must be an integer in [1, {T - 1}], got {h!r}")
    span = h * dt
    step = se2.wrap_angle(phase[..., h:] - phase[..., :-h])
    return IntervalSamples(
        phase=phase[..., :-h] + step / 2,
        r=(r[..., h:, :] + r[..., :-h, :]) / 2,
        r_dot=(r[..., h:, :] - r[..., :-h, :]) / span,
        xi=se2.log(se2.relative(pose[..., :-h, :], pose[..., h:, :])) / span,
        h=h, dt=float(dt),
    )


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
    dz = torch.einsum("bi,bk,jk->bkij", s_rate, sb, eye).flatten(-2)
    rz = torch.einsum("bj,bk,ik->bkij", s_delta, sa, eye).flatten(-2)
    zz = (torch.einsum("bik,bj,jl->bijkl", q_rate, sb, eye)
          + torch.einsum("bjl,bi,ik->bijkl", q_delta, sa, eye)
          - torch.einsum("b,bi,bj,ik,jl->bijkl", w, sa, sb, eye, eye)).reshape(-1, d * d, d * d)
    z0 = 1 + 2 * d
    out[:, 1:1 + d, z0:] = dz
    out[:, 1 + d:z0, z0:] = rz
    out[:, z0:, 1:1 + d] = dz.mT
    out[:, z0:, 1 + d:z0] = rz.mT
    out[:, z0:, z0:] = zz
    return out


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
) -> ConnectionFit:
    """Per-bin ``ξ ≈ c + bδ + Aδ̇ + ∂A/∂r (δ̇⊗δ)`` on interval samples, noise-corrected.

    Args:
        samples: :func:`interval_samples` ``(..., N, ·)``.
        bins: :func:`~torchconn.regression.assign_bins` of ``samples.phase``.
        gamma_m, gamma_dot_m: ``(..., M, d)`` limit cycle and ``γ̇`` at the bin centres.
        noise_var: ``(..., d)`` measurement-noise variance of each joint angle (broadcastable
            to the batch), e.g. :func:`estimate_noise`'s ``measurement²``.
        delta_max, ridge, on_ill_conditioned: as in
            :func:`~torchconn.regression.connection_regression`.

    Returns:
        :class:`~torchconn.regression.ConnectionFit`. The standard errors treat the rows as
        independent although consecutive intervals overlap; measured against the truth
        (3-, 5-, 9-link, ω = 0.005-0.01, ``h`` = 6-12) the squared errors average 0.9-1.1 times
        the squared standard errors this way (an extra ``√h`` made them ``h`` times too wide).
    """
    fn = "noise_aware_regression"
    s = _wls.prepare(fn, samples.r, samples.r_dot, samples.xi, "xi", 3, bins, gamma_m,
                     gamma_dot_m)
    d = s.r.shape[-1]
    batch = tuple(s.batch_shape)
    if not isinstance(noise_var, Tensor) or noise_var.shape[-1:] != (d,):
        raise ValueError(f"{fn}: noise_var must be a tensor (..., d) with d = {d}, got "
                         f"{getattr(noise_var, 'shape', type(noise_var).__name__)}")
    if bool((noise_var < 0).any()) or not bool(torch.isfinite(noise_var).all()):
        raise ValueError(f"{fn}: noise_var must be finite and >= 0")
    var = noise_var.to(s.r).expand(batch + (d,))
    p = 1 + 2 * d + d * d
    m = s.n_bins
    var_bins = var.unsqueeze(-2).expand(batch + (m, d)).reshape(-1, d)
    span = samples.h * samples.dt
    var_delta, var_rate = var_bins / 2, 2 * var_bins / span**2

    def correction(gram: Tensor, sel) -> Tensor:
        return eiv_correction(gram, var_delta[sel], var_rate[sel])

    sol = _wls.solve(s, _blocks, p, fn=fn, delta_max=delta_max, ridge=ridge, min_samples=None,
                     max_condition=None, on_ill_conditioned=on_ill_conditioned,
                     correction=correction)
    sol = sol.unflatten(s.batch_shape, m)
    return _connection_fit(sol, d)


# ------------------------------------------------------------------------ the regression stage
#: the velocity interval is the shortest at which the joint-angle noise adds at most this
#: fraction of the process noise's variance to a shape-velocity difference
_INTERVAL_NOISE_FRACTION = 0.05
#: longest velocity interval, as a fraction of a cycle (the mid-point rule's bias grows with it)
_MAX_INTERVAL_CYCLES = 1 / 10
#: bin half-width grows by this many bin spacings per unit of the noise ratio (see noise_ratio),
#: up to _MAX_NOISE_WINDOW spacings: wider windows lowered the error on a circle gait but
#: biased the strongly curved 3-link reference gait (measured: 9 % at 3 spacings, 17 % at 6,
#: ω = 0.005)
_WINDOW_PER_NOISE_RATIO = 20.0
_MAX_NOISE_WINDOW = 3.0
#: :func:`blend_fits` keeps the corrected estimate only where it differs from the smoothed one
#: by more than this many times its own variance. Set on seed 5 (3-, 5-, 9-link circle gaits,
#: one trial of 30 cycles, ω = 0.002-0.02): with 1 (the plain Stein rule) the blend was worse
#: than the smoothed estimate in 4 of 12 cells (Â 44 % vs 38 % at 5 links, ω = 0.01), with 2
#: in none; pooled 4 x 30 cycles it cost 0-2.5 points of Â against factor 1 at ω ≤ 0.005
#: and 0.5-5 points at ω = 0.01 (still below the smoothed estimate)
_BLEND_VARIANCE_FACTOR = 2.0


@dataclass(frozen=True, kw_only=True)
class NoiseAwareRegression(TubeRegression):
    """:class:`~torchconn.regression.tube.TubeRegression` with the connection regressed on raw
    interval differences and corrected for the joint angles' measurement noise.

    Body and shape velocities are differences of the recorded poses and joint angles over
    ``velocity_interval`` samples (:func:`interval_samples`), so target and regressors see the
    same operation and nothing is smoothed; each joint's noise is estimated from the spectrum
    of its increments (:func:`estimate_noise`) and removed from every bin's normal equations
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
        velocity_interval: samples per difference; None chooses it per batch element from the
            noise (:func:`velocity_interval_for`). With ``window=None`` the bins' width also
            grows with the noise.
        noise_band_low: lowest frequency (cycles per sample) of the noise fit; None: chosen
            per batch element and joint from the data (:func:`estimate_noise`).
        shrink_to_smoothed: combine with the smoothed estimate (:func:`blend_fits`); False:
            the corrected estimate alone (unbiased, but with one trial of a 9-link swimmer at
            ω ≥ 0.005 measured 2-4 times further off than the smoothed one).
    """

    velocity_interval: int | None = option(None, ge=1)
    noise_band_low: float | None = option(None, gt=0, le=0.45)
    shrink_to_smoothed: bool = True

    def _corrected_fit(self, traj, pool, samples, gamma_m, gamma_dot_m, opts, bins_for):
        """Unpooled batch elements may carry different noise (a sweep's noise levels), so each
        gets its own interval and window; elements sharing both are regressed together (one
        call per distinct pair, not per trial)."""
        d, n_bins = traj.shape_dim, self.n_bins
        var, ratio, h = self.noise_setup(traj, pool)
        if pool:
            view = interval_view(traj, h)
            view = IntervalSamples(phase=pool_batch(view.phase, 0), r=pool_batch(view.r, 1),
                                   r_dot=pool_batch(view.r_dot, 1), xi=pool_batch(view.xi, 1),
                                   h=int(h), dt=float(traj.dt))
            window = self.window or self._window(view.phase, d, float(ratio))
            bins = assign_bins(view.phase, n_bins, window=window, kernel=self.kernel)
            fit = noise_aware_regression(view, bins, gamma_m, gamma_dot_m, var, **opts)
            meta = {"velocity_interval": int(h), "noise_ratio": float(ratio),
                    "noise_r": var.sqrt().tolist()}
            return fit, window, meta
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
        parts = []
        for g, (hg, wg) in enumerate(groups.tolist()):
            idx = torch.nonzero(inverse == g).flatten()
            iv = _take_intervals(by_h[int(hg)], idx)
            bins = assign_bins(iv.phase, n_bins, window=wg, kernel=self.kernel)
            parts.append((idx, noise_aware_regression(iv, bins, g_m[idx], g_dot[idx],
                                                      var_flat[idx], **opts)))
        meta = {"velocity_interval": h.tolist(), "noise_ratio": ratio.tolist(),
                "noise_r": var.sqrt().tolist(), "windows": windows.reshape(batch).tolist()}
        return _scatter_fits(parts, n, batch), float(windows.max()), meta

    def _connection_fit(self, traj, pool, samples, gamma_m, gamma_dot_m, opts, bins_for):
        """The corrected fit, shrunk towards the smoothed one (:func:`blend_fits`)."""
        fit, window, meta = self._corrected_fit(traj, pool, samples, gamma_m, gamma_dot_m, opts,
                                                bins_for)
        if not self.shrink_to_smoothed:
            return fit, window, meta
        tube, _, _ = super()._connection_fit(traj, pool, samples, gamma_m, gamma_dot_m, opts,
                                             bins_for)
        fit, weights = blend_fits(tube, fit)
        meta["corrected_weight"] = weights.tolist()
        return fit, window, meta

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

    def noise_setup(self, traj: Trajectory, pool: bool):
        """Joint-angle noise variance ``(..., d)``, noise ratio and velocity interval ``(...)``
        (``(d,)`` and scalars when ``pool``: the trials share one rig).

        Unpooled, each batch element's are its own: its samples per cycle (which set the
        longest interval) come from its own phase rate and its noise band from its own data
        (:func:`estimate_noise`), so a trial's fit does not depend on the trials it shares a
        batch with (a sweep's cells)."""
        per_cycle = 2 * math.pi / (phase_rate(traj.phase, traj.dt) * traj.dt)  # (...)
        if pool:
            per_cycle = per_cycle.nanmean()
        band = None if self.noise_band_low is None else (self.noise_band_low, 0.5)
        noise = estimate_noise(traj.r, band=band)  # (..., d), each element on its own
        n_pool = traj.phase.ndim - 1 if pool else 0
        var = noise.pooled_variance(n_pool)
        q2 = noise.process.square()
        q2 = q2.mean(tuple(range(n_pool))) if n_pool else q2
        ratio = noise_ratio(var, q2)
        if self.velocity_interval:
            h = torch.full(ratio.shape, self.velocity_interval, dtype=torch.long, device=ratio.device)
        else:
            h = velocity_interval_for(ratio, per_cycle)
        return var, ratio, h


def blend_fits(smoothed: ConnectionFit, corrected: ConnectionFit, *,
               variance_factor: float = _BLEND_VARIANCE_FACTOR) -> tuple[ConnectionFit, Tensor]:
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

    Args:
        smoothed, corrected: fits of the same bins, batch dims ``...``.

    Returns:
        the combined :class:`~torchconn.regression.ConnectionFit` (fields other than the four
        blocks and their standard errors are the corrected fit's; the standard errors are
        ``(1 − w) se_s + w se_c``, an upper bound) and ``w (..., 4)`` for ``c, b, A, ∂A/∂r``.
    """
    out, weights = {}, []
    for name in ("c", "b", "A", "dA"):
        est_s, est_c = getattr(smoothed, name), getattr(corrected, name)
        se_s, se_c = getattr(smoothed, "se_" + name), getattr(corrected, "se_" + name)
        n_tail = est_s.ndim - smoothed.n_samples.ndim + 1  # the bins and the block's entries
        dims = tuple(range(-n_tail, 0))
        d2 = (est_c - est_s).square().nansum(dims)
        var = se_c.square().nansum(dims)
        w = torch.where(d2 > 0, (1 - variance_factor * var / d2.clamp_min(1e-300)).clamp(0, 1),
                        0.0)
        wx = w.reshape(w.shape + (1,) * n_tail)
        out[name] = est_s + wx * (est_c - est_s)
        out["se_" + name] = (1 - wx) * se_s + wx * se_c
        weights.append(w)
    return dataclasses.replace(corrected, **out), torch.stack(weights, -1)


def noise_ratio(var: Tensor, process_var: Tensor) -> Tensor:
    """``2σ²/q²`` ``(...)``: joint-angle measurement-noise variance of a one-sample difference
    over the process noise's (``(..., d)`` each), averaged over the joints (0 on clean data;
    ~0.6 for ω = 0.005 in the paper's SDE at Δt = 0.05)."""
    q2 = process_var.mean(-1)
    return torch.where(q2 > 0, 2 * var.mean(-1) / q2.clamp_min(1e-300), 0.0)


def velocity_interval_for(ratio: Tensor, samples_per_cycle: Tensor | float) -> Tensor:
    """Samples per difference ``(...)`` of the noise-aware regression, from the noise ratio
    ``(...)`` and the samples per cycle (a number, or ``(...)`` per element).

    Over ``h`` samples the process noise's variance grows as ``h`` and the measurement noise's
    stays, so ``h = ⌈ratio / _INTERVAL_NOISE_FRACTION⌉``, at least 1 and at most
    :data:`_MAX_INTERVAL_CYCLES` of a cycle (but never capped below 2).
    """
    per_cycle = torch.as_tensor(samples_per_cycle, dtype=torch.float64, device=ratio.device)
    longest = torch.floor(per_cycle * _MAX_INTERVAL_CYCLES).clamp_min(2)
    h = torch.ceil(ratio / _INTERVAL_NOISE_FRACTION).clamp_min(1)
    return torch.minimum(h.to(longest), longest).long()


def _flatten_batch(traj: Trajectory) -> Trajectory:
    """``pose, r, phase`` with the batch dims flattened to one: ``(B, T, ·)``."""
    T = traj.n_samples
    return Trajectory(t=traj.t, pose=traj.pose.reshape(-1, T, 3),
                      r=traj.r.reshape(-1, T, traj.shape_dim)).with_fields(
        phase=traj.phase.reshape(-1, T))


#: torch's CPU elementwise kernels work in chunks of this many values (two AVX-512 vectors of
#: float32) and round the remainder at a tensor's end differently (sin, atan2, ...)
_KERNEL_CHUNK = 32


def _intervals_by_h(flat: Trajectory, h: Tensor, dt: float) -> dict[int, IntervalSamples]:
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
        iv = interval_samples(pose, r, phase, dt, hg)
        out[hg] = _take_intervals(iv, slice(None), T - hg)
    return out


def _take_intervals(iv: IntervalSamples, idx, n: int | None = None) -> IntervalSamples:
    """Batch elements ``idx`` (and the first ``n`` intervals) of flattened interval samples
    ``(n, N, ·)``."""
    return dataclasses.replace(iv, phase=iv.phase[idx, :n], r=iv.r[idx, :n],
                               r_dot=iv.r_dot[idx, :n], xi=iv.xi[idx, :n])


def _scatter_fits(parts, n: int, batch: tuple) -> ConnectionFit:
    """One fit ``(*batch, M, ·)`` from fits of subsets ``(len(idx), M, ·)`` of ``n`` elements."""
    first = parts[0][1]
    out = {}
    for f in dataclasses.fields(first):
        ref = getattr(first, f.name)
        if ref is None:
            out[f.name] = None
            continue
        full = ref.new_zeros((n,) + ref.shape[1:])
        for idx, fit in parts:
            full[idx] = getattr(fit, f.name)
        out[f.name] = full.reshape(batch + ref.shape[1:])
    return ConnectionFit(**out)


def interval_view(traj: Trajectory, h) -> IntervalSamples:
    """:func:`interval_samples` of a trajectory with a per-element interval ``h`` (an int or a
    ``(...)`` tensor): ``(..., T − min h, ·)``, elements with a longer interval padded with NaN
    at the end (``.h`` is the shortest)."""
    h = torch.as_tensor(h, device=traj.pose.device)
    if h.ndim == 0:
        return interval_samples(traj.pose, traj.r, traj.phase, traj.dt, int(h))
    flat = _flatten_batch(traj)
    h_flat = h.reshape(-1)
    n = traj.n_samples - int(h_flat.min())
    out = None
    for hg, iv in _intervals_by_h(flat, h_flat, traj.dt).items():
        idx = torch.nonzero(h_flat == hg).flatten()
        vals = [v[idx] for v in (iv.phase, iv.r, iv.r_dot, iv.xi)]
        if out is None:
            out = [v.new_full((h_flat.numel(), n) + v.shape[2:], float("nan")) for v in vals]
        for o, v in zip(out, vals, strict=True):
            o[idx, :v.shape[1]] = v
    batch = tuple(traj.batch_shape)
    phase, r, r_dot, xi = (o.reshape(batch + o.shape[1:]) for o in out)
    return IntervalSamples(phase=phase, r=r, r_dot=r_dot, xi=xi, h=int(h_flat.min()),
                           dt=float(traj.dt))
