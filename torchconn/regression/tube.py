"""The estimator's regression stage: tube regressions in phase bins, then Fourier in phase.

:class:`TubeRegression` fits, in each of M phase bins, the first-order model of the body
velocity around the cycle (eq. ``advancedregression``, :func:`connection_regression`) and, when
the data carry power, the metric -- the tied, noise-corrected model of
:func:`~torchconn.regression.metric.tied_metric_regression` on the sample intervals of the raw
shapes -- and interpolates the per-bin estimates by Fourier series in phase into a
:class:`~torchconn.regression.model.LocalConnectionModel`. Other regression methods derive from
:class:`Regression` and slot into ``ConnectionEstimator(regression=…)``.
"""

from __future__ import annotations

import abc
import math
import warnings
from dataclasses import asdict, dataclass
from typing import Literal

import torch
from torch import Tensor, nn

from .._options import Options, option
from ..noise import estimate_noise, interval_samples
from ..phase.fourier import FourierSeries, fit_fourier
from ..phase.limit_cycle import LimitCycle
from ..phase.phaser import held_out_order, whole_cycle_weights
from ..phase.smoothing import recorded_span
from ..trajectory import Trajectory, over_spans, pool_batch, span_bounds
from .binning import assign_bins, auto_window
from .connection import connection_regression
from .metric import (
    power_noise_variance,
    tied_metric_coefficients,
    tied_metric_n_coef,
    tied_metric_predict,
)
from .model import BinEstimates, LocalConnectionModel

__all__ = ["Regression", "TubeRegression", "check_bin_count"]


def check_bin_count(n_bins: int, n_samples: int, where: str) -> None:
    """Refuse more phase bins than the recording's ``n_samples`` samples (``ValueError``
    naming ``where``): every bin needs samples of its own, and the bins' series grow as
    ``n_bins²``."""
    if n_bins > n_samples:
        raise ValueError(
            f"{where}: n_bins = {n_bins} is more than the {n_samples} samples of the recording: "
            "every phase bin needs samples of its own; use fewer bins (regression__n_bins; "
            "torchconn-fit --n-bins, estimator.regression.n_bins)")


#: fewest usable power samples per coefficient of the tied metric model
_MIN_SAMPLES_PER_COEF = 3.0
#: the fields of :class:`TubeRegression` that its tied metric's coefficients depend on
#: (besides the data, the cycle and the pooling; not the bins, where they are only evaluated)
METRIC_SETTINGS = ("metric_order", "metric_derivative_order", "metric_second_order",
                   "metric_held_out_order")
#: the metric's per-bin fields of :class:`~torchconn.regression.model.BinEstimates`
_METRIC_BIN_FIELDS = ("M", "M_se", "M_gamma_dot", "M_gamma_dot_se", "power_on_cycle",
                      "power_on_cycle_se", "M_bias", "M_change_factor", "M_sampling_factor", "dM",
                      "M_offset_bias")


class Regression(Options, abc.ABC):
    """Base of the estimator's regression stage: ``fit(traj, cycle, pool=...) -> model``."""

    @abc.abstractmethod
    def fit(self, traj: Trajectory, cycle: LimitCycle, *, pool: bool = False
            ) -> LocalConnectionModel:
        """The local model of a prepared trajectory (``smoothed`` and ``phase`` set) around
        ``cycle``: batch dims ``...`` of ``traj``, or none when ``pool``."""


