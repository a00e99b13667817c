"""Better gaits from data: use the local model to propose, and verify, gait improvements.

The paper's closing extension, as a loop: **record → fit → propose a better nearby gait →
record it → …**

- :meth:`LocalConnectionModel.evaluate_gait <torchconn.regression.model.LocalConnectionModel.evaluate_gait>`
  -- a nearby gait's displacement, cost and efficiency from the local model alone, with standard
  errors and its distance from the data;
- :func:`propose_gait` -- one improvement step within a :class:`TrustRegion`;
- :func:`improve` -- the loop on a simulator (:class:`LoopSettings`, :class:`LoopResult`), with
  one model from every recording (:class:`PooledConnection`);
- :func:`measure_cycles` -- displacement and cost per cycle from recordings, model-free;
- :func:`finite_difference_baseline` -- the model-free optimiser; :func:`ceiling` -- the best gait
  with the true connection; :func:`exact_local_model` -- a perfect estimator's model;
- :func:`gait_table`, :func:`write_gait` -- the next gait as joint-angle time series and
  Fourier coefficients a robot can execute.

``python -m torchconn.improve`` runs the loop (``simulate``) or proposes the next gait from
recordings (``propose``).
"""

from .baselines import BaselineStep, finite_difference_baseline
from .export import gait_table, write_gait
from .loop import (
    LoopResult,
    LoopSettings,
    Round,
    circle_gait,
    excitation_gait,
    improve,
    true_objective,
    true_score,
)
from .measure import CycleMeasurement, measure_cycles
from .pooled import GaitRecording, PooledConnection, gait_recording
from .propose import (
    OBJECTIVES,
    Proposal,
    TrustRegion,
    check_trust_region,
    objective_value,
    propose_gait,
)
from .truth import Ceiling, ceiling, exact_local_model

__all__ = [
    "OBJECTIVES", "TrustRegion", "Proposal", "propose_gait", "objective_value",
    "LoopSettings", "Round", "LoopResult", "improve", "circle_gait", "true_objective",
    "true_score", "excitation_gait", "PooledConnection", "GaitRecording", "gait_recording",
    "CycleMeasurement", "measure_cycles", "Ceiling", "ceiling", "exact_local_model", "check_trust_region",
    "finite_difference_baseline", "BaselineStep", "gait_table", "write_gait",
]
