"""The default metric stage: the tied, noise-corrected metric of :mod:`.tied`.

:class:`TiedMetric` fits one ``M(φ)`` (and ``∂M/∂r(φ)``), Fourier in phase, that explains the
power of each sample interval, ``P ≈ vᵀ[M + ∂M/∂r δ]v`` with ``v`` the raw sample differences,
corrected for the shapes' observation noise, with its bands widened by its order bias and that
estimate's own variance, and, without ``second_order``, the tube's second-order bias estimated
beside it (``BinEstimates.M_offset_bias``, drawn by nearby-gait predictions). The fit does not
depend on the connection's phase bins: :meth:`TiedMetric.attach` evaluates it at a fitted
connection's bins, so every candidate model of one recording shares one metric fit.
"""

from __future__ import annotations

import dataclasses
import math
import warnings
from dataclasses import dataclass
from typing import Literal

import torch
from torch import Tensor, nn

from ..._options import option
from ...cycles import trials_apart
from ...noise import estimate_noise, interval_samples
from ...phase.fourier import fit_fourier
from ...phase.limit_cycle import LimitCycle
from ...phase.smoothing import recorded_span
from ...trajectory import Trajectory, over_spans, span_bounds
from ..model import LocalConnectionModel
from .base import MetricEstimator
from .noise import power_noise_variance
from .tied import (
    TiedMetricCoefficients,
    tied_metric_coefficients,
    tied_metric_n_coef,
    tied_metric_predict,
)

__all__ = ["TiedMetric", "FittedMetric"]

#: fewest usable power samples per coefficient of the tied metric model
MIN_SAMPLES_PER_COEF = 3.0
#: the metric's per-bin fields of :class:`~torchconn.regression.model.BinEstimates`
_BIN_FIELDS = ("M", "M_se", "M_gamma_dot", "M_gamma_dot_se", "power_on_cycle",
               "power_on_cycle_se", "M_bias", "M_change_factor", "M_sampling_factor", "dM",
               "M_offset_bias")


@dataclass(frozen=True)
class FittedMetric:
    """A fitted tied metric: its coefficients and the shapes' noise level it corrected for.

    Attributes:
        coefficients: the :class:`~torchconn.regression.metric.tied.TiedMetricCoefficients`.
        noise_std: the estimated observation-noise standard deviation of each joint angle
            (rad; nested lists of the batch's shape x ``d``, JSON-ready).
    """

    coefficients: TiedMetricCoefficients
    noise_std: list


