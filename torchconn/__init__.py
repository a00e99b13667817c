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

from . import io  # noqa: F401  # sets the conversion behind Trajectory.from_movement
from ._lazy import lazy_exports
from ._version import __version__

#: the public names and the modules that define them, imported on first use (``import
#: torchconn`` loads no stage but the file formats; ``torchconn.regression`` and the other
#: subpackages are imported when first read too)
_EXPORTS = {
    "NLinkSwimmer": ".physics.systems", "AffineConnectionSystem": ".physics.systems",
    "LocomotionSystem": ".physics.systems",
    "Trajectory": ".trajectory", "GroundTruth": ".trajectory", "SmoothedState": ".trajectory",
    "gaits": ".physics", "se2": ".physics",
    "simulate": ".simulation", "observe": ".simulation",
    "read_csv": ".io", "write_csv": ".io",
    "ConnectionEstimator": ".regression", "LocalConnectionModel": ".regression",
    "estimator_from_settings": ".regression",
    "RTSSmoother": ".phase", "Phaser": ".phase", "SelfConsistentCycle": ".phase",
    "TubeRegression": ".regression", "NoiseAwareRegression": ".regression",
    "TiedMetric": ".regression",
}

__all__ = [
    "__version__",
    "NLinkSwimmer", "AffineConnectionSystem", "LocomotionSystem",
    "Trajectory", "GroundTruth", "SmoothedState", "gaits", "se2",
    "simulate", "observe", "read_csv", "write_csv",
    "ConnectionEstimator", "LocalConnectionModel", "estimator_from_settings",
    "RTSSmoother", "Phaser", "SelfConsistentCycle", "TubeRegression", "NoiseAwareRegression",
    "TiedMetric",
]

__getattr__, __dir__ = lazy_exports(__name__, _EXPORTS)
