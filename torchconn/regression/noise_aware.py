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
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass

import torch
from torch import Tensor

from ..physics import se2
from . import _wls
from .binning import BinIndex
from .connection import ConnectionFit, _blocks, _connection_fit

__all__ = ["NoiseEstimate", "estimate_noise", "interval_samples", "IntervalSamples",
           "eiv_correction", "noise_aware_regression"]

#: default frequency band (cycles per sample) of the noise fit: above the 6th harmonic of a gait
#: sampled at ≥ 60 samples per cycle, where the increments' spectrum is the process noise's
#: flat floor plus the measurement noise's ``4 sin²(πf) σ²``
NOISE_BAND = (0.1, 0.5)


@dataclass(frozen=True)
class NoiseEstimate:
    """Per-channel noise of recordings, from the spectrum of their increments.

    Attributes:
        measurement: ``(..., C)`` standard deviation of the white measurement noise
            (motion-capture noise ω).
        process: ``(..., C)`` the increments' process-noise floor per sample (the standard
            deviation of a one-sample increment of the driving noise: ``η √Δt`` for the paper's
            SDE, more where phase noise moves the gait).
        variance_se: ``(..., C)`` standard error of ``measurement²`` (from the spread of the
            periodogram about its fitted line).
    """

    measurement: Tensor
    process: Tensor
    variance_se: Tensor

    def pooled_variance(self, n_batch_dims: int, *, min_z: float = 2.0) -> Tensor:
        """Measurement variance ``(C,)``-shaped after averaging the leading ``n_batch_dims``
        dims (trials of one rig), set to 0 where it is not ``min_z`` standard errors above 0
        (clean data: the estimate is then only the periodogram's scatter)."""
        dims = tuple(range(n_batch_dims))
        var = self.measurement.square()
        count = math.prod(var.shape[:n_batch_dims])
        mean = var.mean(dims) if dims else var
        se = (self.variance_se.square().sum(dims).sqrt() / count) if dims else self.variance_se
        return torch.where(mean > min_z * se, mean, torch.zeros_like(mean))


def estimate_noise(x: Tensor, *, band: tuple[float, float] = NOISE_BAND,
                   angular: Tensor | None = None) -> NoiseEstimate:
    """Measurement noise of every channel of ``x (..., T, C)``, separated from process noise.

    The increments ``u_k = x_{k+1} − x_k`` of a signal driven by white process noise and
    observed with white measurement noise of variance ``σ²`` have the spectrum
    ``S(f) = q + 4 sin²(πf) σ²`` away from the signal's own harmonics (``f`` in cycles per
    sample): the process noise is flat, the measurement noise rises towards Nyquist. A
    least-squares line of the increments' periodogram against ``4 sin²(πf)`` over ``band``
    gives ``σ²`` (its slope) and ``q`` (its intercept). A plain variance of differences would
    count the process noise as measurement noise.

    Args:
        x: ``(..., T, C)`` recordings; NaN drop-outs allowed (their increments count as 0 and
            the periodogram is rescaled by the finite fraction).
        band: ``(f_lo, f_hi)`` frequencies fitted, ``0 < f_lo < f_hi ≤ 0.5``.
        angular: optional ``(C,)`` bool, channels whose increments are wrapped to ``(−π, π]``
            (a heading recorded wrapped).

    Returns:
        :class:`NoiseEstimate` with ``(..., C)`` standard deviations (clamped at 0).
    """
    if not isinstance(x, Tensor) or not x.is_floating_point() or x.ndim < 2:
        raise TypeError("estimate_noise: x must be a floating-point tensor (..., T, C)")
    lo, hi = band
    if not 0 < lo < hi <= 0.5:
        raise ValueError(f"estimate_noise: band must satisfy 0 < f_lo < f_hi <= 0.5 (cycles per "
                         f"sample), got {band!r}")
    n = x.shape[-2] - 1
    if n < 16:
        raise ValueError(f"estimate_noise: need at least 17 samples along T, got {n + 1}")
    u = torch.diff(x, dim=-2)
    if angular is not None:
        u = torch.where(angular.to(x.device), se2.wrap_angle(u), u)
    finite = torch.isfinite(u)
    frac = finite.to(x.dtype).mean(-2, keepdim=True).clamp_min(1e-12)
    u = torch.where(finite, u, 0.0)
    u = torch.where(finite, u - u.sum(-2, keepdim=True) / (frac * n), 0.0)
    power = torch.fft.rfft(u, dim=-2).abs().square() / (frac * n)  # (..., F, C)
    f = torch.fft.rfftfreq(n, dtype=x.dtype).to(x.device)
    keep = (f >= lo) & (f <= hi)
    if int(keep.sum()) < 4:
        raise ValueError(f"estimate_noise: the band {band} holds fewer than 4 frequencies of a "
                         f"{n + 1}-sample record")
    z = 4 * torch.sin(math.pi * f[keep]).square()  # (F',)
    p = power[..., keep, :]
    zc = z - z.mean()
    sxx = zc.square().sum()
    slope = (zc[:, None] * p).sum(-2) / sxx
    intercept = p.mean(-2) - slope * z.mean()
    resid = p - intercept.unsqueeze(-2) - slope.unsqueeze(-2) * z[:, None]
    slope_se = (resid.square().sum(-2) / ((z.numel() - 2) * sxx)).sqrt()
    return NoiseEstimate(measurement=slope.clamp_min(0).sqrt(),
                         process=intercept.clamp_min(0).sqrt(), variance_se=slope_se)


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
        :class:`~torchconn.regression.ConnectionFit`; its standard errors are inflated by
        ``√h`` for the overlap of consecutive intervals (each noise sample enters ``2`` of the
        ``h`` overlapping differences around it, so the rows are not independent).
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
    m = s.n_bins
    var_bins = var.unsqueeze(-2).expand(batch + (m, d)).reshape(-1, d)
    span = samples.h * samples.dt
    var_delta, var_rate = var_bins / 2, 2 * var_bins / span**2

    def correction(gram: Tensor, sel) -> Tensor:
        return eiv_correction(gram, var_delta[sel], var_rate[sel])

    p = 1 + 2 * d + d * d
    sol = _wls.solve(s, _blocks, p, fn=fn, delta_max=delta_max, ridge=ridge, min_samples=None,
                     max_condition=None, on_ill_conditioned=on_ill_conditioned,
                     correction=correction)
    sol = sol.unflatten(s.batch_shape, m)
    # overlapping intervals: rows are not independent (see Returns)
    return _connection_fit(dataclasses.replace(sol, se=sol.se * math.sqrt(samples.h)), d)
