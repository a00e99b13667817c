"""Velocity filters over intervals of samples, and the noise they carry.

Target and regressors see the same linear filter over ``h`` samples and nothing else is
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
(``Σ a_j b_j = 0`` for every filter). Consecutive rows overlap, which inflates a bin's
coefficient variance (:func:`overlap_inflation`); :func:`velocity_interval_for` chooses ``h``
from the noise ratio (:func:`noise_ratio`).
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from typing import TYPE_CHECKING

import torch
from torch import Tensor, nn

from ..physics import se2
from ..trajectory import Trajectory, pool_batch
from .spectrum import KERNEL_CHUNK

if TYPE_CHECKING:
    from ..regression.binning import BinIndex

__all__ = ["VELOCITY_KERNELS", "VELOCITY_KERNEL", "MAX_INTERVAL_CYCLES", "interval_weights",
           "IntervalSamples", "interval_noise_gains", "interval_samples", "overlap_inflation",
           "noise_ratio", "velocity_interval_for", "flatten_batch",
           "intervals_by_h", "take_intervals", "pooled_view", "interval_view"]


#: shapes of the velocity filter over an interval (:func:`interval_weights`)
VELOCITY_KERNELS = ("box", "triangle")


#: the filter of :func:`interval_samples` (and so of
#: :class:`~torchconn.regression.noise_aware.NoiseAwareRegression`)
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
    at ``h = 8-24`` gives 2.4-7.
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


# ------------------------------------------------------------------------ the regression stage
#: the velocity interval is the shortest at which the joint-angle noise adds at most this
#: fraction of the process noise's variance to a filtered shape velocity
#: (:func:`velocity_interval_for`); the pooled fit then chooses between it and longer ones
_INTERVAL_NOISE_FRACTION = 0.05


#: longest velocity interval, as a fraction of a cycle
MAX_INTERVAL_CYCLES = 1 / 4


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
    :data:`MAX_INTERVAL_CYCLES` of a cycle (but never capped below 2).
    """
    per_cycle = torch.as_tensor(samples_per_cycle, dtype=torch.float64, device=ratio.device)
    longest = torch.floor(per_cycle * MAX_INTERVAL_CYCLES).clamp_min(2)
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


def flatten_batch(traj: Trajectory) -> Trajectory:
    """``pose, r, phase`` with the batch dims flattened to one: ``(B, T, ·)``."""
    T = traj.n_samples
    return Trajectory(t=traj.t, pose=traj.pose.reshape(-1, T, 3),
                      r=traj.r.reshape(-1, T, traj.shape_dim)).with_fields(
        phase=traj.phase.reshape(-1, T))


def intervals_by_h(flat: Trajectory, h: Tensor, dt: float, kernel: str = VELOCITY_KERNEL
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
        pad = -(T - hg) % KERNEL_CHUNK
        pose, r, phase = (nn.functional.pad(x, (0, 0, 0, pad) if x.ndim == 3 else (0, pad),
                                            value=float("nan"))
                          for x in (flat.pose, flat.r, flat.phase))
        iv = interval_samples(pose, r, phase, dt, hg, kernel)
        out[hg] = take_intervals(iv, slice(None), T - hg)
    return out


def take_intervals(iv: IntervalSamples, idx, n: int | None = None) -> IntervalSamples:
    """Batch elements ``idx`` (and the first ``n`` intervals) of flattened interval samples
    ``(n, N, ·)``."""
    return dataclasses.replace(iv, phase=iv.phase[idx, :n], r=iv.r[idx, :n],
                               r_dot=iv.r_dot[idx, :n], xi=iv.xi[idx, :n])


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
    flat = flatten_batch(traj)
    h_flat = h.reshape(-1)
    n = traj.n_samples - int(h_flat.min())
    out = None
    for hg, iv in intervals_by_h(flat, h_flat, traj.dt, kernel).items():
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
