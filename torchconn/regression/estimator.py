"""The estimator: recordings in, a local connection model out (the paper's Sec. 4).

Three pure, batched steps, each usable on its own, and a scikit-learn style wrapper:

1. :func:`prepare` -- smooth poses and shapes (Kalman/RTS), derive body velocities, and
   estimate the phase (Phaser) unless one is supplied; adds ``smoothed`` and ``phase`` to the
   :class:`~torchconn.trajectory.Trajectory`.
2. :func:`fit_limit_cycle` (:mod:`torchconn.phase.limit_cycle`) -- the self-consistent cycle γ(φ).
3. :func:`fit_local_model` -- the tube regressions in M phase bins (eq. ``advancedregression``
   and, with power, ``advancedmetricregression``) and their Fourier series in phase.

:class:`ConnectionEstimator` strings them together: ``ConnectionEstimator(n_bins=16).fit(traj)``.
"""

from __future__ import annotations

import dataclasses
import math
import warnings
from dataclasses import asdict, dataclass, fields

import torch
from torch import Tensor

from ..phase.fourier import fit_fourier
from ..phase.limit_cycle import LimitCycle, fit_limit_cycle, phase_rate
from ..phase.phaser import estimate_phase
from ..phase.smoothing import smooth_trajectory
from ..trajectory import SmoothedState, Trajectory
from ._wls import IllConditionedBinWarning
from .binning import assign_bins
from .connection import connection_regression
from .metric import metric_n_coef, metric_regression
from .model import BinEstimates, LocalConnectionModel
from .noise_aware import (
    IntervalSamples,
    estimate_noise,
    interval_samples,
    noise_aware_regression,
)

__all__ = ["EstimatorSettings", "ConnectionEstimator", "prepare", "fit_local_model",
           "REGRESSIONS", "Skill", "PoorHeldOutSkillWarning", "ComplexityChoice",
           "COMPLEXITY_GRID", "RIDGE_GRID"]


#: (n_bins, fourier_order) candidates of complexity="cv", simplest first
COMPLEXITY_GRID = ((12, 3), (24, 6), (48, 12))
#: ridge candidates of complexity="cv" (relative to the standardised normal matrix)
RIDGE_GRID = (0.0, 0.1, 1.0, 10.0)


@dataclass(frozen=True)
class ComplexityChoice:
    """What ``complexity="cv"`` chose, and every candidate's mean held-out ``SSE/SST``."""

    n_bins: int
    fourier_order: int
    ridge: float
    scores: tuple[dict, ...]


class PoorHeldOutSkillWarning(UserWarning):
    """The fitted model predicted held-out cycles worse than their phase-averaged velocity."""


@dataclass(frozen=True)
class Skill:
    """Skill of predicted body velocities per component ``(v_x, v_y, ω)``: ``R² = 1 − SSE/SST``
    against the observed velocity the regression sees (its target), beside two baselines.

    Attributes:
        r2: ``(..., 3)`` the fitted model ``ĉ + b̂δ + Âδ̇ + ∂Â/∂r (δ̇⊗δ)``.
        r2_phase_average: ``(..., 3)`` the phase-averaged velocity of the training data (a
            Fourier series in phase of the observed velocity, ignoring the shape).
        r2_template: ``(..., 3)`` the template ``ĉ(φ) = Â(γ)γ̇`` (the model on the cycle).
        n_samples: ``(...)`` samples scored.
    """

    r2: Tensor
    r2_phase_average: Tensor
    r2_template: Tensor
    n_samples: Tensor

    @property
    def worse_than_phase_average(self) -> Tensor:
        """``(..., 3)`` True where the model loses to a phase-averaged baseline that has skill
        (``R² > 0``)."""
        return (self.r2 < self.r2_phase_average) & (self.r2_phase_average > 0)

#: the connection regressions :class:`EstimatorSettings` offers
REGRESSIONS = ("noise_aware", "smoothed")


