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
