"""The gait as executed: a self-consistent limit cycle fitted to phased shape data.

Data-Driven Floquet Analysis (the paper's Sec. 3) fits two Fourier series in phase: ``γ₀(φ)``
to the shapes ``r`` and ``ω(φ)`` to the shape velocities ``ṙ``. They come from different noisy
data, so ``dγ₀/dφ ≠ ω`` in general. A matched filter combines them into one cycle ``γ``: for
each harmonic ``k >= 1`` and shape coordinate, ``γ``'s coefficients are the inverse-variance
weighted mean of ``γ₀``'s and of ``∫ω dφ``'s (``(a_k, b_k) -> (-b_k, a_k) / k``), with
variances ``σ_r²`` and ``σ_ṙ² / k²`` from the two fits' residuals (integration divides
harmonic ``k``'s noise by ``k``, so high harmonics lean on ``ω``). The mean comes from ``γ₀``.
"""

from __future__ import annotations

import abc
import dataclasses
import math
from dataclasses import dataclass

import torch
from torch import Tensor

from .. import _checks
from .._options import Options, option
from ..trajectory import Trajectory, over_spans, pool_batch
from .fourier import FourierSeries, fit_fourier

__all__ = ["CycleEstimator", "SelfConsistentCycle", "LimitCycle", "fit_limit_cycle", "phase_rate"]


@dataclass(frozen=True, eq=False)
class LimitCycle:
    """A fitted limit cycle, batched over leading dims ``...``.

    Attributes:
        gamma: self-consistent cycle ``γ(φ)``, values ``(d,)``.
        gamma0: direct fit to the shapes, ``γ₀(φ) ≈ r``.
        omega: fit to the shape velocities per unit phase, ``ω(φ) ≈ ṙ / φ̇``.
        phase_rate: ``(...)`` mean phase velocity ``φ̇`` used to turn ``dγ/dφ`` into a time
            derivative, in rad per unit of ``t`` (rad/s for recorded data; 1 on the
            simulations' clock, one cycle per 2π).
        gamma0_weight: ``(..., K, d)`` the matched filter's weight on ``γ₀`` for harmonic
            ``k = 1..K`` of each coordinate (``1 - weight`` is on ``∫ω``).
    """

    gamma: FourierSeries
    gamma0: FourierSeries
    omega: FourierSeries
    phase_rate: Tensor
    gamma0_weight: Tensor

    def gamma_at(self, phi: Tensor) -> Tensor:
        """``γ(φ)``: ``phi (..., P)`` -> ``(..., P, d)``."""
        return self.gamma(phi)

    def gamma_dot_at(self, phi: Tensor) -> Tensor:
        """``dγ/dφ``: ``phi (..., P)`` -> ``(..., P, d)``; on the cycle ``ṙ = φ̇ dγ/dφ``."""
        return self.gamma.derivative()(phi)

    def offsets(self, phase: Tensor, r: Tensor, r_dot: Tensor) -> tuple[Tensor, Tensor]:
        """Offsets from the cycle at the same phase.

        Args:
            phase: ``(..., T)``; r, r_dot: ``(..., T, d)``.

        Returns:
            ``(delta, delta_dot)``, both ``(..., T, d)``: ``δ = r - γ(φ)`` and
            ``δ̇ = ṙ - φ̇ dγ/dφ(φ)`` (``φ̇`` = :attr:`phase_rate`, 1 by convention).
        """
        _checks.phase_samples(phase, r, r_dot, fn="LimitCycle.offsets")
        delta = r - self.gamma_at(phase)
        delta_dot = r_dot - self.phase_rate[..., None, None] * self.gamma_dot_at(phase)
        return delta, delta_dot


class CycleEstimator(Options, abc.ABC):
    """Base of the estimator's cycle stage: ``fit(traj, pool=...) -> LimitCycle``."""

    @abc.abstractmethod
    def fit(self, traj: Trajectory, *, pool: bool = False) -> LimitCycle:
        """The cycle of a prepared trajectory (``phase`` and ``smoothed`` set).

        One cycle per batch element, or with ``pool`` one for all trials together.
        """


