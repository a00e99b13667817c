"""Gaits and recordings shared by tests in several folders."""

import math

import torch

from torchconn.physics.gaits import FourierGait

F64 = torch.float64


def wave_gait(n_joints: int = 4, radius: float = 0.7) -> FourierGait:
    """A travelling wave of ``n_joints`` joint angles of amplitude ``radius`` (rad): the joints lag
    each other by ``2π / max(n_joints, 4)`` at the first harmonic."""
    coeffs = torch.zeros(3, n_joints, dtype=F64)
    lag = torch.arange(n_joints, dtype=F64) * (2 * math.pi / max(n_joints, 4))
    coeffs[1], coeffs[2] = radius * torch.cos(lag), radius * torch.sin(lag)
    return FourierGait(coeffs)
