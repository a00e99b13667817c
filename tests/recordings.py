"""Gaits and recordings shared by tests in several folders."""

from __future__ import annotations

import math

import torch
from torch import Tensor

from torchconn import NLinkSwimmer
from torchconn.physics.gaits import FourierGait
from torchconn.regression.model import LocalConnectionModel

F64 = torch.float64


def wave_gait(n_joints: int = 4, radius: float = 0.7) -> FourierGait:
    """A travelling wave of ``n_joints`` joint angles of amplitude ``radius`` (rad): the joints lag
    each other by ``2π / max(n_joints, 4)`` at the first harmonic."""
    coeffs = torch.zeros(3, n_joints, dtype=F64)
    lag = torch.arange(n_joints, dtype=F64) * (2 * math.pi / max(n_joints, 4))
    coeffs[1], coeffs[2] = radius * torch.cos(lag), radius * torch.sin(lag)
    return FourierGait(coeffs)


#: phases along a cycle, 48 of them
PHI = torch.linspace(0, 2 * math.pi, 49, dtype=F64)[:-1]


def five_link_a_error(model: LocalConnectionModel) -> Tensor:
    """Relative RMS error ``(...)`` of ``Â`` along the fitted cycle against the swimmer's."""
    truth = NLinkSwimmer(5).connection(model.gamma_at(PHI))
    a = model.connection(PHI)
    return ((a - truth).square().sum((-3, -2, -1)) / truth.square().sum((-3, -2, -1))).sqrt()