@dataclass(frozen=True, kw_only=True)
class TiedMetric(MetricEstimator):
    """The dissipation metric ``M(φ)`` (and ``∂M/∂r(φ)``) from a recorded power channel.

    Attributes:
        enabled: None (default) fits the metric when the data carry a power channel, True
            requires one (data without it are an error naming the missing ``power`` column),
            False never fits it.
        order, derivative_order: Fourier orders in phase of ``M(φ)`` (the largest considered
            when ``held_out_order``) and ``∂M/∂r(φ)`` (None: no derivative term; it is also
            left out, with a warning, when the data hold fewer than 3 usable power samples per
            coefficient with it).
        second_order: the second-order offset term ``½ δᵀ∂²M/∂r²δ``
            (:func:`~torchconn.regression.metric.tied_metric_regression`'s ``second_order``):
            None (default), ``"diagonal"`` or ``"full"``. Without it ``M̂`` is the metric
            averaged over the tube; with it the bias is removed on clean data at the cost of
            variance under noise. Left out where the data hold fewer than 3 usable samples
            per coefficient with it.
        held_out_order: choose the order of ``M(φ)`` in ``0 … order`` from the data, by the
            noise-corrected error on held-out blocks of whole cycles (lower orders where the
            noise leaves the higher harmonics unresolved); False: ``order``.
    """

    enabled: bool | None = None
    order: int = option(6, ge=0)
    derivative_order: int | None = option(1, ge=0)
    second_order: Literal["diagonal", "full"] | None = None
    held_out_order: bool = True

    def fit(self, traj: Trajectory, cycle: LimitCycle, *, pool: bool = False) -> FittedMetric:
        """The tied metric regression on the sample intervals of the raw recorded shapes.

        Raises:
            ValueError: the power channel has no values, or too few for the model.
        """
        if not bool(torch.isfinite(traj.power).any()):
            raise ValueError("the power column has no values (all empty or NaN): the metric "
                             "cannot be estimated; fit the connection alone "
                             "(metric__enabled=False; torchconn-fit: --metric no)")
        offset, v, power, phase = _interval_rows(traj, cycle, pool)
        usable = int((torch.isfinite(power) & torch.isfinite(v).all(-1)).sum(-1).min())
        orders = self._orders(v.shape[-1], usable)
        omega2 = self._noise(traj, offset, v, power, phase, orders, pool)  # (..., d)
        noise_variance = 2 * omega2 / traj.dt**2
        # its bias allowance in the form the data identify (the 9-link's 36² coefficients of
        # the full form outnumber 4 x 30 cycles' samples / 3; its diagonal's 8·36 do not)
        offset_bias = None if orders["second_order"] is not None else next(
            (f for f in ("full", "diagonal")
             if self._identified(v.shape[-1], usable, orders["derivative_order"], f)), None)
        fit = tied_metric_coefficients(offset, v, power, phase, **orders,
                                       noise_variance=noise_variance,
                                       held_out_order=self.held_out_order,
                                       order_bias=True, offset_bias=offset_bias,
                                       min_samples_per_coef=MIN_SAMPLES_PER_COEF)
        return FittedMetric(fit, omega2.sqrt().tolist())

    def attach(self, model: LocalConnectionModel, fitted: FittedMetric) -> LocalConnectionModel:
        bins = model.bins
        m = fitted.coefficients.at(bins.phase, bins.gamma_dot)
        values = dict(zip(_BIN_FIELDS, (
            m.M, m.se_M, m.M_gamma_dot, m.se_M_gamma_dot, m.power_on_cycle, m.se_power_on_cycle,
            m.bias_M, m.change_factor_M, m.sampling_factor_M, m.dM, m.offset_bias_M),
            strict=True))
        order = model.b.order

        def series(x: Tensor, ndim: int):
            return fit_fourier(bins.phase, x, order, value_ndim=ndim)

        return dataclasses.replace(
            model, bins=dataclasses.replace(bins, **values), M=series(m.M, 2),
            dM=None if m.dM is None else series(m.dM, 3),
            meta={**(model.meta or {}), "metric_noise_std": fitted.noise_std,
                  "metric_order": None if m.order is None else m.order.tolist(),
                  "metric_second_order": fitted.coefficients.second_order})

    def _identified(self, d: int, usable: int, derivative: int | None, form=None) -> bool:
        """Whether ``usable`` power samples identify the model with the ∂M/∂r term of order
        ``derivative`` and the second-order term ``form`` (3 samples per coefficient)."""
        return derivative is not None and usable >= MIN_SAMPLES_PER_COEF * tied_metric_n_coef(
            d, self.order, derivative, form)

    def _orders(self, d: int, usable: int) -> dict:
        """The model's orders for ``usable`` power samples: ∂M/∂r and the second-order term
        only where the data identify them (with a warning where one is left out)."""
        derivative = self.derivative_order
        if derivative is not None and not self._identified(d, usable, derivative):
            warnings.warn(
                f"metric: {usable} usable power samples are too few for the ∂M/∂r term "
                f"({tied_metric_n_coef(d, self.order, derivative)} coefficients with it, "
                f"{MIN_SAMPLES_PER_COEF:g} samples each); it is left out, so M̂ also absorbs "
                "how M varies off the cycle. Pool more trials or record more cycles",
                stacklevel=5)
            derivative = None
        second = self.second_order if self._identified(d, usable, derivative,
                                                       self.second_order) else None
        if self.second_order is not None and second is None:
            warnings.warn(
                f"metric: the second-order offset term (second_order={self.second_order!r}) "
                f"is left out: it needs the ∂M/∂r term and {MIN_SAMPLES_PER_COEF:g} usable "
                f"power samples per coefficient ({usable} usable); M̂ keeps the tube's "
                "second-order bias. Pool more trials or cycles, or use 'diagonal'",
                stacklevel=5)
        return dict(order=self.order, derivative_order=derivative, second_order=second)

    def _noise(self, traj: Trajectory, offset: Tensor, v: Tensor, power: Tensor,
               phase: Tensor, orders: dict, pool: bool) -> Tensor:
        """The shapes' observation-noise variance ``(..., d)`` (one level for all joints, and
        for the pooled trials: they share the rig): the estimate from the spectrum of the
        shapes' increments (:func:`~torchconn.noise.estimate_noise`) and the one from the lag
        structure of an uncorrected fit's power residuals
        (:func:`~torchconn.regression.metric.power_noise_variance`) averaged with weights from
        their standard errors, then set to 0 unless 2 standard errors above it."""
        spectrum = estimate_noise(traj.r)
        n_pool = traj.r.ndim - 2 if pool else 0
        # the joints taken as independent (their correlated standard errors are not used)
        estimates = [tuple(x.to(v) for x in spectrum.pooled_mean(
            n_pool, channels=True, correlated=False))]
        # from the uncorrected fit's power residuals (the power channel is noise-free)
        first = tied_metric_coefficients(offset, v, power, phase, **orders,
                                         min_samples_per_coef=MIN_SAMPLES_PER_COEF)
        predicted, m_v = tied_metric_predict(first.coef, offset, v, phase, **orders)
        estimates.append(_per_span(
            lambda res, mv: power_noise_variance(res, mv, traj.dt, with_se=True),
            power - predicted, m_v, None if pool else recorded_span(traj)))
        # inverse-variance weights (an unresolved estimate, infinite standard error, gets none)
        tiny = torch.finfo(v.dtype).tiny
        weights = [1 / se.square().clamp(min=tiny) for _, se in estimates]
        total = sum(weights)
        mean = sum(w * m for w, (m, _) in zip(weights, estimates, strict=True)) / total
        return torch.where(mean > 2 * total.rsqrt(), mean, torch.zeros_like(mean))


