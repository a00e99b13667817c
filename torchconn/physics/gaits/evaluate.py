"""Net displacement, cost and efficiency of one gait cycle.

The pose obeys ``ġ = g A(r) ṙ``. Each of ``n_steps`` equal steps in φ is taken with the
fourth-order Magnus method on SE(2) (two Gauss–Legendre points and one commutator), and
the steps are composed exactly on the group, so the result is accurate to O(h⁴) and
differentiable in the gait's coefficients and the system's parameters. The cost
``∫ √(ṙᵀ M ṙ) dφ`` uses the same Gauss points.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch
from torch import Tensor

from .. import se2
from ..systems.base import LocomotionSystem
from .gait import as_gait

__all__ = ["GaitMetrics", "evaluate", "displacement", "gauss_phases", "magnus_displacement",
           "gauss_cost"]

_GAUSS = (0.5 - math.sqrt(3) / 6, 0.5 + math.sqrt(3) / 6)


@dataclass(frozen=True)
class GaitMetrics:
    """One cycle's net displacement ``(3,)`` = final pose (x, y, θ), cost and efficiency."""

    displacement: Tensor
    cost: Tensor
    efficiency: Tensor


def gauss_phases(n_steps: int, dtype=torch.float64, device=None) -> tuple[float, Tensor]:
    """Step ``h = 2π/n_steps`` and the two Gauss–Legendre phases of every step, ``(n_steps, 2)``.

    Evaluate the body velocity there and pass it to :func:`magnus_displacement`.
    """
    if not isinstance(n_steps, int) or n_steps < 1:
        raise ValueError(f"n_steps must be a positive integer, got {n_steps!r}")
    h = 2 * math.pi / n_steps
    start = torch.arange(n_steps, dtype=dtype, device=device) * h
    return h, torch.stack([start + c * h for c in _GAUSS], -1)


def _gauss_samples(system: LocomotionSystem, gait, n_steps: int, with_metric: bool):
    # on the gait's device (a plain callable has none: torch's default)
    h, phi = gauss_phases(n_steps, device=getattr(gait, "device", None))  # (n, 2)
    r, r_dot = gait(phi), gait.velocity(phi)
    if with_metric:
        a, m = system.connection_and_metric(r)
    else:
        a, m = system.connection(r), None
    xi = (a @ r_dot.unsqueeze(-1)).squeeze(-1)  # (n, 2, 3)
    return h, xi, r_dot, m


def displacement(system: LocomotionSystem, gait, n_steps: int = 256) -> Tensor:
    """Net displacement ``(3,)`` of one cycle, ``g(2π)`` for ``g(0) = e``."""
    gait = as_gait(gait)
    h, xi, _, _ = _gauss_samples(system, gait, n_steps, with_metric=False)
    return magnus_displacement(xi, h)


def magnus_displacement(xi: Tensor, h: float) -> Tensor:
    """One cycle's net displacement from body velocities at the Gauss phases of each step.

    Args:
        xi: ``(..., n_steps, 2, 3)`` body velocity ``dg/dφ`` (body frame) at the phases
            :func:`gauss_phases` returns; leading dims are batch dims.
        h: the step ``2π / n_steps``.
    Returns:
        ``(..., 3)``: the final pose ``g(2π)`` for ``g(0) = e``.
    """
    x1, x2 = xi[..., 0, :], xi[..., 1, :]
    omega = 0.5 * h * (x1 + x2) + (math.sqrt(3) / 12) * h * h * se2.bracket(x1, x2)
    steps = se2.exp(omega)
    zero = torch.zeros(3, dtype=xi.dtype, device=xi.device)
    return se2.accumulate(steps, zero)[..., -1, :]


def gauss_cost(power: Tensor, h: float) -> Tensor:
    """One cycle's cost ``∫√P dφ`` from the power ``(..., n_steps, 2)`` at the Gauss phases."""
    return 0.5 * h * power.clamp_min(0).sqrt().sum((-2, -1))


def evaluate(system: LocomotionSystem, gait, n_steps: int = 256) -> GaitMetrics:
    """Displacement, cost ``∫√(ṙᵀMṙ)dφ`` and efficiency ``|(x, y)| / cost`` of one cycle.

    Args:
        system: a :class:`~torchconn.physics.systems.LocomotionSystem` (e.g. ``NLinkSwimmer(3)``).
        gait: a gait object or a callable ``phi -> r`` over ``[0, 2π)``.
        n_steps: integration steps per cycle (error ∝ n_steps⁻⁴).
    """
    gait = as_gait(gait)
    if gait.shape_dim != system.shape_dim:
        raise ValueError(
            f"gait has {gait.shape_dim} joints but the system has {system.shape_dim}"
        )
    h, xi, r_dot, m = _gauss_samples(system, gait, n_steps, with_metric=True)
    disp = magnus_displacement(xi, h)
    power = torch.einsum("...i,...ij,...j->...", r_dot, m, r_dot)
    cost = gauss_cost(power, h)
    return GaitMetrics(disp, cost, torch.linalg.vector_norm(disp[:2]) / cost)