@dataclass(frozen=True, kw_only=True)
class TubeRegression(Regression):
    """Tube regressions in phase bins and their Fourier series in phase (the paper's Sec. 4).

    Attributes:
        n_bins: phase bins M (regression centres φ_m = 2πm/M).
        fourier_order: order of the Fourier series interpolating the per-bin estimates
            (at most (M−1)/2). ``A(γ(φ))`` is nonlinear in the gait, so it carries harmonics
            well above the gait's own; a low order biases the model.
        intercept_order: order of the series of the intercept ``c(φ)`` (the body velocity on
            the cycle, ``A(γ)γ̇``: the gait's harmonics times the connection's, the richest of
            the model's terms). ``"auto"`` (default): ``fourier_order``, or more where the
            recording's phase-averaged body velocity has harmonics above it that hold up on
            held-out blocks of whole cycles (:func:`~torchconn.phase.held_out_order`, at most
            (M−1)/2, per batch element; ``model.meta["intercept_order"]``); an integer fixes
            it; None: ``fourier_order``. Measured on the 9-link reference gait at 0.25η: the
            intercept truncated at order 12 doubled the model's error (README, "Accuracy").
        window: half-width of a bin's phase window in units of the bin spacing (0.5: each
            sample in exactly one bin; larger: overlapping windows, more samples per bin).
            None (default) sizes it from the data: wide enough that a window holds about
            ``samples_per_regressor`` samples per regressor, and at least 1.
        samples_per_regressor: the data-size rule behind ``window=None``.
        kernel: sample weights within a window (``"tricube"`` falls smoothly to zero at the
            window's edge, which lowers the bias from the gait's curvature within a window).
        delta_max: only samples with ``|δ| < delta_max`` enter a bin's regression (None: all).
        ridge: Tikhonov penalty on the scaled regressors (0: ordinary least squares).
        ridge_connection: the ridge (given, added for ill-conditioned bins, or chosen by
            :func:`~torchconn.regression.skill.select_complexity`) also penalises ``A``'s
            columns (default, the previous behaviour); False: only those of ``b`` and
            ``∂A/∂r`` (:func:`~torchconn.regression.connection.unpenalised_columns`). Chosen
            by held-out prediction, a ridge on ``A`` shrank it at video rates (one trial,
            32 samples per cycle, ω = 0.005: Â 79 % off at scale 0.23; False: 12.8 %); False
            is better for ``Â`` wherever the complexity is chosen (README "The ridge and Â")
            but predicts v_x on the later cycles of short recordings worse (losses to the
            phase average 6 -> 18 of 360 components), so it is not the default.
            :class:`~torchconn.regression.estimator.ConnectionEstimator` chooses and fits its
            connection (``model_``) with False wherever the ridge it chose would penalise
            ``A``, and keeps the penalised fit for its forecasts (``forecast_model_``).
        on_ill_conditioned: what to do with bins with too few samples or a rank-deficient
            design: raise, warn, or regularise (``"ridge"``).
        metric: estimate the dissipation metric: None (default) when the data carry a power
            channel, True to require one (fitting data without it is an error that names the
            missing ``power`` column), False never.
        metric_order, metric_derivative_order: Fourier orders in phase of the tied model's
            ``M(φ)`` (the largest considered when ``metric_held_out_order``) and ``∂M/∂r(φ)``
            (None: no derivative term; it is also left out when the data hold fewer than 3
            usable samples per coefficient with it, e.g. a 9-link trial of 30 cycles). Chosen
            by measurement on 3- and 5-link gaits other than the benchmark's (README, "Known
            limits").
        metric_second_order: the tied model's second-order offset term ``½ δᵀ∂²M/∂r²δ``
            (:func:`~torchconn.regression.metric.tied_metric_regression`'s ``second_order``):
            None (default), ``"diagonal"`` or ``"full"``. Without it ``M̂`` is the metric
            averaged over the tube (on-cycle power +0.1-0.3 % at ω = 0 on the 3- and 5-link).
            Measured (README, "Is the cost standard error honest?"): it removes that bias on
            clean data (5-link on-cycle power 0.24 -> 0.01 %) but costs variance under noise
            (5-link M̂γ̇ 2.3 -> 3.1 % at ω = 0.002, 5.5 -> 8.7 % at 0.005, 8 held-out seed
            sets), so it is an option.
            Left out where the data hold fewer than 3 usable samples per coefficient with it.
        metric_held_out_order: choose the order of ``M(φ)`` in ``0 … metric_order`` from the
            data, by the noise-corrected error on held-out blocks of whole cycles (lower orders
            where the noise leaves the higher harmonics unresolved); False: ``metric_order``.

    The metric is one ``M(φ)`` (and ``∂M/∂r(φ)``), Fourier in phase, that explains the
    power of each sample interval, ``P ≈ vᵀ[M + ∂M/∂r δ]v`` with ``v`` the raw sample
    differences, corrected for the shapes' observation noise
    (:func:`~torchconn.regression.metric.tied_metric_regression`), with its bands widened
    by its order bias and that estimate's own variance, and, without
    ``metric_second_order``, the tube's second-order bias estimated beside it
    (``BinEstimates.M_offset_bias``, drawn by nearby-gait predictions).
    """

    n_bins: int = option(48, ge=3)
    fourier_order: int = option(12, ge=0)
    intercept_order: int | Literal["auto"] | None = option("auto", ge=0)
    window: float | None = option(None, gt=0)
    samples_per_regressor: float = option(2.5, gt=0)
    kernel: Literal["box", "tricube", "epanechnikov"] = "tricube"
    delta_max: float | None = option(None, gt=0)
    ridge: float = option(0.0, ge=0)
    ridge_connection: bool = True
    on_ill_conditioned: Literal["raise", "warn", "ridge"] = "raise"
    metric: bool | None = None
    metric_order: int = option(6, ge=0)
    metric_derivative_order: int | None = option(1, ge=0)
    metric_second_order: Literal["diagonal", "full"] | None = None
    metric_held_out_order: bool = True

    def __post_init__(self) -> None:
        super().__post_init__()
        if not 2 * self.fourier_order < self.n_bins:
            raise ValueError(
                f"TubeRegression.fourier_order must satisfy 2*fourier_order < n_bins="
                f"{self.n_bins} (the series is fitted to one value per bin), got "
                f"{self.fourier_order!r}"
            )
        if isinstance(self.intercept_order, int) and not 2 * self.intercept_order < self.n_bins:
            raise ValueError(
                f"TubeRegression.intercept_order must satisfy 2*intercept_order < n_bins="
                f"{self.n_bins}, got {self.intercept_order!r}"
            )

    def fit(self, traj: Trajectory, cycle: LimitCycle, *, pool: bool = False,
            metric_cache: dict | None = None) -> LocalConnectionModel:
        """Regressions in every phase bin and their Fourier series in phase.

        Args:
            traj: a prepared trajectory (``smoothed`` and ``phase`` set), batch dims ``...``.
            cycle: its limit cycle (batch dims ``...``, or none when ``pool``).
            pool: fit one model to all trials together.
            metric_cache: a dict shared by fits of the same ``traj`` and ``cycle`` (the
                estimator's fit and its refit after choosing the complexity): the tied
                metric's coefficients are kept there under the pooling and the metric's
                settings (:data:`METRIC_SETTINGS`; they do not depend on the bins, where they
                are only evaluated) and taken from it by a fit with the same ones, instead of
                fitted again (the same numbers bit for bit).

        Returns:
            a :class:`LocalConnectionModel` with batch dims ``...`` (none when pooled).
        """
        if traj.smoothed is None or traj.phase is None:
            raise ValueError("TubeRegression.fit needs a prepared trajectory: call "
                             "ConnectionEstimator.prepare(traj) first")
        s = traj.smoothed
        phase, r, r_dot, xi, power = traj.phase, s.r, s.r_dot, s.xi, traj.power
        if pool:
            phase, r, r_dot, xi = (pool_batch(x, k)
                                   for x, k in ((phase, 0), (r, 1), (r_dot, 1), (xi, 1)))
            power = None if power is None else pool_batch(power, 0)
        M = self.n_bins
        check_bin_count(M, int(torch.isfinite(phase).sum()), type(self).__name__)
        centres = torch.arange(M, dtype=r.dtype, device=r.device) * (2 * math.pi / M)
        batch = phase.shape[:-1]
        gamma_m = cycle.gamma_at(centres.expand(batch + (M,)))
        gamma_dot_m = (cycle.phase_rate[..., None, None]
                       * cycle.gamma_dot_at(centres.expand(batch + (M,))))
        opts = dict(delta_max=self.delta_max, ridge=self.ridge,
                    on_ill_conditioned=self.on_ill_conditioned,
                    ridge_connection=self.ridge_connection)

        def bins_for(n_regressors: int):
            window = self.window or auto_window(phase, M, n_regressors,
                                                self.samples_per_regressor)
            return assign_bins(phase, M, window=window, kernel=self.kernel), window

        fit, window, connection_meta = self._connection_fit(
            traj, pool, (phase, r, r_dot, xi), gamma_m, gamma_dot_m, opts, bins_for)
        # the metric's per-bin estimates (BinEstimates' fields), noise and order (the tied
        # metric has no bins of its own: metric_window None)
        metric, metric_window, noise, metric_order = {}, None, None, None
        second_order = None
        if self.metric is not False and power is not None:
            coefficients, noise = self._tied_metric(traj, cycle, pool, metric_cache)
            metric_fit = coefficients.at(centres, gamma_dot_m)
            second_order = coefficients.second_order
            metric = dict(zip(_METRIC_BIN_FIELDS, (
                metric_fit.M, metric_fit.se_M, metric_fit.M_gamma_dot,
                metric_fit.se_M_gamma_dot, metric_fit.power_on_cycle,
                metric_fit.se_power_on_cycle, metric_fit.bias_M, metric_fit.change_factor_M,
                metric_fit.sampling_factor_M, metric_fit.dM, metric_fit.offset_bias_M),
                strict=True))
            metric_order = None if metric_fit.order is None else metric_fit.order.tolist()

        estimates = BinEstimates(
            phase=centres, gamma=gamma_m, gamma_dot=gamma_dot_m,
            c=fit.c, b=fit.b, A=fit.A, dA=fit.dA,
            c_se=fit.se_c, b_se=fit.se_b, A_se=fit.se_A, dA_se=fit.se_dA,
            n_samples=fit.n_samples, A_sampling_factor=fit.sampling_factor_A,
            A_bias_allowance=fit.bias_allowance_A, dA_correlation=fit.corr_dA, **metric,
        )

        def series(values: Tensor, ndim: int):
            return fit_fourier(centres, values, self.fourier_order, value_ndim=ndim)

        c_order = self.intercept_orders(traj, pool)
        if c_order is not None:
            connection_meta["intercept_order"] = c_order.tolist()
        # (unpooled fits may bin each element at its own window: meta["windows"], (...))
        a_series, offsets, a_meta = self._a_series(centres, fit,
                                                   connection_meta.get("windows", window), pool)
        connection_meta.update(a_meta)
        model = LocalConnectionModel(
            gamma=cycle.gamma, phase_rate=cycle.phase_rate,
            c=intercept_series(centres, offsets.c, self.fourier_order, c_order),
            b=series(offsets.b, 2),
            A=a_series, dA=series(fit.dA, 3),
            M=series(metric["M"], 2) if metric else None,
            dM=series(metric["dM"], 3) if metric and metric["dM"] is not None else None,
            dA_fit=None if fit.dA_direct is None else series(fit.dA_direct, 3),
            bins=estimates,
            meta={"settings": {"regression": asdict(self), "pool": pool}, "dt": traj.dt,
                  "batch_shape": list(batch), "window": window, "metric_window": metric_window,
                  "metric_noise_std": noise, "metric_order": metric_order,
                  "metric_second_order": second_order,
                  **connection_meta,
                  "tube_rms": _tube_rms(r, cycle.gamma_at(phase))},
        )
        return model

    def _a_series(self, centres: Tensor, fit, window, pool: bool):
        """The Fourier series of ``Â`` (order ``fourier_order``), the fit whose per-bin ``ĉ``
        and ``b̂`` go with it (``fit`` here; :class:`~torchconn.regression.NoiseAwareRegression`
        may shrink unresolved harmonics and re-estimate those to the shrunk series) and extra
        meta (none here). ``window``: the bins' half-width, a number or, unpooled, per element
        (nested lists of the batch's shape)."""
        return fit_fourier(centres, fit.A, self.fourier_order, value_ndim=2), fit, {}

    def intercept_orders(self, traj: Trajectory, pool: bool) -> Tensor | None:
        """The intercept's Fourier order ``(...)`` per batch element (``()`` when ``pool``) of a
        prepared trajectory, or None where it is ``fourier_order`` by setting."""
        if self.intercept_order is None:
            return None
        batch = () if pool else tuple(traj.batch_shape)
        device = traj.r.device
        if self.intercept_order != "auto":
            return torch.full(batch, self.intercept_order, dtype=torch.long, device=device)
        theta, weights = _unwrapped_cycles(traj.phase)
        chosen = held_out_order(theta, weights, traj.smoothed.xi, (self.n_bins - 1) // 2,
                                n_pooled=traj.phase.ndim - 1 if pool else 0)
        return chosen.clamp_min(self.fourier_order)

    def _connection_fit(self, traj: Trajectory, pool: bool, samples, gamma_m: Tensor,
                        gamma_dot_m: Tensor, opts: dict, bins_for):
        """The connection's per-bin regression (:meth:`_smoothed_fit`): returns the
        :class:`ConnectionFit`, the window and extra meta. Subclasses regress differently
        (:class:`~torchconn.regression.NoiseAwareRegression`, which also ties ``∂Â/∂r``)."""
        return self._smoothed_fit(samples, gamma_m, gamma_dot_m, opts, bins_for)

    def _smoothed_fit(self, samples, gamma_m: Tensor, gamma_dot_m: Tensor, opts: dict,
                      bins_for):
        """The per-bin regression on the smoothed ``samples`` (phase, r, ṙ, ξ, pooled when
        ``pool``): the :class:`ConnectionFit`, the window and extra meta."""
        phase, r, r_dot, xi = samples
        d = r.shape[-1]
        bins, window = bins_for(1 + 2 * d + d * d)
        fit = connection_regression(r, r_dot, xi, bins, gamma_m, gamma_dot_m, **opts)
        return fit, window, {}

    def _tied_metric(self, traj: Trajectory, cycle: LimitCycle, pool: bool,
                     cache: dict | None = None):
        """The tied metric regression on the sample intervals of the raw recorded shapes.

        Returns its :class:`~torchconn.regression.metric.TiedMetricCoefficients` (to evaluate
        at the bin centres) and the estimated shape-noise standard deviations (a list,
        JSON-ready; None without correction); ``cache``: see :meth:`fit`'s ``metric_cache``.
        """
        key = (type(self), pool, *(getattr(self, k) for k in METRIC_SETTINGS))
        if cache is not None and key in cache:
            return cache[key]
        if not bool(torch.isfinite(traj.power).any()):
            raise ValueError("the power column has no values (all empty or NaN): the metric "
                             "cannot be estimated; fit the connection alone with "
                             "TubeRegression(metric=False) (torchconn-fit: --metric no)")
        # one-sample intervals; power k belongs to [t_k, t_{k+1}) (docs/conventions.md). A NaN
        # row closes each trial, so pooled trials stay apart in the residuals' lag structure.
        iv = interval_samples(traj.pose, traj.r, traj.phase, traj.dt, 1)
        nan = float("nan")
        phase = nn.functional.pad(_unwrapped(iv.phase), (0, 1), value=nan)
        offset = nn.functional.pad(iv.r - cycle.gamma_at(torch.nan_to_num(iv.phase)).to(iv.r),
                                   (0, 0, 0, 1), value=nan)
        v = nn.functional.pad(iv.r_dot, (0, 0, 0, 1), value=nan)
        power = nn.functional.pad(traj.power[..., :-1].to(v), (0, 1), value=nan)
        if pool:
            # distinct cycle numbers per trial, so that each trial's cycles are their own clusters
            span = float(torch.nan_to_num(phase).abs().amax()) + 4 * math.pi
            trial = torch.arange(math.prod(phase.shape[:-1]), dtype=phase.dtype,
                                 device=phase.device)
            phase = phase + (2 * math.pi * math.ceil(span / (2 * math.pi)) * trial).reshape(
                phase.shape[:-1] + (1,))
            # each trial's recorded rows only: a shorter trial's padding would move the rows
            # after it in the pooled sequence (and so the blocks of the noise's standard error)
            recorded = recorded_span(traj)
            phase, offset, v, power = (x[recorded] for x in (phase, offset, v, power))
        derivative = self.metric_derivative_order
        usable = (torch.isfinite(power) & torch.isfinite(v).all(-1)).sum(-1).min()
        d = v.shape[-1]
        if derivative is not None and int(usable) < _MIN_SAMPLES_PER_COEF * tied_metric_n_coef(
                d, self.metric_order, derivative):
            # ∂M/∂r only where the data identify it (many joints, short data)
            warnings.warn(
                f"metric: {int(usable)} usable power samples are too few for the ∂M/∂r term "
                f"({tied_metric_n_coef(d, self.metric_order, derivative)} coefficients with it, "
                f"{_MIN_SAMPLES_PER_COEF:g} samples each); it is left out, so M̂ also absorbs "
                "how M varies off the cycle (measured on the 9-link, 2 trials x 30 cycles: "
                "M̂γ̇ 30-40 % off, against 3 % with 4 trials). Pool more trials or cycles",
                stacklevel=3)
            derivative = None

        def identified(form):  # the second-order term only beside the first, where identified
            return derivative is not None and int(usable) >= _MIN_SAMPLES_PER_COEF * \
                tied_metric_n_coef(d, self.metric_order, derivative, form)

        second = self.metric_second_order if identified(self.metric_second_order) else None
        if self.metric_second_order is not None and second is None:
            warnings.warn(
                f"metric: the second-order offset term (metric_second_order="
                f"{self.metric_second_order!r}) is left out: it needs the ∂M/∂r term and "
                f"{_MIN_SAMPLES_PER_COEF:g} usable power samples per coefficient "
                f"({int(usable)} usable); M̂ keeps the tube's second-order bias. Pool more "
                "trials or cycles, or use 'diagonal'", stacklevel=3)
        # its bias allowance in the form the data identify (the 9-link's 36² coefficients of
        # the full form outnumber 4 x 30 cycles' samples / 3; its diagonal's 8·36 do not)
        offset_bias = next((f for f in ("full", "diagonal") if identified(f)), None) \
            if second is None else None
        orders = dict(order=self.metric_order, derivative_order=derivative,
                      second_order=second)
        omega2 = self._metric_noise(traj, offset, v, power, phase, orders, pool)  # (..., d)
        noise = omega2.sqrt().tolist()
        noise_variance = 2 * omega2 / traj.dt**2
        fit = tied_metric_coefficients(offset, v, power, phase, **orders,
                                       noise_variance=noise_variance,
                                       held_out_order=self.metric_held_out_order,
                                       order_bias="posterior",
                                       offset_bias=offset_bias,
                                       min_samples_per_coef=_MIN_SAMPLES_PER_COEF)
        if cache is not None:
            cache[key] = fit, noise
        return fit, noise

    def _metric_noise(self, traj: Trajectory, offset: Tensor, v: Tensor, power: Tensor,
                      phase: Tensor, orders: dict, pool: bool) -> Tensor:
        """The shapes' observation-noise variance ``(..., d)`` (one level for all joints, and
        for the pooled trials: they share the rig): the estimate from the spectrum of the shapes'
        increments (:func:`~torchconn.regression.noise_aware.estimate_noise`) and the one from
        the lag structure of an uncorrected fit's power residuals
        (:func:`~torchconn.regression.metric.power_noise_variance`) averaged with weights from
        their standard errors, then set to 0 unless 2 standard errors above it."""
        spectrum = estimate_noise(traj.r)
        n_pool = traj.r.ndim - 2 if pool else 0
        # the joints taken as independent: the metric's combination was set that way
        # (correlated standard errors, NoiseEstimate.correlation, not measured here)
        estimates = [tuple(x.to(v) for x in spectrum.pooled_mean(
            n_pool, channels=True, correlated=False))]
        # from the uncorrected fit's power residuals (the power channel is noise-free)
        first = tied_metric_coefficients(offset, v, power, phase, **orders,
                                         min_samples_per_coef=_MIN_SAMPLES_PER_COEF)
        predicted, m_v = tied_metric_predict(first.coef, offset, v, phase, **orders)
        residual = _per_span(lambda res, mv: power_noise_variance(res, mv, traj.dt,
                                                                  with_se=True),
                             power - predicted, m_v, None if pool else recorded_span(traj))
        estimates.append(residual)
        # inverse-variance weights (an unresolved estimate, infinite standard error, gets none)
        tiny = torch.finfo(v.dtype).tiny
        weights = [1 / se.square().clamp(min=tiny) for _, se in estimates]
        total = sum(weights)
        mean = sum(w * m for w, (m, _) in zip(weights, estimates, strict=True)) / total
        return torch.where(mean > 2 * total.rsqrt(), mean, torch.zeros_like(mean))


