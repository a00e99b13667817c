"""Gaits and recordings shared by tests in several folders."""

from __future__ import annotations

import math

import torch
from torch import Tensor

from torchconn import ConnectionEstimator, NLinkSwimmer
from torchconn.noise import estimate_noise
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


def gait_noise(traj, floor="low_rate"):
    """:func:`estimate_noise` of the shapes with each trial's estimated cycle (as
    ``NoiseAwareRegression`` unpooled: with ``noise_floor="low_rate"``, its floor shaped by
    the gait at few samples per cycle, or ``floor="flat"``, the default, which uses the
    cycle for the joints' correlation)."""
    from torchconn.phase.limit_cycle import phase_rate

    est = ConnectionEstimator()
    prep = est.prepare(traj)
    cycle = est.cycle.fit(prep)
    per_cycle = 2 * math.pi / (phase_rate(prep.phase, prep.dt) * prep.dt)
    return estimate_noise(traj.r, cycle=cycle.gamma, samples_per_cycle=per_cycle, floor=floor)


def wobbled_gait(base: FourierGait, eps: float) -> FourierGait:
    """``base`` plus a change of size ``eps`` in harmonics 1 and 2 (within the tube's order)."""
    c = torch.cat([base.coeffs, torch.zeros(max(5 - base.coeffs.shape[0], 0), 2,
                                            dtype=torch.float64)])
    c[1] += eps * torch.tensor([0.6, -0.3], dtype=torch.float64)
    c[4] += eps * torch.tensor([0.5, 0.4], dtype=torch.float64)
    return FourierGait(c)
