"""Gaits, their displacement/cost/efficiency, the reference gaits and the gait optimiser."""

from .evaluate import (
    GaitMetrics,
    displacement,
    evaluate,
    gauss_cost,
    gauss_phases,
    magnus_displacement,
)
from .gait import CallableGait, FourierGait, Gait, ModalGait, PolarGait, as_gait
from .reference import nine_link_modes, optimised_gait, reference_gait, three_link_gait

__all__ = [
    "Gait", "FourierGait", "ModalGait", "PolarGait", "CallableGait", "as_gait",
    "GaitMetrics", "evaluate", "displacement", "gauss_phases", "magnus_displacement", "gauss_cost",
    "three_link_gait", "nine_link_modes", "reference_gait", "optimised_gait",
]
