"""Locomotion systems: the viscous N-link swimmer and a toy with an exact affine connection."""

from .base import LocomotionSystem, check_shapes
from .swimmer import FRAMES, NLinkSwimmer
from .toy import AffineConnectionSystem

__all__ = ["LocomotionSystem", "NLinkSwimmer", "AffineConnectionSystem", "FRAMES", "check_shapes"]
