"""Model selection: held-out skill, the complexity ladder and the connection alone.

- :mod:`~torchconn.regression.selection.skill` -- :class:`Skill`, the held-out ``R²`` of a
  fitted model against the phase-averaged velocity and the template, on contiguous blocks of
  whole cycles, interleaved or forward in time (:func:`cross_validate`), beside the physics
  reference and zero; :func:`regression_view`, the samples as a regression sees them;
  :func:`forward_prediction`, the forward check's predictions sample by sample. (Its
  function :func:`~torchconn.regression.selection.skill.skill` is not re-exported here:
  ``selection.skill`` is the module.)
- :mod:`~torchconn.regression.selection.complexity` -- :func:`select_complexity`, the bins,
  Fourier order and ridge of least held-out error, and per component the full model, the
  connection alone or the phase average (:class:`ComplexityChoice`);
  :func:`select_connection_alone` where no model with ``b̂`` and ``∂Â/∂r`` can be scored.
- :mod:`~torchconn.regression.selection.held_out` -- :func:`leave_blocks_out`, the fits
  without each block by downdating every bin's normal equations.
"""

from __future__ import annotations

from ...cycles import FALLBACK_CYCLES, few_cycles
from .complexity import (
    COMPLEXITY_GRID,
    FALLBACK_MARGIN,
    FALLBACK_Z,
    OFFSET_TERMS_Z,
    RIDGE_GRID,
    RIDGE_MIN_GAIN,
    ComplexityChoice,
    ConnectionAlone,
    checked_terms,
    connection_alone_model,
    nested_list,
    select_complexities,
    select_complexity,
    select_connection_alone,
    unchecked_choice,
    warn_if_poor,
)
from .held_out import leave_blocks_out
from .prior import blend, blended_r2, forward_checked, prior_weights
from .skill import (
    COMPONENTS,
    ForwardPrediction,
    PoorHeldOutSkillWarning,
    RegressionView,
    Skill,
    cross_validate,
    downdates,
    fold_models,
    fold_references,
    forward_prediction,
    held_out_checks,
    held_out_predictions,
    phase_average,
    phase_average_orders,
    regression_view,
    with_phase_average,
    with_physics,
)

__all__ = [
    "Skill", "PoorHeldOutSkillWarning", "COMPONENTS", "RegressionView", "regression_view",
    "phase_average", "phase_average_orders", "cross_validate", "downdates",
    "with_phase_average", "leave_blocks_out", "held_out_checks", "fold_references",
    "with_physics", "ForwardPrediction", "forward_prediction", "fold_models",
    "held_out_predictions", "prior_weights", "forward_checked", "blend", "blended_r2",
    "ComplexityChoice", "ConnectionAlone", "COMPLEXITY_GRID", "RIDGE_GRID", "RIDGE_MIN_GAIN",
    "FALLBACK_Z", "FALLBACK_MARGIN", "FALLBACK_CYCLES", "OFFSET_TERMS_Z",
    "select_complexity", "select_complexities", "select_connection_alone",
    "connection_alone_model", "checked_terms", "unchecked_choice", "warn_if_poor",
    "few_cycles", "nested_list",
]
