"""Phase estimation for noisy oscillator data: the Phaser algorithm, batched.

Phaser (Revzen & Guckenheimer 2008, Phys. Rev. E 78, 051907) turns a multichannel
record of an oscillator into a phase that advances uniformly in time on average:

1. each channel is centred and scaled, and its *protophase* is the angle of its analytic
   signal (FFT-based Hilbert transform along time);
2. each protophase ``θ`` is corrected to ``ψ = θ + P(θ)`` so that it advances uniformly:
   samples taken uniformly in time have protophase density ``ρ(θ) ∝ 1/θ̇``, and a phase
   with ``ψ̇`` constant has ``dψ/dθ = 2π ρ(θ)``; with ``S_k = <e^{-ikθ}>`` averaged over
   the record this integrates to ``P(θ) = Σ_{k≤K} 2 Re(S_k e^{ikθ} / (ik))``
   (:func:`correction_series`);
3. the corrected channel phases, which differ by constant offsets, are combined through the
   leading principal component of their unit phasors ``e^{iψ_c}`` (the Hermitian ``C x C``
   coherence matrix), which also down-weights incoherent (noisy) channels;
4. the combined phase is corrected once more as in 2;
5. a Poincaré-section offset fixes phase 0 (see :func:`estimate_phase`).

Two refinements over a plain implementation matter at the 1e-3 rad level. Averages (channel
means, the ``S_k``) are taken over a whole number of cycles, since a trailing partial cycle
biases them by ``O(1/cycles)``. And because an FFT Hilbert transform treats the record as
periodic, which makes it wrong by ~0.1-1 rad within a cycle of either end, a first pass
measures the period and the second pass appends a periodic continuation of the cycle that
leads from the record's end back into its start, so the transform sees no seam.
Step 3 is a variant of Phaser's PCA step (which projects ``(cos ψ_c, sin ψ_c)`` on two real
principal components); it needs no choice of sign or rotation direction.
"""

from __future__ import annotations

import math

import torch
from torch import Tensor

from .. import _checks
from .fourier import FourierSeries, fit_fourier, fourier_design
from .smoothing import unwrap

__all__ = [
    "analytic_signal",
    "protophase",
    "correction_series",
    "whole_cycle_weights",
    "estimate_phase",
    "hilbert_phase_pc1",
    "circular_rms",
]

# channels whose standard deviation is below this fraction of their magnitude are constant
_CONST_TOL = 1e-10