def _per_span(fn, residual: Tensor, m_v: Tensor, recorded: Tensor | None
              ) -> tuple[Tensor, Tensor]:
    """``fn(residual, m_v)`` (two ``(..., d)`` results) of the interval samples of each trial
    over its recorded span (``recorded (..., T)``, :func:`~torchconn.phase.smoothing.
    recorded_span`; the samples' rows are the trial's), as it would be alone; None: over the
    whole of each row."""
    batch, (T, d) = residual.shape[:-1], m_v.shape[-2:]
    res, mv = residual.reshape(-1, T), m_v.reshape(-1, T, d)
    split = None if recorded is None else over_spans(
        recorded.reshape(-1, T), lambda rows, a, b: fn(res[rows, a:b], mv[rows, a:b]))
    if split is None:
        return fn(residual, m_v)
    return tuple(o.reshape(batch + (d,)) for o in split)


def _unwrapped(phase: Tensor) -> Tensor:
    """``(..., T)`` phase made continuous (each step from the last finite value wrapped into
    ``[-π, π)``, so NaN gaps are bridged), starting at its first finite value (a trial whose
    first samples are missing, or that starts later on a shared grid, keeps its phase)."""
    finite = torch.isfinite(phase)
    first = span_bounds(finite)[0].unsqueeze(-1)
    idx = torch.arange(phase.shape[-1], device=phase.device)
    # forward-filled: the last finite value at or before each sample (the first before it)
    filled = phase.gather(-1, torch.cummax(torch.where(finite, idx, first), -1).values)
    step = torch.remainder(filled.diff(dim=-1) + math.pi, 2 * math.pi) - math.pi
    cum = torch.cat([torch.zeros_like(phase[..., :1]), torch.nan_to_num(step).cumsum(-1)], -1)
    out = (filled.gather(-1, first) - cum.gather(-1, first)) + cum
    return torch.where(torch.isnan(phase), torch.nan, out)