@dataclass(frozen=True, kw_only=True)
class EstimatorSettings:
    """Every knob of the estimator, with the defaults used throughout torchconn.

    Attributes:
        n_bins: phase bins M (regression centres φ_m = 2πm/M).
        fourier_order: order of the Fourier series interpolating the per-bin estimates
            (at most (M−1)/2). ``A(γ(φ))`` is nonlinear in the gait, so it carries harmonics
            well above the gait's own; a low order biases the model.
        window: half-width of a bin's phase window in units of the bin spacing (0.5: each
            sample in exactly one bin; larger: overlapping windows, more samples per bin).
            None (default) sizes it from the data: wide enough that a window holds about
            ``samples_per_regressor`` samples per regressor, and at least 1.
        samples_per_regressor: the data-size rule behind ``window=None``.
        kernel: sample weights within a window, ``"box"`` or ``"tricube"`` (weights fall
            smoothly to zero at the window's edge, which lowers the bias from the gait's
            curvature within a window).
        delta_max: only samples with ``|δ| < delta_max`` enter a bin's regression (None: all).
        ridge: Tikhonov penalty on the scaled regressors (0: ordinary least squares).
        on_ill_conditioned: ``"raise"`` | ``"warn"`` | ``"ridge"`` for bins with too few samples
            or a rank-deficient design.
        phase_order: Phaser's correction order (2-4 robust).
        cycle_order: Fourier order of the limit cycle γ(φ).
        smoother_order: Kalman smoother model order (2: white acceleration).
        min_cycles: fewest cycles a trial must cover.
        metric: also estimate the metric when the data carry power.
        pool: fit one model to all trials together (their phases must share a Poincaré section,
            which Phaser's phase 0 provides) instead of one model per trial.
        regression: how the connection is regressed. ``"noise_aware"`` (default): body and
            shape velocities from raw differences of the recordings over ``velocity_interval``
            samples, the joint angles' measurement noise estimated from the data and its
            contribution to the normal equations removed
            (:mod:`torchconn.regression.noise_aware`); the smoothed state serves only the
            phase and the limit cycle. ``"smoothed"``: the Kalman smoother's velocities (the
            method before issue 12); under motion-capture noise its Â shrinks towards 0,
            because the smoother treats the pose channels, the target, differently from the
            shapes (``benchmarks/accuracy.py`` compares the two).
        velocity_interval: samples per difference of the ``"noise_aware"`` regression; None
            chooses it from the data's noise (:func:`velocity_interval_for`). With
            ``window=None`` that regression also widens its bins with the noise.
        noise_band: frequency band ``(f_lo, 0.5)`` (cycles per sample) of the noise estimate;
            None: from the 6th harmonic of the gait up (``f_lo = 6 / samples per cycle``,
            within [0.1, 0.3]).
        complexity: ``"cv"``: ``n_bins``, ``fourier_order`` and ``ridge`` chosen among
            :data:`COMPLEXITY_GRID` x :data:`RIDGE_GRID` by the held-out error over
            ``held_out_folds`` (at least 2) blocks of whole cycles (``complexity_`` records the
            choice and every candidate's score; ~3-7x the time of one fit). ``"fixed"``:
            ``n_bins``, ``fourier_order`` and ``ridge`` as given. None (default): ``"cv"``
            unless one of the three was set away from its default.
        held_out_folds: after fitting, refit on all but one of this many blocks of whole
            cycles and score the held-out block against the baselines of :class:`Skill`
            (``held_out_skill_``); warn when the model loses to the phase-averaged velocity.
            0 skips the check.
    """

    n_bins: int = 48
    fourier_order: int = 12
    window: float | None = None
    samples_per_regressor: float = 2.5
    kernel: str = "tricube"
    delta_max: float | None = None
    ridge: float = 0.0
    on_ill_conditioned: str = "raise"
    phase_order: int = 3
    cycle_order: int = 8
    smoother_order: int = 2
    min_cycles: float = 3.0
    metric: bool = True
    pool: bool = False
    regression: str = "noise_aware"
    velocity_interval: int | None = None
    noise_band: tuple[float, float] | None = None
    complexity: str | None = None
    held_out_folds: int = 3

    @property
    def complexity_mode(self) -> str:
        """``"cv"`` or ``"fixed"``: :attr:`complexity` with None resolved."""
        if self.complexity is not None:
            return self.complexity
        given = (self.n_bins, self.fourier_order, self.ridge) != (48, 12, 0.0)
        return "fixed" if given else "cv"

    def __post_init__(self) -> None:
        if not isinstance(self.n_bins, int) or self.n_bins < 3:
            raise ValueError(f"n_bins must be an integer >= 3, got {self.n_bins!r}")
        if not isinstance(self.fourier_order, int) or not 0 <= 2 * self.fourier_order < self.n_bins:
            raise ValueError(
                f"fourier_order must satisfy 0 <= 2*fourier_order < n_bins={self.n_bins} (the "
                f"series is fitted to one value per bin), got {self.fourier_order!r}"
            )
        if self.window is not None and self.window <= 0:
            raise ValueError(f"window must be positive or None (auto), got {self.window!r}")
        if self.regression not in REGRESSIONS:
            raise ValueError(f"regression must be one of {REGRESSIONS}, got {self.regression!r}")
        if (isinstance(self.held_out_folds, bool) or not isinstance(self.held_out_folds, int)
                or self.held_out_folds == 1 or self.held_out_folds < 0):
            raise ValueError(f"held_out_folds must be 0 (no check) or an integer >= 2, got "
                             f"{self.held_out_folds!r}")
        if self.complexity not in ("fixed", "cv", None):
            raise ValueError(f"complexity must be 'fixed', 'cv' or None, got {self.complexity!r}")
        if self.complexity_mode == "cv" and self.held_out_folds < 2:
            raise ValueError("complexity='cv' needs held_out_folds >= 2 (the blocks of cycles "
                             f"it validates on), got {self.held_out_folds!r}")
        h = self.velocity_interval
        if h is not None and (isinstance(h, bool) or not isinstance(h, int) or h < 1):
            raise ValueError(f"velocity_interval must be a positive integer (samples) or None "
                             f"(chosen from the data), got {h!r}")


