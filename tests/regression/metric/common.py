"""Gaits and error measures shared by the metric tests."""

import math

import torch

from torchconn.physics.gaits import FourierGait

F64 = torch.float64


def travelling_wave(d: int, amp: float = 0.8) -> FourierGait:
    """A travelling wave ``r_k = amp cos(φ − πk/d)`` (not the benchmark's gaits)."""
    k = torch.arange(d, dtype=F64)
    c = torch.zeros(3, d, dtype=F64)
    c[1], c[2] = amp * torch.cos(math.pi * k / d), amp * torch.sin(math.pi * k / d)
    return FourierGait(c)


def rel_rms(est: torch.Tensor, true: torch.Tensor, value_dims: int) -> float:
    dims = tuple(range(-value_dims, 0)) if value_dims else ()
    num = ((est - true) ** 2).sum(dims) if dims else (est - true) ** 2
    den = (true**2).sum(dims) if dims else true**2
    return float((num.mean() / den.mean()).sqrt())
