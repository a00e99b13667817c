"""Evaluate: ground-truth, data-driven, analytic and template models of the body velocity, and errors.

See :mod:`~torchconn.evaluation.models`.
"""

from .models import (
    COMPONENTS,
    MODELS,
    clean_trajectory,
    error_summary,
    models_on,
    observed_view,
    phase_bin_errors,
    reference_models,
    simulator_on_cycle,
)

__all__ = ["MODELS", "COMPONENTS", "reference_models", "models_on", "observed_view",
           "simulator_on_cycle", "clean_trajectory", "error_summary", "phase_bin_errors"]