def prepare(
    traj: Trajectory,
    *,
    phase: Tensor | None = None,
    phase_order: int = 3,
    smoother_order: int = 2,
    min_cycles: float = 3.0,
) -> Trajectory:
    """Add smoothed state and phase to a trajectory (steps that do not depend on the model).

    Args:
        traj: recordings ``(..., T, ·)``; NaN drop-outs allowed.
        phase: ``(..., T)`` phase to use instead of estimating one (a robot's gait clock, or the
            true phase of a simulation). An existing ``traj.phase`` is used likewise.
        phase_order, smoother_order, min_cycles: see :class:`EstimatorSettings`.

    Returns:
        the trajectory with ``smoothed`` and ``phase`` set.
    """
    recorded = _recorded_span(traj)  # (..., T): False on the NaN padding after a trial's end
    padded = not bool(recorded.all())
    if traj.smoothed is None:
        smoothed = smooth_trajectory(traj.pose, traj.r, traj.dt, order=smoother_order)
        if padded:  # the smoother extrapolates into the padding: those values mean nothing
            smoothed = SmoothedState(**{
                f.name: _blank(getattr(smoothed, f.name), recorded) for f in fields(smoothed)
            })
        traj = traj.with_fields(smoothed=smoothed)
    if phase is not None:
        traj = traj.with_fields(phase=phase)
    elif traj.phase is None:
        r = traj.smoothed.r
        if padded:
            traj = traj.with_fields(phase=_phase_per_trial(r, recorded, phase_order, min_cycles))
        else:
            traj = traj.with_fields(phase=estimate_phase(r, order=phase_order,
                                                         min_cycles=min_cycles))
    return traj


def _recorded_span(traj: Trajectory) -> Tensor:
    """``(..., T)`` True from the first to the last sample with any finite value per trial.

    Trials of different lengths share one time grid, the shorter ones padded with NaN rows; the
    padding is not a drop-out to smooth through but time that was never recorded.
    """
    finite = torch.isfinite(torch.cat([traj.pose, traj.r], -1)).any(-1)  # (..., T)
    idx = torch.arange(finite.shape[-1], device=finite.device)
    first = torch.where(finite, idx, finite.shape[-1]).min(-1, keepdim=True).values
    last = torch.where(finite, idx, -1).max(-1, keepdim=True).values
    return (idx >= first) & (idx <= last)


def _blank(x: Tensor, keep: Tensor) -> Tensor:
    """``x (..., T, C)`` with NaN where ``keep (..., T)`` is False."""
    return torch.where(keep[..., None], x, torch.full_like(x, float("nan")))


def _phase_per_trial(r: Tensor, recorded: Tensor, order: int, min_cycles: float) -> Tensor:
    """Phaser on each trial's recorded span (unequal lengths: one call per trial), NaN outside.

    Phase 0 is the same Poincaré section in every trial, so the phases are comparable.
    """
    flat_r, flat_ok = r.reshape(-1, *r.shape[-2:]), recorded.reshape(-1, recorded.shape[-1])
    out = torch.full(flat_ok.shape, float("nan"), dtype=r.dtype, device=r.device)
    for k in range(flat_r.shape[0]):
        span = torch.nonzero(flat_ok[k]).flatten()
        lo, hi = int(span[0]), int(span[-1]) + 1
        out[k, lo:hi] = estimate_phase(flat_r[k, lo:hi], order=order, min_cycles=min_cycles)
    return out.reshape(recorded.shape)


