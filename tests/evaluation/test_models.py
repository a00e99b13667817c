"""The evaluation models' simulator terms along a cycle, against the simulator itself."""

from __future__ import annotations

import math

import torch

from torchconn import NLinkSwimmer
from torchconn.evaluation.models import simulator_on_cycle
from torchconn.phase.fourier import FourierSeries

DT = torch.float64


class _Cycle:
    """The part of a fitted model that :func:`simulator_on_cycle` reads: its cycle ``γ(φ)``."""

    def __init__(self, gamma: FourierSeries):
        self.gamma = gamma
        self.batch_shape = gamma.batch_shape

    def gamma_at(self, phase):
        return self.gamma(phase)


def test_simulator_on_cycle_is_the_simulator_at_the_cycle():
    """A(γ(φ)) and ∂A/∂r(γ(φ)) interpolated in phase equal the swimmer's own connection and
    autograd Jacobian at arbitrary (off-grid, unwrapped) phases of two trials' cycles."""
    gen = torch.Generator().manual_seed(5)
    system = NLinkSwimmer(5)
    coeffs = 0.3 * torch.randn(2, 7, 4, generator=gen, dtype=DT) / torch.arange(1, 8)[:, None]
    cycle = _Cycle(FourierSeries(coeffs, 1))  # order 3, two trials
    phase = 4 * math.pi * torch.rand(2, 40, generator=gen, dtype=DT) - math.pi
    terms = simulator_on_cycle(system, cycle)(phase)  # (2, 40, 3, 4, 5)
    gamma = cycle.gamma(phase)
    a, da = system.connection(gamma), system.connection_jacobian(gamma)
    torch.testing.assert_close(terms[..., 0], a, rtol=0, atol=1e-10 * float(a.abs().max()))
    torch.testing.assert_close(terms[..., 1:], da, rtol=0, atol=1e-10 * float(da.abs().max()))