def _interval_rows(traj: Trajectory, cycle: LimitCycle, pool: bool
                   ) -> tuple[Tensor, Tensor, Tensor, Tensor]:
    """The one-sample intervals of ``traj``'s raw shapes as the tied model takes them: offsets
    from ``cycle`` ``(..., N, d)``, velocities ``(..., N, d)``, power ``(..., N)`` and
    unwrapped phase ``(..., N)``. Power ``k`` belongs to ``[t_k, t_{k+1})``
    (docs/conventions.md); a NaN row closes each trial, so pooled trials stay apart in the
    residuals' lag structure. Pooled: one row of each trial's recorded rows, their cycles
    numbered apart (each trial's cycles are their own clusters)."""
    iv = interval_samples(traj.pose, traj.r, traj.phase, traj.dt, 1)
    nan = float("nan")
    phase = nn.functional.pad(_unwrapped(iv.phase), (0, 1), value=nan)
    offset = nn.functional.pad(iv.r - cycle.gamma_at(torch.nan_to_num(iv.phase)).to(iv.r),
                               (0, 0, 0, 1), value=nan)
    v = nn.functional.pad(iv.r_dot, (0, 0, 0, 1), value=nan)
    power = nn.functional.pad(traj.power[..., :-1].to(v), (0, 1), value=nan)
    if not pool:
        return offset, v, power, phase
    phase = trials_apart(phase)
    # each trial's recorded rows only: a shorter trial's padding would move the rows after it
    # in the pooled sequence (and so the blocks of the noise's standard error)
    recorded = recorded_span(traj)
    return tuple(x[recorded] for x in (offset, v, power, phase))


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