def fit_local_model(
    traj: Trajectory, cycle: LimitCycle, settings: EstimatorSettings = EstimatorSettings()
) -> LocalConnectionModel:
    """The tube regressions in every phase bin and their Fourier series in phase.

    Args:
        traj: a prepared trajectory (``smoothed`` and ``phase`` set), batch dims ``...``.
        cycle: its limit cycle (batch dims ``...``, or none when ``settings.pool``).
        settings: estimator settings.

    Returns:
        a :class:`LocalConnectionModel` with batch dims ``...`` (none when pooled).
    """
    if traj.smoothed is None or traj.phase is None:
        raise ValueError("fit_local_model needs a prepared trajectory: call prepare(traj) first")
    s = traj.smoothed
    phase, r, r_dot, xi, power = traj.phase, s.r, s.r_dot, s.xi, traj.power
    if settings.pool:
        phase, r, r_dot, xi = (_pool(x, k) for x, k in ((phase, 0), (r, 1), (r_dot, 1), (xi, 1)))
        power = None if power is None else _pool(power, 0)
    M = settings.n_bins
    centres = torch.arange(M, dtype=r.dtype, device=r.device) * (2 * math.pi / M)
    batch = phase.shape[:-1]
    gamma_m = cycle.gamma_at(centres.expand(batch + (M,)))
    gamma_dot_m = cycle.phase_rate[..., None, None] * cycle.gamma_dot_at(centres.expand(batch + (M,)))
    opts = dict(
        delta_max=settings.delta_max, ridge=settings.ridge,
        on_ill_conditioned=settings.on_ill_conditioned,
    )
    d = r.shape[-1]

    def bins_for(n_regressors: int):
        window = settings.window or _auto_window(phase, M, n_regressors,
                                                 settings.samples_per_regressor)
        return assign_bins(phase, M, window=window, kernel=settings.kernel), window

    noise_meta = {}
    if settings.regression == "noise_aware":
        fit, window, noise_meta = _noise_aware_fit(traj, settings, M, gamma_m, gamma_dot_m, opts)
    else:
        bins, window = bins_for(1 + 2 * d + d * d)
        fit = connection_regression(r, r_dot, xi, bins, gamma_m, gamma_dot_m, **opts)
    metric_fit, metric_window = None, None
    if settings.metric and power is not None:
        mbins, metric_window = bins_for(metric_n_coef(d, False))
        metric_fit = metric_regression(r, r_dot, power, mbins, gamma_m, gamma_dot_m,
                                       with_metric_derivative=False, **opts)

    estimates = BinEstimates(
        phase=centres, gamma=gamma_m, gamma_dot=gamma_dot_m,
        c=fit.c, b=fit.b, A=fit.A, dA=fit.dA,
        c_se=fit.se_c, b_se=fit.se_b, A_se=fit.se_A, dA_se=fit.se_dA,
        n_samples=fit.n_samples,
        M=None if metric_fit is None else metric_fit.M,
        M_se=None if metric_fit is None else metric_fit.se_M,
    )
    K = settings.fourier_order

    def series(values: Tensor, ndim: int):
        return fit_fourier(centres, values, K, value_ndim=ndim)

    return LocalConnectionModel(
        gamma=cycle.gamma, phase_rate=cycle.phase_rate,
        c=series(fit.c, 1), b=series(fit.b, 2), A=series(fit.A, 2), dA=series(fit.dA, 3),
        M=None if metric_fit is None else series(metric_fit.M, 2),
        bins=estimates,
        meta={"settings": asdict(settings), "dt": traj.dt, "batch_shape": list(batch),
              "window": window, "metric_window": metric_window, **noise_meta},
    )


def _noise_aware_fit(traj: Trajectory, settings: EstimatorSettings, n_bins: int,
                     gamma_m: Tensor, gamma_dot_m: Tensor, opts: dict):
    """The ``"noise_aware"`` connection regression of :func:`fit_local_model`.

    Unpooled batch elements may carry different noise (a sweep's noise levels), so each gets
    its own interval and window; elements that share both are regressed together (one call
    per distinct pair, not per trial).
    """
    d = traj.shape_dim
    var, ratio, h = _noise_setup(traj, settings)
    if settings.pool:
        view = _interval_view(traj, h, pool=True)
        window = settings.window or _noise_window(view.phase, n_bins, d, settings, float(ratio))
        bins = assign_bins(view.phase, n_bins, window=window, kernel=settings.kernel)
        samples = IntervalSamples(phase=view.phase, r=view.r, r_dot=view.r_dot, xi=view.xi,
                                  h=int(h), dt=float(traj.dt))
        fit = noise_aware_regression(samples, bins, gamma_m, gamma_dot_m, var, **opts)
        meta = {"velocity_interval": int(h), "noise_ratio": float(ratio),
                "noise_r": var.sqrt().tolist()}
        return fit, window, meta

    batch = tuple(traj.batch_shape)
    n, m = math.prod(batch), n_bins
    flat = _flatten_batch(traj)
    h_flat, ratio_flat = h.reshape(-1), ratio.reshape(-1)
    windows = torch.tensor([settings.window or _noise_window(
        flat.phase[b:b + 1], n_bins, d, settings, float(ratio_flat[b])) for b in range(n)],
        dtype=torch.float64)
    windows = torch.round(windows * 2) / 2  # half spacings: few distinct groups
    groups, inverse = torch.unique(torch.stack([h_flat.to(windows), windows], -1), dim=0,
                                   return_inverse=True)
    g_m = gamma_m.expand(batch + (m, d)).reshape(n, m, d)
    g_dot = gamma_dot_m.expand(batch + (m, d)).reshape(n, m, d)
    var_flat = var.reshape(n, d)
    parts = []
    for g, (hg, wg) in enumerate(groups.tolist()):
        idx = torch.nonzero(inverse == g).flatten()
        sub = _take(flat, idx)
        iv = interval_samples(sub.pose, sub.r, sub.phase, traj.dt, int(hg))
        bins = assign_bins(iv.phase, n_bins, window=wg, kernel=settings.kernel)
        parts.append((idx, noise_aware_regression(iv, bins, g_m[idx], g_dot[idx],
                                                  var_flat[idx], **opts)))
    meta = {"velocity_interval": h.tolist(), "noise_ratio": ratio.tolist(),
            "noise_r": var.sqrt().tolist(), "windows": windows.reshape(batch).tolist()}
    return _scatter_fits(parts, n, batch), float(windows.max()), meta


