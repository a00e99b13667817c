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
from .binning import assign_bins
from .connection import connection_regression
from .metric import metric_n_coef, metric_regression
from .model import BinEstimates, LocalConnectionModel

__all__ = ["EstimatorSettings", "ConnectionEstimator", "prepare", "fit_local_model"]


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
              "window": window, "metric_window": metric_window,
              "tube_rms": _tube_rms(r, cycle.gamma_at(phase))},
    )


def _tube_rms(r: Tensor, gamma: Tensor) -> list[float]:
    """Per-joint RMS of the offsets ``δ = r − γ(φ)`` over every sample of every trial: the
    width of the tube the data covered (``(d,)`` as a list, for the JSON-able ``meta``)."""
    delta = (r - gamma).reshape(-1, r.shape[-1])
    return [float(v) for v in delta.pow(2).nanmean(0).sqrt()]


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
    - ``model_``: the :class:`~torchconn.regression.model.LocalConnectionModel`.

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
        self.model_ = fit_local_model(traj, cycle, s)
        return self

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
