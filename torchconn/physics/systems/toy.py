"""A toy system whose connection is affine in shape, so its first-order Taylor model is exact.

``A(r) = A0 + Σ_j A1[..., j] r_j`` and a constant metric ``M``. Any estimator of
``(A(γ), ∂A/∂r(γ))`` must recover it exactly from noise-free data, whatever the tube width.
"""

from __future__ import annotations

import torch
from torch import Tensor

from .base import LocomotionSystem

__all__ = ["AffineConnectionSystem"]


class AffineConnectionSystem(LocomotionSystem):
    """``A(r) = A0 + A1 · r`` with ``A0 (3, d)``, ``A1 (3, d, d)`` (``[k, i, j] = ∂A^k_i/∂r_j``).

    Args:
        a0: ``(3, d)`` connection at ``r = 0``.
        a1: ``(3, d, d)`` constant Jacobian.
        metric: ``(d, d)`` symmetric positive-definite constant metric (identity by default).
    """

    def __init__(self, a0, a1, metric=None):
        a0 = torch.as_tensor(a0, dtype=torch.float64)
        a1 = torch.as_tensor(a1, dtype=torch.float64)
        if a0.ndim != 2 or a0.shape[0] != 3:
            raise ValueError(f"a0 must have shape (3, d), got {tuple(a0.shape)}")
        d = a0.shape[1]
        if tuple(a1.shape) != (3, d, d):
            raise ValueError(f"a1 must have shape (3, {d}, {d}), got {tuple(a1.shape)}")
        m = torch.eye(d, dtype=torch.float64) if metric is None else torch.as_tensor(metric)
        if tuple(m.shape) != (d, d) or not torch.allclose(m, m.T):
            raise ValueError(f"metric must be a symmetric ({d}, {d}) matrix")
        self.shape_dim = d
        self.a0, self.a1, self.m = a0, a1, m.to(torch.float64)

    @classmethod
    def random(cls, d: int = 2, scale: float = 0.3, seed: int = 0) -> "AffineConnectionSystem":
        """A reproducible random instance with ``d`` joints."""
        gen = torch.Generator().manual_seed(seed)
        a0 = torch.randn(3, d, generator=gen, dtype=torch.float64)
        a1 = scale * torch.randn(3, d, d, generator=gen, dtype=torch.float64)
        q = torch.randn(d, d, generator=gen, dtype=torch.float64)
        return cls(a0, a1, q @ q.T + d * torch.eye(d, dtype=torch.float64))

    def _connection(self, r: Tensor) -> Tensor:
        a0 = self.a0.to(r.dtype).to(r.device)
        a1 = self.a1.to(r.dtype).to(r.device)
        return a0 + torch.einsum("kij,...j->...ki", a1, r)

    def _metric(self, r: Tensor) -> Tensor:
        m = self.m.to(r.dtype).to(r.device)
        return m.expand(r.shape[:-1] + m.shape)