def _noise_window(phase: Tensor, n_bins: int, d: int, settings: EstimatorSettings,
                  ratio: float) -> float:
    """Bin half-width of the noise-aware regression: the data-size rule, widened with noise."""
    return max(_auto_window(phase, n_bins, 1 + 2 * d + d * d, settings.samples_per_regressor),
               min(1 + _WINDOW_PER_NOISE_RATIO * ratio, _MAX_NOISE_WINDOW))


def _flatten_batch(traj: Trajectory) -> Trajectory:
    """``pose, r, phase`` with the batch dims flattened to one: ``(B, T, ·)``."""
    T = traj.n_samples
    return Trajectory(t=traj.t, pose=traj.pose.reshape(-1, T, 3),
                      r=traj.r.reshape(-1, T, traj.shape_dim)).with_fields(
        phase=traj.phase.reshape(-1, T))


def _take(traj: Trajectory, idx: Tensor) -> Trajectory:
    """Batch elements ``idx`` of a flattened trajectory (pose, r, phase)."""
    return Trajectory(t=traj.t, pose=traj.pose[idx], r=traj.r[idx]).with_fields(
        phase=traj.phase[idx])


def _scatter_fits(parts, n: int, batch: tuple):
    """One fit ``(*batch, M, ·)`` from fits of subsets ``(len(idx), M, ·)`` of ``n`` elements."""
    first = parts[0][1]
    out = {}
    for f in fields(first):
        ref = getattr(first, f.name)
        if ref is None:
            out[f.name] = None
            continue
        full = ref.new_zeros((n,) + ref.shape[1:])
        for idx, fit in parts:
            full[idx] = getattr(fit, f.name)
        out[f.name] = full.reshape(batch + ref.shape[1:])
    return type(first)(**out)


def _interval_view(traj: Trajectory, h: Tensor, pool: bool = False) -> "RegressionView":
    """Interval samples ``(..., T − min h, ·)`` with a per-element interval ``h`` (a ``(...)``
    tensor, or a scalar); elements with a longer interval are padded with NaN at the end."""
    h = torch.as_tensor(h)
    if h.ndim == 0:
        iv = interval_samples(traj.pose, traj.r, traj.phase, traj.dt, int(h))
        view = RegressionView(iv.phase, iv.r, iv.r_dot, iv.xi)
    else:
        flat = _flatten_batch(traj)
        h_flat = h.reshape(-1)
        n = traj.n_samples - int(h_flat.min())
        out = None
        for hg in torch.unique(h_flat).tolist():
            idx = torch.nonzero(h_flat == hg).flatten()
            sub = _take(flat, idx)
            iv = interval_samples(sub.pose, sub.r, sub.phase, traj.dt, int(hg))
            vals = [iv.phase, iv.r, iv.r_dot, iv.xi]
            if out is None:
                out = [v.new_full((h_flat.numel(), n) + v.shape[2:], float("nan"))
                       for v in vals]
            for o, v in zip(out, vals, strict=True):
                o[idx, :v.shape[1]] = v
        batch = tuple(traj.batch_shape)
        view = RegressionView(*(o.reshape(batch + o.shape[1:]) for o in out))
    if pool:
        view = RegressionView(_pool(view.phase, 0), _pool(view.r, 1), _pool(view.r_dot, 1),
                              _pool(view.xi, 1))
    return view


def _noise_setup(traj: Trajectory, settings: EstimatorSettings):
    """Joint-angle noise variance ``(..., d)``, noise ratio and velocity interval ``(...)`` of
    the noise-aware regression (``(d,)`` and scalars when the fit pools the trials)."""
    per_cycle = 2 * math.pi / float(phase_rate(traj.phase, traj.dt).nanmean() * traj.dt)
    band = settings.noise_band or (min(max(6 / per_cycle, 0.1), 0.3), 0.5)
    noise = estimate_noise(traj.r, band=band)  # (..., d)
    n_pool = traj.phase.ndim - 1 if settings.pool else 0
    # one rig: when pooled, the trials share one noise level per joint
    var = noise.pooled_variance(n_pool)
    q2 = noise.process.square()
    q2 = q2.mean(tuple(range(n_pool))) if n_pool else q2
    ratio = noise_ratio(var, q2)
    if settings.velocity_interval:
        h = torch.full(ratio.shape, settings.velocity_interval, dtype=torch.long)
    else:
        h = velocity_interval_for(ratio, per_cycle)
    return var, ratio, h


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


def noise_ratio(var: Tensor, process_var: Tensor) -> Tensor:
    """``2σ²/q²`` ``(...)``: joint-angle measurement-noise variance of a one-sample difference
    over the process noise's (``(..., d)`` each), averaged over the joints (0 on clean data;
    ~0.6 for ω = 0.005 in the paper's SDE at Δt = 0.05)."""
    q2 = process_var.mean(-1)
    return torch.where(q2 > 0, 2 * var.mean(-1) / q2.clamp_min(1e-300), 0.0)