def intercept_series(centres: Tensor, values: Tensor, order: int, intercept_order: Tensor | None
                     ) -> FourierSeries:
    """The Fourier series in phase of per-bin intercepts ``values (..., M, 3)`` at bin centres
    ``centres (M,)``: order ``order``, or per batch element ``intercept_order (...)`` (None:
    ``order``). Elements at ``order`` get exactly the order-``order`` least-squares series, the
    others the series of the highest order the bins carry, ``(M − 1) // 2``, truncated to their
    own; the coefficients always have that highest order, so that no element's series depends
    on the others in its batch."""
    base = fit_fourier(centres, values, order, value_ndim=1)
    if intercept_order is None:
        return base
    top = (centres.shape[-1] - 1) // 2
    high = fit_fourier(centres, values, top, value_ndim=1).truncated(intercept_order)
    padded = torch.zeros_like(high.coeffs)
    padded[..., :2 * order + 1, :] = base.coeffs
    keep_base = (intercept_order <= order).reshape(intercept_order.shape + (1, 1))
    return FourierSeries(torch.where(keep_base, padded, high.coeffs), 1)


def _unwrapped_cycles(phase: Tensor) -> tuple[Tensor, Tensor]:
    """A prepared trajectory's phase ``(..., T)`` as :func:`~torchconn.phase.held_out_order`
    wants it: non-decreasing (NaN drop-outs filled with the phase before them) and the
    whole-cycle weights, 0 at the drop-outs."""
    finite = torch.isfinite(phase)
    filled = torch.cummax(torch.where(finite, phase, -math.inf), dim=-1).values
    first = torch.where(finite, phase, math.inf).amin(-1, keepdim=True)
    filled = torch.where(torch.isfinite(filled), filled, first)
    return filled, whole_cycle_weights(filled) * finite.to(phase.dtype)


def _tube_rms(r: Tensor, gamma: Tensor) -> list[float]:
    """Per-joint RMS of the offsets ``δ = r − γ(φ)`` over every sample of every trial: the
    width of the tube the data covered (``(d,)`` as a list, for the JSON-able ``meta``)."""
    delta = (r - gamma).reshape(-1, r.shape[-1])
    return [float(v) for v in delta.pow(2).nanmean(0).sqrt()]


#: the old private name, read by regression/skill.py until it imports binning.auto_window
_auto_window = auto_window