@dataclass(frozen=True, kw_only=True)
class SelfConsistentCycle(CycleEstimator):
    """The matched-filter cycle of :func:`fit_limit_cycle` as the estimator's cycle stage.

    ``γ₀`` is fitted to the recorded shapes (smoothing damps the gait's high harmonics), ``ω``
    to the smoothed shape velocities per unit phase.

    Attributes:
        order: harmonics of the cycle's Fourier series.
    """

    order: int = option(8, ge=1)

    def fit(self, traj: Trajectory, *, pool: bool = False) -> LimitCycle:
        if not isinstance(traj, Trajectory) or traj.phase is None or traj.smoothed is None:
            raise ValueError("SelfConsistentCycle.fit needs a trajectory with phase and smoothed "
                             "state (ConnectionEstimator.prepare adds them)")
        r_dot = traj.smoothed.r_dot
        if not pool:
            return fit_limit_cycle(traj.phase, traj.r, r_dot, order=self.order, dt=traj.dt)
        # one cycle for all trials: fit dr/dφ (each trial's ṙ over its own phase rate) and keep
        # the trials' mean rate
        rate = phase_rate(traj.phase, traj.dt)
        cycle = fit_limit_cycle(pool_batch(traj.phase, 0), pool_batch(traj.r, 1),
                                pool_batch(r_dot / rate[..., None, None], 1), order=self.order)
        return dataclasses.replace(cycle, phase_rate=rate.mean())


def fit_limit_cycle(
    phase: Tensor,
    r: Tensor,
    r_dot: Tensor,
    *,
    order: int = 5,
    dt: float | None = None,
) -> LimitCycle:
    """Fit ``γ₀``, ``ω`` and the self-consistent cycle ``γ`` to phased shape data.

    Args:
        phase: ``(..., T)`` phase of every sample (e.g. from
            :func:`torchconn.phase.phaser.estimate_phase`; wrapped or not).
        r: ``(..., T, d)`` shapes; r_dot: ``(..., T, d)`` shape velocities (``d/dt``).
            Samples with NaN in ``phase``, ``r`` or ``r_dot`` are ignored by both fits.
        order: harmonics of every series (the reference gaits use odd harmonics up to 5).
        dt: sampling interval. If given, the phase velocity ``φ̇`` is the least-squares slope
            of ``phase`` (which must then be unwrapped) against time per batch element
            (:func:`phase_rate`), and ``ω`` is fitted to ``ṙ / φ̇``; if None, ``φ̇ = 1`` (the
            simulations' clock: one cycle per 2π time units).

    Returns:
        :class:`LimitCycle`; each batch element gets its own cycle.
    """
    _checks.phase_samples(phase, r, r_dot, fn="fit_limit_cycle")
    dtype = torch.promote_types(torch.promote_types(phase.dtype, r.dtype), r_dot.dtype)
    phase, r, r_dot = phase.to(dtype), r.to(dtype), r_dot.to(dtype)
    if dt is None:
        rate = torch.ones(phase.shape[:-1], dtype=dtype, device=phase.device)
    else:
        rate = phase_rate(phase, float(dt))
    v = r_dot / rate[..., None, None]

    gamma0 = fit_fourier(phase, r, order)
    omega = fit_fourier(phase, v, order)
    k = torch.arange(1, order + 1, dtype=dtype, device=phase.device)[:, None]  # (K, 1)
    if dt is None:
        # white-residual model: a coefficient's variance is the residual variance
        var_r = _residual_variance(gamma0, phase, r)[..., None, :]  # (..., 1, d)
        var_v = _residual_variance(omega, phase, v)[..., None, :]
    else:
        # the residuals are coloured (the shape offset δ is an OU process, δ̇ its derivative):
        # a harmonic's coefficient is only disturbed by residual power near its frequency
        var_r = _residual_spectrum(gamma0, phase, r, rate, float(dt), order)  # (..., K, d)
        var_v = _residual_spectrum(omega, phase, v, rate, float(dt), order)

    # matched filter, per harmonic k and coordinate: weight on γ₀ = var(∫ω)/(var(γ₀)+var(∫ω))
    var_int = var_v / k**2  # (..., K, d)
    total = var_r + var_int
    w0 = torch.where(total > 0, var_int / total.clamp_min(1e-300), torch.full_like(total, 0.5))
    w = torch.repeat_interleave(w0, 2, dim=-2)  # (..., 2K, d): same weight for a_k and b_k
    integ = omega.integral(drop_mean=True).coeffs
    c0 = gamma0.coeffs
    harmonics = w * c0[..., 1:, :] + (1 - w) * integ[..., 1:, :]
    gamma = FourierSeries(torch.cat([c0[..., :1, :], harmonics], dim=-2), 1)
    return LimitCycle(gamma=gamma, gamma0=gamma0, omega=omega, phase_rate=rate, gamma0_weight=w0)