def velocity_interval_for(ratio: Tensor, samples_per_cycle: float) -> Tensor:
    """Samples per difference ``(...)`` of the noise-aware regression, from the noise ratio.

    Over ``h`` samples the process noise's variance grows as ``h`` and the measurement noise's
    stays, so ``h = ⌈ratio / _INTERVAL_NOISE_FRACTION⌉``, at least 1 and at most
    :data:`_MAX_INTERVAL_CYCLES` of a cycle.
    """
    longest = max(2, int(samples_per_cycle * _MAX_INTERVAL_CYCLES))
    return torch.ceil(ratio / _INTERVAL_NOISE_FRACTION).clamp(1, longest).long()


def _regression_view(traj: Trajectory, s: EstimatorSettings, h,
                     pool: bool | None = None) -> RegressionView:
    """Samples ``(..., N, ·)`` as the regression of ``s`` sees them (interval ``h``: an int or
    nested list / tensor of the batch shape)."""
    if s.regression == "noise_aware":
        view = _interval_view(traj, torch.as_tensor(h))
    else:
        sm = traj.smoothed
        view = RegressionView(traj.phase, sm.r, sm.r_dot, sm.xi)
    if s.pool if pool is None else pool:
        view = RegressionView(_pool(view.phase, 0), _pool(view.r, 1), _pool(view.r_dot, 1),
                              _pool(view.xi, 1))
    return view


def _cross_validate(traj: Trajectory, cycle: LimitCycle, s: EstimatorSettings,
                    h, n_folds: int) -> Skill:
    """Held-out :class:`Skill` of settings ``s`` over ``n_folds`` blocks of whole cycles."""
    s = dataclasses.replace(s, held_out_folds=0, complexity="fixed")
    view = _regression_view(traj, s, h)
    fold = _cycle_blocks(_regression_view(traj, s, h, pool=False).phase, n_folds)
    if s.pool:
        fold = _pool(fold, 0)
    phase_fold = _cycle_blocks(traj.phase, n_folds)
    sums = []
    for f in range(n_folds):
        # held-out samples leave the regression as drop-outs do: with a NaN phase
        train = traj.with_fields(phase=torch.where(phase_fold == f, torch.nan, traj.phase))
        model = fit_local_model(train, cycle, s)
        pa = fit_fourier(torch.where(fold != f, view.phase, torch.nan), view.xi,
                         s.fourier_order, value_ndim=1)
        sums.append(_skill_sums(model, pa, view, fold == f))
    return _skill_from_sums(*[sum(parts) for parts in zip(*sums, strict=True)])


@dataclass(frozen=True)
class RegressionView:
    """Samples as a connection regression sees them: ``phase (..., N)``, ``r, r_dot (..., N, d)``,
    ``xi (..., N, 3)``."""

    phase: Tensor
    r: Tensor
    r_dot: Tensor
    xi: Tensor


def _cycle_blocks(phase: Tensor, n_folds: int) -> Tensor:
    """``(..., N)`` block index in ``[0, n_folds)`` of contiguous whole cycles per trial
    (-1 where the phase is NaN)."""
    start = torch.nan_to_num(phase, nan=float("inf")).amin(-1, keepdim=True)
    cyc = torch.floor((phase - start) / (2 * math.pi))
    n_cyc = torch.nan_to_num(cyc, nan=-1.0).amax(-1, keepdim=True) + 1
    fold = torch.floor(cyc * n_folds / n_cyc)
    return torch.where(torch.isfinite(fold), fold, -1.0).long()


def _skill_sums(model: LocalConnectionModel, phase_average, view: RegressionView,
                mask: Tensor | None):
    """Sums over the scored samples: SSE of model, phase average, template; Σy, Σy², count."""
    ok = torch.isfinite(view.phase) & torch.isfinite(view.xi).all(-1)
    ok &= torch.isfinite(view.r).all(-1) & torch.isfinite(view.r_dot).all(-1)
    if mask is not None:
        ok &= mask
    phase = torch.where(ok, view.phase, 0.0)
    r = torch.where(ok[..., None], view.r, 0.0)
    r_dot = torch.where(ok[..., None], view.r_dot, 0.0)
    y = torch.where(ok[..., None], view.xi, 0.0)
    w = ok.to(y.dtype)[..., None]
    preds = (model.predict(phase, r, r_dot), phase_average(phase), model.c(phase))
    sse = [((y - p).square() * w).sum(-2) for p in preds]
    return (*sse, (y * w).sum(-2), (y.square() * w).sum(-2), w.sum(-2)[..., 0])


def _skill_from_sums(sse_model, sse_pa, sse_template, sy, syy, n) -> Skill:
    sst = syy - sy.square() / n[..., None]
    return Skill(r2=1 - sse_model / sst, r2_phase_average=1 - sse_pa / sst,
                 r2_template=1 - sse_template / sst, n_samples=n)


def _skill(model, phase_average, view: RegressionView, mask) -> Skill:
    return _skill_from_sums(*_skill_sums(model, phase_average, view, mask))


