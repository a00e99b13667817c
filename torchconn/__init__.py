"""torchconn: batched data-driven estimation of local connections around gaits.

The pipeline's stages, one module each: ``systems`` (the swimmer), ``gaits``, ``rollout``
(simulate), ``observe``, ``phase``, ``smoothing``, ``limit_cycle``, ``regression`` and
``estimator`` (regress), ``evaluation``, ``sweep``, ``discrepancy``.
"""

from . import gaits, se2
from .data import GroundTruth, SmoothedState, Trajectory
from .estimator import ConnectionEstimator, EstimatorSettings
from .io import read_csv, write_csv
from .model import LocalConnectionModel
from .observe import observe
from .rollout import simulate
from .systems import AffineConnectionSystem, LocomotionSystem, NLinkSwimmer

__all__ = [
    "NLinkSwimmer", "AffineConnectionSystem", "LocomotionSystem",
    "Trajectory", "GroundTruth", "SmoothedState", "gaits", "se2",
    "simulate", "observe", "read_csv", "write_csv",
    "ConnectionEstimator", "EstimatorSettings", "LocalConnectionModel",
]
__version__ = "0.1.0"
