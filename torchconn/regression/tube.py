"""The estimator's regression stage: tube regressions in phase bins, then Fourier in phase.

:class:`TubeRegression` fits, in each of M phase bins, the first-order model of the body
velocity around the cycle (eq. ``advancedregression``, :func:`connection_regression`) and
interpolates the per-bin estimates by Fourier series in phase into a
:class:`~torchconn.regression.model.LocalConnectionModel`; the metric is a stage of its own
(:mod:`torchconn.regression.metric`). Other regression methods derive from
:class:`~torchconn.regression.base.Regression` and slot into ``ConnectionEstimator(regression=…)``.
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass
from typing import Literal

import torch
from torch import Tensor

from .._options import option
from ..cycles import whole_cycle_phase
from ..phase.fourier import FourierSeries, fit_fourier
from ..phase.limit_cycle import LimitCycle
from ..phase.phaser import held_out_order
from ..trajectory import Trajectory, pool_batch
from .base import Regression, check_bin_count
from .binning import assign_bins, auto_window
from .connection import connection_regression
from .model import BinEstimates, LocalConnectionModel

__all__ = ["TubeRegression"]


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
            it; None: ``fourier_order``.
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
            columns (default); False: only those of ``b`` and ``∂A/∂r``
            (:func:`~torchconn.regression.connection.unpenalised_columns`): a ridge on ``A``
            shrinks ``Â`` towards 0, while one on ``b`` and ``∂A/∂r`` alone can forecast the
            body velocity worse. :class:`~torchconn.regression.estimator.ConnectionEstimator`
            chooses and fits its
            connection (``model_``) with False wherever the ridge it chose would penalise
            ``A``, and keeps the penalised fit for its forecasts (``forecast_model_``).
        on_ill_conditioned: what to do with bins with too few samples or a rank-deficient
            design: raise, warn, or regularise (``"ridge"``).
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

    def fit(self, traj: Trajectory, cycle: LimitCycle, *, pool: bool = False
            ) -> LocalConnectionModel:
        """Regressions in every phase bin and their Fourier series in phase.

        Args:
            traj: a prepared trajectory (``smoothed`` and ``phase`` set), batch dims ``...``.
            cycle: its limit cycle (batch dims ``...``, or none when ``pool``).
            pool: fit one model to all trials together.

        Returns:
            a :class:`LocalConnectionModel` with batch dims ``...`` (none when pooled).
        """
        if traj.smoothed is None or traj.phase is None:
            raise ValueError("TubeRegression.fit needs a prepared trajectory: call "
                             "ConnectionEstimator.prepare(traj) first")
        s = traj.smoothed
        phase, r, r_dot, xi = traj.phase, s.r, s.r_dot, s.xi
        if pool:
            phase, r, r_dot, xi = (pool_batch(x, k)
                                   for x, k in ((phase, 0), (r, 1), (r_dot, 1), (xi, 1)))
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
        estimates = BinEstimates(
            phase=centres, gamma=gamma_m, gamma_dot=gamma_dot_m,
            c=fit.c, b=fit.b, A=fit.A, dA=fit.dA,
            c_se=fit.se_c, b_se=fit.se_b, A_se=fit.se_A, dA_se=fit.se_dA,
            n_samples=fit.n_samples, A_sampling_factor=fit.sampling_factor_A,
            A_bias_allowance=fit.bias_allowance_A, dA_correlation=fit.corr_dA,
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
            dA_fit=None if fit.dA_direct is None else series(fit.dA_direct, 3),
            bins=estimates,
            meta={"settings": {"regression": asdict(self), "pool": pool}, "dt": traj.dt,
                  "batch_shape": list(batch), "window": window,
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
        theta, weights = whole_cycle_phase(traj.phase)
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


def _tube_rms(r: Tensor, gamma: Tensor) -> list[float]:
    """Per-joint RMS of the offsets ``δ = r − γ(φ)`` over every sample of every trial: the
    width of the tube the data covered (``(d,)`` as a list, for the JSON-able ``meta``)."""
    delta = (r - gamma).reshape(-1, r.shape[-1])
    return [float(v) for v in delta.pow(2).nanmean(0).sqrt()]
