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
           "interval_weights", "interval_noise_gains", "overlap_inflation",
           "eiv_correction", "noise_aware_regression", "blend_fits", "NoiseAwareRegression", "interval_view",
           "noise_ratio", "velocity_interval_for"]

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
    f = torch.fft.rfftfreq(n, dtype=x.dtype, device=x.device)
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
        :class:`~torchconn.regression.ConnectionFit`. The standard errors are the solver's
        (rows independent) times ``√κ`` for the rows' overlap (:func:`overlap_inflation`; 1
        for the box filter, whose errors measured 0.9-1.1 times its squared standard errors).
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
    g_delta, g_rate = samples.noise_gains()
    var_delta, var_rate = var_bins * g_delta, var_bins * g_rate

    def correction(gram: Tensor, sel) -> Tensor:
        return eiv_correction(gram, var_delta[sel], var_rate[sel])

    sol = _wls.solve(s, _blocks, p, fn=fn, delta_max=delta_max, ridge=ridge, min_samples=None,
                     max_condition=None, on_ill_conditioned=on_ill_conditioned,
                     correction=correction)
    kappa = overlap_inflation(bins, samples.h, samples.kernel).to(sol.se).reshape(-1, 1, 1)
    sol = dataclasses.replace(sol, se=sol.se * kappa.sqrt()).unflatten(s.batch_shape, m)
    return _connection_fit(sol, d)