def _residual_variance(series: FourierSeries, phase: Tensor, y: Tensor) -> Tensor:
    """Per-coordinate residual variance ``(..., d)`` of a fit, ignoring NaN samples,
    corrected for the ``2K+1`` fitted coefficients."""
    res = y - series(phase)
    ok = torch.isfinite(res).all(-1, keepdim=True)
    n = ok.sum(-2).to(y.dtype)  # (..., 1)
    ss = torch.where(ok, res, torch.zeros_like(res)).pow(2).sum(-2)
    return ss / (n - (2 * series.order + 1)).clamp_min(1.0)


def _residual_spectrum(
    series: FourierSeries, phase: Tensor, y: Tensor, rate: Tensor, dt: float, order: int
) -> Tensor:
    """Residual power spectral density ``(..., K, d)`` near each harmonic's frequency.

    The periodogram of the residual time series (NaNs as zeros, rescaled by the count kept)
    is averaged over a band of ±0.3 harmonic spacings around ``k φ̇ / 2π`` cycles per time unit,
    each batch element over its own span (a shorter trial's padding on a shared grid would
    refine its periodogram's frequency grid).
    """
    res = y - series(phase)
    batch, (T, d) = res.shape[:-2], res.shape[-2:]
    flat, rates = res.reshape(-1, T, d), rate.expand(batch).reshape(-1)
    split = over_spans(torch.isfinite(flat).any(-1), lambda rows, a, b: _band_power(
        flat[rows, a:b], rates[rows], dt, order))
    return _band_power(res, rate, dt, order) if split is None else split.reshape(
        batch + (order, d))


def _band_power(res: Tensor, rate: Tensor, dt: float, order: int) -> Tensor:
    """:func:`_residual_spectrum` of residuals ``res (..., T, d)`` (NaN where missing) at the
    phase rates ``rate (...)``."""
    ok = torch.isfinite(res)
    res = torch.where(ok, res, torch.zeros_like(res))
    T = res.shape[-2]
    power = torch.fft.rfft(res, dim=-2).abs().pow(2) / ok.sum(-2, keepdim=True).clamp_min(1)
    freq = torch.fft.rfftfreq(T, d=dt, dtype=res.dtype, device=res.device)  # cycles / time
    spacing = rate / (2 * math.pi)  # (...) harmonic spacing in cycles / time
    k = torch.arange(1, order + 1, dtype=res.dtype, device=res.device)
    centre = k * spacing[..., None]  # (..., K)
    band = ((freq - centre[..., None]).abs() <= 0.3 * spacing[..., None, None]).to(res.dtype)
    return (band @ power) / band.sum(-1, keepdim=True).clamp_min(1)


def phase_rate(phase: Tensor, dt: float) -> Tensor:
    """Mean phase velocity ``φ̇``: least-squares slope of an unwrapped ``phase (..., T)``
    against time ``t = n dt``, ignoring NaN samples -> ``(...)``."""
    _checks.tensor(phase, "phase", "(..., T) with T >= 2", fn="phase_rate",
                   valid=lambda t: t.ndim >= 1 and t.shape[-1] >= 2)
    ok = torch.isfinite(phase)
    t = torch.arange(phase.shape[-1], dtype=phase.dtype, device=phase.device) * dt
    m = ok.to(phase.dtype)
    n = m.sum(-1, keepdim=True)
    p = torch.where(ok, phase, torch.zeros_like(phase))
    tc = (t - (m * t).sum(-1, keepdim=True) / n) * m
    return (tc * p).sum(-1) / (tc * tc).sum(-1)
