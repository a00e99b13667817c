"""The metric stage: the dissipation metric ``M(φ)`` (and ``∂M/∂r(φ)``) from recorded power.

- :mod:`.base`: :class:`MetricEstimator`, the abstract stage;
- :mod:`.stage`: :class:`TiedMetric`, the default stage;
- :mod:`.tied`: the tied model's regression, :func:`tied_metric_regression`;
- :mod:`.normal`: its noise-corrected normal equations and held-out orders;
- :mod:`.noise`: the shapes' noise level from its power residuals.
"""

from .base import MetricEstimator
from .noise import power_noise_variance
from .stage import FittedMetric, TiedMetric
from .tied import (
    MetricFit,
    SecondOrder,
    TiedMetricCoefficients,
    tied_metric_coefficients,
    tied_metric_n_coef,
    tied_metric_predict,
    tied_metric_regression,
)

__all__ = [
    "MetricEstimator", "TiedMetric", "FittedMetric", "MetricFit", "SecondOrder",
    "TiedMetricCoefficients", "tied_metric_regression", "tied_metric_coefficients",
    "tied_metric_n_coef", "tied_metric_predict", "power_noise_variance",
]
