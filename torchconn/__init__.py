"""torchconn: batched data-driven estimation of local connections around gaits.

The package's folders are the pipeline's stages:

================  =====================================================================
``physics``       SE(2), locomotion systems (N-link viscous swimmer, affine toy), gaits
``simulation``    batched Stratonovich rollouts, the motion-capture observation model
``phase``         RTS smoother, Phaser, the limit cycle, Fourier series in phase
``regression``    phase binning, weighted least squares, connection and metric regressions,
                  the local model and the :class:`ConnectionEstimator`
``evaluation``    ground-truth / data-driven / analytic / template models and their errors
``sweep``         the paper's experiments: configs, resumable store, claims, figures
``discrepancy``   where simulator and data disagree, and which physical effect is missing
``improve``       better gaits from data: propose and verify gait improvements with the model
``io``            trajectory files (CSV, NPZ), tracking files (SLEAP, DeepLabCut, WCON,
                  points) and their conversion, the checks before fitting
================  =====================================================================

``trajectory`` holds the :class:`Trajectory` container that flows through every stage.
"""

from ._version import __version__
from .io import read_csv, write_csv
from .phase import Phaser, RTSSmoother, SelfConsistentCycle
from .physics import gaits, se2
from .physics.systems import AffineConnectionSystem, LocomotionSystem, NLinkSwimmer
from .regression import (
    ConnectionEstimator,
    LocalConnectionModel,
    NoiseAwareRegression,
    TiedMetric,
    TubeRegression,
    estimator_from_settings,
)
from .simulation import observe, simulate
from .trajectory import GroundTruth, SmoothedState, Trajectory

__all__ = [
    "__version__",
    "NLinkSwimmer", "AffineConnectionSystem", "LocomotionSystem",
    "Trajectory", "GroundTruth", "SmoothedState", "gaits", "se2",
    "simulate", "observe", "read_csv", "write_csv",
    "ConnectionEstimator", "LocalConnectionModel", "estimator_from_settings",
    "RTSSmoother", "Phaser", "SelfConsistentCycle", "TubeRegression", "NoiseAwareRegression",
    "TiedMetric",
]