# ------------------------------------------------------------------------ the regression stage
#: the velocity interval is the shortest at which the joint-angle noise adds at most this
#: fraction of the process noise's variance to a filtered shape velocity
#: (:func:`velocity_interval_for`); the pooled fit then chooses between it and longer ones
_INTERVAL_NOISE_FRACTION = 0.05
#: longest velocity interval, as a fraction of a cycle. The triangle filter's error grows
#: more slowly with the interval than the box's; seed 5 (pooled, ω = 0.01) chose 24-32 of 126
#: samples per cycle
_MAX_INTERVAL_CYCLES = 1 / 4
#: the pooled fit's candidate bin half-widths (bin spacings) and longer intervals (multiples
#: of the noise rule's), chosen among by estimated mean squared error (see
#: ``NoiseAwareRegression._chosen_fit``). Set on seeds 5 and 6 (3-/5-link circle, 3-link
#: reference, 5-link wave, ω = 0-0.01, pooled 4 x 30 cycles) against a grid of intervals
#: 2-32 and windows 1-4: the chosen fits' Â errors were 1.09 times the best of the grid's on
#: average (at most 1.45; the best at ω = 0), with 6 fits (all 12 pairs of these: 1.11; the
#: multiples 2 and 3 instead: 1.13); the strongly curved 3-link reference gait gets 2-3
#: spacings, circle gaits 3-4
_INTERVAL_MULTIPLES = (1.5, 2.0)
_CANDIDATE_WINDOWS = (1.0, 2.0, 3.0, 4.0)
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
            with the noise.
        noise_band_low: lowest frequency (cycles per sample) of the noise fit; None: the 6th
            harmonic of the gait (``6 / samples per cycle`` of each trial, rounded up to 0.01,
            within [0.1, 0.3]).
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
            fit, h, window, scores = self._chosen_fit(traj, var, int(h), gamma_m, gamma_dot_m,
                                                      opts)
            meta = {"velocity_interval": h, "noise_ratio": float(ratio),
                    "noise_r": var.sqrt().tolist(), "interval_window_scores": scores}
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

    def _chosen_fit(self, traj: Trajectory, var: Tensor, h0: int, gamma_m: Tensor,
                    gamma_dot_m: Tensor, opts: dict):
        """The pooled corrected fit at the velocity interval and bin width of least estimated
        mean squared error of ``Â``.

        Longer intervals and wider bins lower the variance and add bias (they average ``A``
        over more of the cycle). With the candidate of the shortest interval and narrowest bins
        (``0``, least bias) as the reference, ``MSE_c ≈ ‖Â_c − Â_0‖² − V_0 + 2 V_c`` (``V``
        the summed squared standard errors of ``Â``, calibrated for the rows' overlap by
        :func:`overlap_inflation`; for nested estimates ``E‖Â_c − Â_0‖²`` is the squared bias
        difference plus ``V_0 − V_c``) and ``MSE_0 = V_0``. The search is greedy: the
        half-widths :data:`_CANDIDATE_WINDOWS` (at least the data-size rule's) at the noise
        rule's interval ``h0`` (:func:`velocity_interval_for`), then the intervals
        ``h0 · _INTERVAL_MULTIPLES`` at the best of them; ``window`` or ``velocity_interval``,
        when given, fix theirs.

        Returns the fit, ``h``, the window and the candidates' ``[h, window, MSE]`` (a list).
        """
        d = traj.shape_dim
        longest = max(2, int(_samples_per_cycle(traj) * _MAX_INTERVAL_CYCLES))
        views, fits, scores, errors = {}, {}, {}, []

        def candidate(h: int, w: float | None) -> tuple[int, float]:
            if h not in views:
                view = interval_view(traj, h)
                views[h] = dataclasses.replace(
                    view, phase=pool_batch(view.phase, 0), r=pool_batch(view.r, 1),
                    r_dot=pool_batch(view.r_dot, 1), xi=pool_batch(view.xi, 1), h=h)
            if w is None:  # the narrowest the data allow
                w = _auto_window(views[h].phase, self.n_bins, 1 + 2 * d + d * d,
                                 self.samples_per_regressor)
            key = (h, float(w))
            if key not in scores:
                bins = assign_bins(views[h].phase, self.n_bins, window=key[1],
                                   kernel=self.kernel)
                try:
                    fit = noise_aware_regression(views[h], bins, gamma_m, gamma_dot_m, var,
                                                 **opts)
                except ValueError as err:  # bins too sparse at this width: not a candidate
                    errors.append(err)
                    scores[key] = math.inf
                    return key
                v = float(fit.se_A.square().nansum())
                if not fits:
                    scores[key] = v
                else:
                    ref = next(iter(fits.values()))
                    v_ref = scores[next(iter(fits))]
                    scores[key] = float((fit.A - ref.A).square().nansum()) - v_ref + 2 * v
                fits[key] = fit
            return key

        h0 = int(self.velocity_interval or h0)
        least = candidate(h0, self.window)[1]  # the reference
        widths = [least] if self.window else [max(least, w) for w in _CANDIDATE_WINDOWS]
        best = min((candidate(h0, w) for w in widths), key=scores.__getitem__)
        if not self.velocity_interval:
            for f in _INTERVAL_MULTIPLES:
                h = min(longest, max(1, round(h0 * f)), traj.n_samples - 1)
                key = candidate(h, best[1])
                best = min(best, key, key=scores.__getitem__)
        if best not in fits:  # no candidate could be fitted
            raise errors[0]
        table = [[h, w, sc] for (h, w), sc in scores.items() if math.isfinite(sc)]
        return fits[best], best[0], best[1], table

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
        noise band and the longest interval) come from its own phase rate, so a trial's fit
        does not depend on the trials it shares a batch with (a sweep's cells)."""
        per_cycle = 2 * math.pi / (phase_rate(traj.phase, traj.dt) * traj.dt)  # (...)
        if pool:
            per_cycle = per_cycle.nanmean()
        if self.noise_band_low:
            low = torch.full_like(per_cycle, self.noise_band_low)
        else:
            # the 6th harmonic, rounded up to 0.01 cycles per sample: few distinct bands
            low = (torch.ceil(600 / per_cycle) / 100).clamp(0.1, 0.3)
        noise = _estimate_noise_by_band(traj.r, low)  # (..., d)
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


def _estimate_noise_by_band(r: Tensor, low: Tensor) -> NoiseEstimate:
    """:func:`estimate_noise` of ``r (..., T, d)`` with each element's band ``(low, 0.5)``,
    ``low`` ``(...)`` (or one value for all): one call per distinct band."""
    if low.ndim == 0 or bool((low == low.reshape(-1)[0]).all()):
        return estimate_noise(r, band=(float(low.reshape(-1)[0]), 0.5))
    batch = r.shape[:-2]
    flat, low_flat = r.reshape((-1,) + r.shape[-2:]), low.expand(batch).reshape(-1)
    parts = {}
    for value in torch.unique(low_flat).tolist():
        idx = torch.nonzero(low_flat == value).flatten()
        parts[value] = (idx, estimate_noise(flat[idx], band=(value, 0.5)))
    out = {}
    for name in ("measurement", "process", "variance_se"):
        full = flat.new_zeros((flat.shape[0], r.shape[-1]))
        for idx, est in parts.values():
            full[idx] = getattr(est, name)
        out[name] = full.reshape(batch + (r.shape[-1],))
    return NoiseEstimate(**out)


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
                           dt=float(traj.dt), kernel=iv.kernel)
