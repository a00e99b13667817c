"""Physics: the SE(2) group, locomotion systems (N-link viscous swimmer, affine toy) and gaits.

- :mod:`~torchconn.physics.se2` -- batched SE(2) algebra (hat/vee, exp/log, composition).
- :mod:`~torchconn.physics.systems` -- ``A(r)``, ``M(r)``, ``∂A/∂r`` and the curvature ``DA``.
- :mod:`~torchconn.physics.gaits` -- gait families, displacement and cost of a cycle, optimiser.
"""

from . import gaits, se2, systems
from .gaits import FourierGait, Gait, ModalGait, PolarGait, evaluate, reference_gait
from .systems import AffineConnectionSystem, LocomotionSystem, NLinkSwimmer

__all__ = [
    "se2", "systems", "gaits",
    "LocomotionSystem", "NLinkSwimmer", "AffineConnectionSystem",
    "Gait", "FourierGait", "ModalGait", "PolarGait", "evaluate", "reference_gait",
]