def _fmt(x: Tensor) -> str:
    flat = x.reshape(-1, 3)
    return "[" + ", ".join(f"{float(v):.2f}" for v in flat.min(0).values) + "]" + (
        " (worst trial)" if flat.shape[0] > 1 else "")


def _auto_window(phase: Tensor, n_bins: int, n_regressors: int, per_regressor: float) -> float:
    """Half-width (in bin spacings) holding ``per_regressor`` samples per regressor on average
    in the batch element with the fewest finite samples; at least 1, at most a quarter cycle
    (a window must stay local for the first-order model to hold)."""
    fewest = float(torch.isfinite(phase).sum(-1).min())
    per_spacing = fewest / n_bins
    # a tricube window of half-width w spacings carries the weight of ~1.2 w spacings
    window = per_regressor * n_regressors / (1.2 * per_spacing)
    return float(min(max(window, 1.0), n_bins / 4))


def _pool(x: Tensor, trailing: int) -> Tensor:
    """Flatten all batch dims into the sample axis: ``(..., T, *c) -> (N·T, *c)``."""
    return x.reshape((-1,) + tuple(x.shape[x.ndim - trailing:]))


class ConnectionEstimator:
    """Estimate a local connection (and metric) around the gait in recorded trials.

    scikit-learn manners: the constructor only stores settings (see
    :class:`EstimatorSettings` for each), :meth:`fit` returns ``self``, fitted attributes end
    in ``_``:

    - ``trajectory_``: the prepared :class:`~torchconn.trajectory.Trajectory` (smoothed, phase);
    - ``limit_cycle_``: the :class:`~torchconn.phase.limit_cycle.LimitCycle`;
    - ``model_``: the :class:`~torchconn.regression.model.LocalConnectionModel`;
    - ``settings_``: the settings it was fitted with (with ``complexity="cv"``, the chosen
      ``n_bins``, ``fourier_order`` and ``ridge``), and ``complexity_`` the choice;
    - ``phase_average_``: the training data's phase-averaged velocity (a baseline);
    - ``held_out_skill_``: :class:`Skill` on held-out blocks of cycles (None if skipped).

    Example::

        est = ConnectionEstimator(n_bins=48, fourier_order=12).fit(traj)
        xi_hat = est.predict(traj)             # (..., T, 3)
        A_on_cycle = est.model_.connection(phi)  # (..., P, 3, d)
    """

    def __init__(self, **settings):
        self.settings = EstimatorSettings(**settings)

    def fit(self, traj: Trajectory, phase: Tensor | None = None) -> "ConnectionEstimator":
        """Fit to recordings ``traj`` (batch dims ``...``: one model per trial unless pooled).

        Args:
            traj: a :class:`~torchconn.trajectory.Trajectory` (simulated, or read with
                :func:`torchconn.io.trajectory_files.read_csv`).
            phase: optional ``(..., T)`` phase to use instead of Phaser's estimate.
        """
        s = self.settings
        if not isinstance(traj, Trajectory):
            raise TypeError(f"traj must be a torchconn.Trajectory, got {type(traj).__name__}")
        if s.metric and traj.power is None:
            warnings.warn("no power channel in the data: the metric is not estimated", stacklevel=2)
        traj = self.prepare(traj, phase)
        # γ₀ from the recorded shapes (smoothing damps the gait's high harmonics), ω from the
        # smoothed velocities
        sm = traj.smoothed
        if s.pool:
            # one cycle for all trials: fit dr/dφ (each trial's ṙ over its own phase rate) and
            # keep the trials' mean rate
            rate = phase_rate(traj.phase, traj.dt)
            cycle = fit_limit_cycle(
                _pool(traj.phase, 0), _pool(traj.r, 1),
                _pool(sm.r_dot / rate[..., None, None], 1), order=s.cycle_order,
            )
            cycle = dataclasses.replace(cycle, phase_rate=rate.mean())
        else:
            cycle = fit_limit_cycle(traj.phase, traj.r, sm.r_dot, order=s.cycle_order,
                                    dt=traj.dt)
        self.trajectory_ = traj
        self.limit_cycle_ = cycle
        if s.complexity_mode == "cv":
            s = self._select_complexity(traj, cycle, s)
        self.settings_ = s  # the settings fitted with (complexity resolved)
        self.held_out_skill_ = None
        self.model_ = fit_local_model(traj, cycle, s)
        view = self._view(traj)
        self.phase_average_ = fit_fourier(view.phase, view.xi, s.fourier_order, value_ndim=1)
        if s.held_out_folds:
            self._check_held_out(s.held_out_folds)
        return self

    def _select_complexity(self, traj: Trajectory, cycle: LimitCycle,
                           s: EstimatorSettings) -> EstimatorSettings:
        """Settings with the bins, Fourier order and ridge of least held-out error."""
        h = _noise_setup(traj, s)[2] if s.regression == "noise_aware" else None
        scores, failed = [], []
        for n_bins, order in COMPLEXITY_GRID:
            for ridge in RIDGE_GRID:
                cand = dataclasses.replace(s, n_bins=n_bins, fourier_order=order, ridge=ridge,
                                           complexity="fixed")
                try:
                    with warnings.catch_warnings():
                        warnings.simplefilter("ignore", IllConditionedBinWarning)
                        skill = _cross_validate(traj, cycle, cand, h, s.held_out_folds)
                except ValueError as err:
                    failed.append(f"{n_bins} bins: {err}")
                    continue
                # mean over components (and trials) of the held-out SSE / SST
                loss = float((1 - skill.r2).mean())
                scores.append({"n_bins": n_bins, "fourier_order": order, "ridge": ridge,
                               "held_out_loss": loss})
        if not scores:
            raise ValueError("complexity='cv': no candidate could be fitted on "
                             f"{s.held_out_folds - 1} of {s.held_out_folds} blocks of cycles "
                             f"({failed[0]}); record more cycles or use complexity='fixed' "
                             "with fewer n_bins")
        best = min(scores, key=lambda row: row["held_out_loss"])
        self.complexity_ = ComplexityChoice(
            n_bins=best["n_bins"], fourier_order=best["fourier_order"], ridge=best["ridge"],
            scores=tuple(scores))
        return dataclasses.replace(s, n_bins=best["n_bins"], fourier_order=best["fourier_order"],
                                   ridge=best["ridge"], complexity="fixed")

    def _view(self, traj: Trajectory) -> RegressionView:
        """The samples as the regression sees them (pooled when the fit pools trials)."""
        return _regression_view(traj, self.settings_, self.model_.meta.get("velocity_interval"))

    def score(self, traj: Trajectory, phase: Tensor | None = None) -> Skill:
        """Skill on recordings ``traj`` that the fit did not see (see :class:`Skill`).

        The target is the observed body velocity the way the regression sees it (raw interval
        differences for ``"noise_aware"``, the smoothed velocity for ``"smoothed"``). The phase
        of ``traj`` is estimated afresh unless given.
        """
        self._fitted()
        view = self._view(self.prepare(traj, phase))
        return _skill(self.model_, self.phase_average_, view, None)

    def cross_validate(self, n_folds: int = 3) -> Skill:
        """Held-out skill on the training recordings: refit on all but one of ``n_folds``
        contiguous blocks of whole cycles (per trial) and score the block left out, for every
        block; the phase and limit cycle of the whole fit are kept (they carry little of the
        model's complexity)."""
        self._fitted()
        return _cross_validate(self.trajectory_, self.limit_cycle_, self.settings_,
                               self.model_.meta.get("velocity_interval"), n_folds)

    def _check_held_out(self, n_folds: int) -> None:
        try:
            with warnings.catch_warnings():
                warnings.simplefilter("ignore", IllConditionedBinWarning)
                skill = self.cross_validate(n_folds)
        except ValueError as err:
            self.held_out_skill_ = None
            warnings.warn(f"held-out check skipped: refitting on {n_folds - 1} of {n_folds} "
                          f"blocks of cycles failed ({err}); record more cycles or pass "
                          f"held_out_folds=0", PoorHeldOutSkillWarning, stacklevel=3)
            return
        self.held_out_skill_ = skill
        worse = skill.worse_than_phase_average
        if bool(worse.any()):
            names = [n for n, w in zip(("v_x", "v_y", "omega"), worse.reshape(-1, 3).any(0),
                                       strict=True) if w]
            warnings.warn(
                f"the model predicts held-out cycles worse than their phase-averaged velocity "
                f"for {', '.join(names)} (held-out R² {_fmt(skill.r2)} vs phase average "
                f"{_fmt(skill.r2_phase_average)}): it overfits this recording; use fewer "
                f"n_bins / a lower fourier_order / a wider window, or record more cycles",
                PoorHeldOutSkillWarning, stacklevel=3)

    def prepare(self, traj: Trajectory, phase: Tensor | None = None) -> Trajectory:
        """:func:`prepare` with this estimator's settings (smoothing, phase)."""
        s = self.settings
        return prepare(traj, phase=phase, phase_order=s.phase_order,
                       smoother_order=s.smoother_order, min_cycles=s.min_cycles)

    def predict(self, traj: Trajectory) -> Tensor:
        """Body velocity ``(..., T, 3)`` the fitted model predicts for (prepared) recordings.

        A trajectory without phase/smoothed state is prepared first with the fit's settings.
        """
        model = self._fitted()
        traj = self.prepare(traj)
        return model.predict(traj.phase, traj.smoothed.r, traj.smoothed.r_dot)

    def _fitted(self) -> LocalConnectionModel:
        if not hasattr(self, "model_"):
            raise RuntimeError("this ConnectionEstimator is not fitted yet: call fit(traj) first")
        return self.model_

    def __repr__(self) -> str:
        changed = {k: v for k, v in asdict(self.settings).items()
                   if v != getattr(EstimatorSettings(), k)}
        return "ConnectionEstimator(" + ", ".join(f"{k}={v!r}" for k, v in changed.items()) + ")"