def analytic_signal(x: Tensor, dim: int = -1) -> Tensor:
    """Analytic signal ``x + i H[x]`` along ``dim`` via the FFT (complex, same shape)."""
    n = x.shape[dim]
    h = torch.zeros(n, dtype=x.dtype, device=x.device)
    h[0] = 1.0
    h[1 : (n + 1) // 2] = 2.0
    if n % 2 == 0:
        h[n // 2] = 1.0
    shape = [1] * x.ndim
    shape[dim] = n
    return torch.fft.ifft(torch.fft.fft(x, dim=dim) * h.reshape(shape), dim=dim)


def protophase(x: Tensor) -> Tensor:
    """Wrapped Hilbert protophase of every channel of ``x (..., T, C)`` -> ``(..., T, C)``."""
    z = x - x.mean(-2, keepdim=True)
    return torch.angle(analytic_signal(z, dim=-2))


def correction_series(theta: Tensor, order: int, weights: Tensor | None = None) -> FourierSeries:
    """Phaser's series correction ``P`` with ``θ + P(θ)`` advancing uniformly on average.

    Args:
        theta: protophases ``(..., T)`` (wrapped or not) of samples taken uniformly in time.
        order: number of harmonics ``K`` kept (0 gives no correction).
        weights: optional ``(..., T)`` sample weights for the averages ``S_k = <e^{-ikθ}>``.
            Averaging over a whole number of cycles (see :func:`whole_cycle_weights`) avoids
            the ``O(1 / cycles)`` bias a trailing partial cycle puts into every ``S_k``.

    Returns:
        scalar :class:`~torchconn.phase.fourier.FourierSeries` of order ``K``, batch ``(...)``.
    """
    if weights is None:
        weights = torch.ones_like(theta)
    w = weights / weights.sum(-1, keepdim=True)
    # [1, c_1, s_1, ...] = <cos kθ>, <sin kθ>: the design matrix averaged over the record
    cs = (w[..., None, :] @ fourier_design(theta, order))[..., 0, :]
    # dψ/dθ - 1 = 2 Σ (c_k cos kθ + s_k sin kθ), a zero-mean series; P is its antiderivative
    rate = torch.cat([torch.zeros_like(cs[..., :1]), 2 * cs[..., 1:]], -1)
    return FourierSeries(rate, 0).integral()


def whole_cycle_weights(theta: Tensor) -> Tensor:
    """Weights selecting a whole number of cycles of an unwrapped phase ``(..., T)``.

    The window is centred in the record and spans ``floor(cycles)`` cycles of ``theta``; each
    sample weighs the fraction of its sampling cell ``[t, t+1)`` inside the window, so the
    weighted mean of a periodic function of ``theta`` is its cycle average.
    """
    T = theta.shape[-1]
    mono = torch.cummax(theta, dim=-1).values  # tolerate small backward steps of noisy phases
    total = (mono[..., -1] - mono[..., 0]) / (2 * math.pi)
    n = total.floor().clamp_min(1.0)
    start = mono[..., 0] + math.pi * (total - n).clamp_min(0.0)
    levels = torch.stack([start, start + 2 * math.pi * n], -1)  # (..., 2)
    a, b = _crossing(mono, levels).unbind(-1)
    t = torch.arange(T, dtype=theta.dtype, device=theta.device)
    cell = torch.minimum(t + 1, b[..., None]) - torch.maximum(t, a[..., None])
    return cell.clamp(0.0, 1.0)


def _crossing(mono: Tensor, levels: Tensor) -> Tensor:
    """Fractional sample positions where non-decreasing ``mono (..., T)`` reaches ``levels``."""
    T = mono.shape[-1]
    i = torch.searchsorted(mono.contiguous(), levels.contiguous()).clamp(1, T - 1)
    lo, hi = mono.gather(-1, i - 1), mono.gather(-1, i)
    frac = ((levels - lo) / (hi - lo).clamp_min(1e-300)).clamp(0.0, 1.0)
    return (i - 1).to(mono.dtype) + frac


def circular_rms(estimate: Tensor, truth: Tensor, dim: int = -1) -> Tensor:
    """RMS of the wrapped difference ``estimate - truth`` after removing its circular mean.

    The natural error of a phase estimate, which is only defined up to a constant offset.
    Shapes broadcast; the mean is taken over ``dim``.
    """
    d = estimate - truth
    off = torch.angle(torch.exp(1j * d).mean(dim, keepdim=True))
    w = torch.remainder(d - off + math.pi, 2 * math.pi) - math.pi
    return w.pow(2).mean(dim).sqrt()


def hilbert_phase_pc1(x: Tensor) -> Tensor:
    """Naive baseline: unwrapped Hilbert phase of the first principal component.

    Args:
        x: ``(..., T, C)``.

    Returns:
        ``(..., T)`` unwrapped phase (no correction, no edge treatment, arbitrary offset).
    """
    _check_x(x, "hilbert_phase_pc1")
    xc = x - x.mean(-2, keepdim=True)
    _, vec = torch.linalg.eigh(xc.mT @ xc)
    pc1 = (xc @ vec[..., -1:])[..., 0]
    return unwrap(torch.angle(analytic_signal(pc1, dim=-1)))


def estimate_phase(
    x: Tensor,
    *,
    order: int = 3,
    min_cycles: float = 3.0,
    section_channel: int = 0,
    periodic_padding: bool = True,
) -> Tensor:
    """Phaser phase estimate of a multichannel oscillator record.

    Args:
        x: ``(..., T, C)`` samples, uniform in time, ``C >= 1`` channels (e.g. shapes ``r``),
            no NaNs (smooth/fill drop-outs first, e.g. with :func:`torchconn.phase.smoothing.rts_smooth`).
        order: harmonics in each series correction. 2-4 is robust; high orders fit the noise
            in the protophase (see tests).
        min_cycles: fewest cycles accepted; fewer make the correction unreliable.
        section_channel: channel that defines phase 0 (below).
        periodic_padding: extend the record by its periodic continuation before the Hilbert
            transform (reduces end effects); False gives the plain FFT transform.

    Phase 0 (the Poincaré section): the offset is chosen so that the first-harmonic component
    of channel ``section_channel`` is ``A sin(φ)`` with ``A > 0``, i.e. it crosses its mean
    upwards at ``φ = 0 (mod 2π)``. For a near-sinusoidal channel this is where the centred
    signal crosses zero upwards, and it is the same place on the cycle in every trial.

    Returns:
        ``(..., T)`` unwrapped phase in radians, increasing on average by 2π per cycle.

    Raises:
        ValueError: wrong shape; NaN anywhere (a channel that is all NaN is named); a constant
            channel (named); fewer than ``min_cycles`` cycles; a section channel without a
            first harmonic.
    """
    _check_x(x, "estimate_phase")
    _checks.integer(order, "order", fn="estimate_phase")
    C = x.shape[-1]
    if not -C <= section_channel < C:
        raise ValueError(
            f"estimate_phase: section_channel={section_channel} is out of range for C={C} channels"
        )
    if not x.is_floating_point():
        x = x.to(torch.get_default_dtype())
    _check_values(x)

    # pass 1 counts cycles and finds the period; pass 2 re-centres each channel on a whole
    # number of cycles (a partial cycle biases the mean by O(1/cycles)) and pads periodically
    z = (x - x.mean(-2, keepdim=True)) / x.std(-2, keepdim=True)
    phase = _phaser(z, order, None)
    span = phase[..., -1] - phase[..., 0]
    cycles = span / (2 * math.pi)
    if bool((cycles < min_cycles).any()):
        where = torch.nonzero(cycles < min_cycles)[0].tolist()
        raise ValueError(
            f"estimate_phase: x covers only about {float(cycles.min()):.1f} cycles (batch index "
            f"{tuple(where)}), fewer than min_cycles={min_cycles}; the phase correction needs "
            "several cycles -- record longer trials"
        )
    per_cycle = float((x.shape[-2] - 1) / cycles.max())
    if 2 * order >= per_cycle:
        raise ValueError(
            f"estimate_phase: order={order} is too high for ~{per_cycle:.0f} samples per cycle "
            "(harmonics alias above half of it); use a small order such as 3"
        )
    w = whole_cycle_weights(phase)[..., None]
    mean = (w * x).sum(-2, keepdim=True) / w.sum(-2, keepdim=True)
    z = (x - mean) / x.std(-2, keepdim=True)
    period = _period(phase) if periodic_padding else None
    phase = _phaser(z, order, period)

    # Poincaré section: rotate so the section channel's fundamental is A sin(φ), A > 0
    fund = fit_fourier(phase, z[..., section_channel], 1).coeffs  # (..., 3): a0, a1, b1
    amp = torch.hypot(fund[..., 1], fund[..., 2])
    if bool((amp < 0.1).any()):
        raise ValueError(
            f"estimate_phase: channel {section_channel} has almost no first harmonic (amplitude "
            f"{float(amp.min()):.2g} of its std), so it cannot define phase 0; pass another "
            "section_channel"
        )
    offset = torch.atan2(-fund[..., 1], fund[..., 2])
    return phase - offset[..., None]


def _phaser(z: Tensor, order: int, period: Tensor | None) -> Tensor:
    """Phaser steps 1-4 on centred, scaled ``z (..., T, C)`` -> unwrapped phase ``(..., T)``."""
    T = z.shape[-2]
    if period is None:
        theta = torch.angle(analytic_signal(z, dim=-2))
    else:
        theta = torch.angle(analytic_signal(_periodic_pad(z, period), dim=-2)[..., :T, :])
    theta = theta.mT  # (..., C, T)
    w = whole_cycle_weights(unwrap(theta))
    psi = theta + correction_series(theta, order, w)(theta)
    u = torch.polar(torch.ones_like(psi), psi).mT  # (..., T, C) unit phasors
    # u_c ≈ e^{iφ} a_c with |a_c| = 1: the coherence uᴴu/T ≈ conj(a) aᵀ, whose top eigenvector
    # v ∝ conj(a) aligns the channels, so u v ∝ e^{iφ}
    _, vec = torch.linalg.eigh(u.mH @ u / T)
    combined = unwrap(torch.angle((u @ vec[..., -1:])[..., 0]))  # (..., T)
    w = whole_cycle_weights(combined)
    return combined + correction_series(combined, order, w)(combined)


def _period(phase: Tensor) -> Tensor:
    """Period in samples from the least-squares slope of ``phase (..., T)`` over its central
    80 % (the plain transform's phase is least reliable within a cycle of either end)."""
    T = phase.shape[-1]
    lo, hi = T // 10, T - T // 10
    t = torch.arange(lo, hi, dtype=phase.dtype, device=phase.device)
    t = t - t.mean()
    p = phase[..., lo:hi]
    slope = (p * t).sum(-1) / (t * t).sum()
    return 2 * math.pi / slope


def _periodic_pad(z: Tensor, period: Tensor) -> Tensor:
    """Append a periodic continuation that leads the record's end back into its start.

    ``z (..., T, C)``, ``period (...)`` in samples -> ``(..., 2T, C)``. Appended sample
    ``T + s`` (``s < L = T``) shows the cycle at virtual time ``τ(s) = T + s + δ h(s / L)``,
    where the smooth step ``h(u) = u - sin(2πu) / 2π`` (slope 0 at both ends) absorbs the
    ``|δ| <= P/2`` that makes ``τ(L)`` a whole number of periods: the padded signal then has
    continuous phase and frequency at the record's end and at the FFT's wrap-around to its
    start. The value at ``τ`` is read one or more periods earlier in the record, cross-fading
    (raised cosine) from the last cycles to the first, so each join looks like data from
    neighbouring cycles.
    """
    T = z.shape[-2]
    P = period.clamp(2.0, (T - 1) / 3.0)[..., None]
    # as long as the record (>= 3 periods): a length set by the data alone, not by the batch,
    # keeps each batch element's result independent of the others
    L = T
    s = torch.arange(L, dtype=z.dtype, device=z.device)
    u = s / L
    delta = torch.round((T + L) / P) * P - (T + L)
    tau = T + s + delta * (u - torch.sin(2 * math.pi * u) / (2 * math.pi))
    pos_end = tau - torch.ceil((tau - (T - 1)) / P) * P  # latest copy inside the record
    pos_start = tau - torch.floor(tau / P) * P  # copy in the first period
    w = 0.5 - 0.5 * torch.cos(math.pi * (s + 1) / (L + 1))
    ext = (1 - w[:, None]) * _interp(z, pos_end) + w[:, None] * _interp(z, pos_start)
    return torch.cat([z, ext], dim=-2)


def _interp(z: Tensor, pos: Tensor) -> Tensor:
    """Linear interpolation of ``z (..., T, C)`` at fractional sample positions ``(..., L)``."""
    T, C = z.shape[-2:]
    pos = pos.clamp(0, T - 1)
    i0 = pos.floor().long().clamp(max=T - 2)
    f = (pos - i0)[..., None]
    g0 = z.gather(-2, i0[..., None].expand(*i0.shape, C))
    g1 = z.gather(-2, (i0 + 1)[..., None].expand(*i0.shape, C))
    return g0 + f * (g1 - g0)


def _check_x(x: Tensor, fn: str) -> None:
    _checks.tensor(
        x, "x", "(..., T, C) with T >= 4 samples along axis -2 and C >= 1 channels along axis -1",
        fn=fn, valid=lambda t: t.ndim >= 2 and t.shape[-1] >= 1 and t.shape[-2] >= 4,
    )


def _check_values(x: Tensor) -> None:
    nan = torch.isnan(x)
    if bool(nan.any()):
        allnan = nan.all(-2)
        if bool(allnan.any()):
            where = _checks.first_index(allnan)
            raise ValueError(
                f"estimate_phase: channel {where[-1]} of x (batch index {where[:-1]}) is "
                "NaN at every sample; drop that channel"
            )
        raise ValueError(
            f"estimate_phase: x contains {int(nan.sum())} NaN samples; fill or smooth drop-outs "
            "first (torchconn.phase.smoothing.rts_smooth predicts through them)"
        )
    _checks.finite(x, "x", fn="estimate_phase")
    std = x.std(-2)
    flat = std <= _CONST_TOL * x.abs().amax(-2)
    if bool(flat.any()):
        where = _checks.first_index(flat)
        raise ValueError(
            f"estimate_phase: channel {where[-1]} of x (batch index {where[:-1]}) is "
            "constant and carries no phase; drop it"
        )
