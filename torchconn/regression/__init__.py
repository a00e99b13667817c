"""Regress: phase-centred local models of the connection and the metric (the paper's Sec. 4).

- :mod:`~torchconn.regression.estimator` -- :class:`ConnectionEstimator`, the whole pipeline
  (smooth → phase → limit cycle → tube regressions → Fourier in phase) in scikit-learn manners,
  each stage a pluggable option object.
- :mod:`~torchconn.regression.tube` -- :class:`TubeRegression`, the regression stage.
- :mod:`~torchconn.regression.metric` -- :class:`TiedMetric`, the metric stage.
- :mod:`~torchconn.regression.online` -- :class:`OnlineConnection`, the tube regressions'
  sums updated cycle by cycle (recursive least squares), with a confidence per cycle.
- :mod:`~torchconn.regression.model` -- :class:`LocalConnectionModel`, the fitted ``Â``, ``∂Â/∂r``,
  ``M̂`` as Fourier series in phase, with per-bin standard errors.
- :mod:`~torchconn.regression.plots` -- figures of a fitted model with confidence bands.

The hot path of the estimator, batched over leading dims ``...`` (noise levels × trials):

1. :func:`assign_bins` -- phase ``(..., N)`` to a padded gather ``(..., M, Nmax)`` of each bin's
   samples with kernel weights.
2. :func:`connection_regression` -- ``ξ ≈ c + b δ + A δ̇ + ∂A/∂r (δ̇ ⊗ δ)`` per bin
   (eq. ``advancedregression``) → :class:`ConnectionFit`; :func:`tie_connection_derivative`
   ties its ``∂Â/∂r`` to ``b̂`` and ``dÂ/dφ`` (:mod:`~torchconn.regression.tied`).
3. :class:`TiedMetric` (:mod:`~torchconn.regression.metric`), the metric stage:
   :func:`tied_metric_regression`, ``P ≈ vᵀ[M(φ) + ∂M/∂r(φ) δ]v`` on the sample intervals of
   the raw shapes, Fourier in phase, noise-corrected → :class:`MetricFit`.

The bin regressions share one batched weighted least-squares solver (equilibrated normal equations,
Cholesky, calibrated standard errors) and one policy for bins that cannot be fitted: too few
samples or a numerically rank-deficient design raise (or warn / regularise), never a silent
garbage estimate. Missing samples are NaN and are excluded automatically.
"""

from __future__ import annotations

from ._wls import IllConditionedBinWarning
from .base import Regression
from .binning import KERNELS, BinIndex, assign_bins
from .connection import ConnectionFit, connection_design, connection_regression
from .estimator import (
    STAGES,
    ConnectionEstimator,
    estimator_from_settings,
    estimator_settings,
    fit_local_model,
    prepare,
)
from .metric import (
    MetricEstimator,
    MetricFit,
    TiedMetric,
    power_noise_variance,
    tied_metric_n_coef,
    tied_metric_predict,
    tied_metric_regression,
)
from .model import BinEstimates, LocalConnectionModel
from .noise_aware import NoiseAwareRegression
from .online import CycleConfidence, OnlineConnection
from .tied import tie_connection_derivative
from .tube import TubeRegression

__all__ = [
    "assign_bins", "BinIndex", "KERNELS",
    "connection_regression", "ConnectionFit", "connection_design", "tie_connection_derivative",
    "MetricEstimator", "TiedMetric", "MetricFit",
    "tied_metric_regression", "tied_metric_n_coef", "tied_metric_predict",
    "power_noise_variance",
    "IllConditionedBinWarning",
    "LocalConnectionModel", "BinEstimates",
    "ConnectionEstimator", "estimator_from_settings", "estimator_settings", "STAGES",
    "Regression", "TubeRegression", "NoiseAwareRegression", "prepare",
    "fit_local_model", "OnlineConnection", "CycleConfidence",
]
