"""Gaits: closed shape curves over one period φ ∈ [0, 2π).

A gait is anything with ``shape_dim``, ``__call__(phi) -> r`` and ``velocity(phi) -> dr/dφ``
(both ``(...,) -> (..., d)``, on ``phi``'s device). :class:`FourierGait` (one Fourier series per
joint) and :class:`ModalGait` (``r = Φ a(φ)``, a Fourier series in a few shape modes) are the
concrete kinds; :class:`CallableGait` wraps a user's function and differentiates it by autograd.
The concrete kinds also say where their parameters live (``device``), which is where a gait is
evaluated when no phases are given (:func:`~torchconn.physics.gaits.evaluate.evaluate`).
"""

from __future__ import annotations

import math
from typing import Callable, Protocol

import torch
from torch import Tensor

from ...phase.fourier import FourierSeries

__all__ = ["Gait", "FourierGait", "ModalGait", "PolarGait", "CallableGait", "as_gait"]


class Gait(Protocol):
    shape_dim: int

    def __call__(self, phi: Tensor) -> Tensor: ...

    def velocity(self, phi: Tensor) -> Tensor: ...


class FourierGait:
    """``r(φ) = a0 + Σ_k a_k cos kφ + b_k sin kφ`` per joint.

    Args:
        coeffs: ``(2K+1, d)`` rows ordered ``[a0, a1, b1, a2, b2, ...]`` (the layout of
            :class:`torchconn.phase.fourier.FourierSeries`). May require grad (gait optimisation).
    """

    def __init__(self, coeffs):
        if not isinstance(coeffs, Tensor):
            coeffs = torch.as_tensor(coeffs, dtype=torch.float64)
        if coeffs.ndim != 2 or coeffs.shape[0] % 2 != 1:
            raise ValueError(f"coeffs must have shape (2K+1, d), got {tuple(coeffs.shape)}")
        self.series = FourierSeries(coeffs, value_ndim=1)
        self.coeffs = coeffs
        self.order = self.series.order
        self.shape_dim = coeffs.shape[1]

    @property
    def device(self) -> torch.device:
        return self.coeffs.device

    def __call__(self, phi: Tensor) -> Tensor:
        """``(...,) -> (..., d)``."""
        return self.series(torch.as_tensor(phi, dtype=self.coeffs.dtype))

    def velocity(self, phi: Tensor) -> Tensor:
        """``dr/dφ``: ``(...,) -> (..., d)``."""
        return self.series.derivative()(torch.as_tensor(phi, dtype=self.coeffs.dtype))

    def reversed(self) -> "FourierGait":
        """The same loop run backwards, ``r(-φ)``."""
        c = self.coeffs.clone()
        c[2::2] = -c[2::2]
        return FourierGait(c)

    def __repr__(self) -> str:
        return f"FourierGait(order={self.order}, d={self.shape_dim})"


class ModalGait:
    """``r(φ) = Φ a(φ)``: a gait ``a`` in a plane of shape modes ``Φ (d, m)``.

    Args:
        modes: ``(d, m)`` mode shapes as columns.
        plane_gait: a gait in the ``m``-dimensional mode coordinates (e.g. a :class:`PolarGait`
            or :class:`FourierGait`), or a ``(2K+1, m)`` array of modal Fourier coefficients.
    """

    def __init__(self, modes, plane_gait):
        modes = torch.as_tensor(modes, dtype=torch.float64)
        if not hasattr(plane_gait, "velocity"):
            plane_gait = FourierGait(plane_gait)
        if modes.ndim != 2 or plane_gait.shape_dim != modes.shape[1]:
            raise ValueError(
                f"modes must have shape (d, m) with m = {plane_gait.shape_dim} (the plane gait's "
                f"dimension), got {tuple(modes.shape)}"
            )
        self.modes, self.plane_gait = modes, plane_gait
        self.shape_dim = modes.shape[0]

    @property
    def device(self) -> torch.device:
        return self.modes.device

    def __call__(self, phi: Tensor) -> Tensor:
        return self.plane_gait(phi) @ self.modes.to(dtype=phi.dtype, device=phi.device).T

    def velocity(self, phi: Tensor) -> Tensor:
        return self.plane_gait.velocity(phi) @ self.modes.to(dtype=phi.dtype, device=phi.device).T

    def __repr__(self) -> str:
        return f"ModalGait(d={self.shape_dim}, plane={self.plane_gait!r})"


class PolarGait:
    """A planar loop that is star-shaped about a centre, hence always simple (winding once).

    ``r(φ) = c + ρ(φ) (cos sφ, sin sφ)`` with ``ρ = ρ_max · sigmoid(f(φ))``, ``f`` a Fourier
    series and ``s = ±1`` the direction (+1 counter-clockwise). Gait optimisation uses this
    family: it cannot add the extra sub-loops that would make "displacement per cycle"
    unbounded, and ``ρ_max`` keeps it inside the physically meaningful shapes.

    Args:
        center: ``(2,)``; radius_logit: ``(2K+1,)`` Fourier coefficients of ``f``;
        direction: ±1; max_radius: ``ρ_max``.
    """

    shape_dim = 2

    def __init__(self, center, radius_logit, direction: int = 1, max_radius: float = math.pi):
        self.center = torch.as_tensor(center, dtype=torch.float64) if not isinstance(
            center, Tensor) else center
        logit = torch.as_tensor(radius_logit, dtype=torch.float64) if not isinstance(
            radius_logit, Tensor) else radius_logit
        if self.center.shape != (2,) or logit.ndim != 1 or logit.shape[0] % 2 != 1:
            raise ValueError("center must have shape (2,) and radius_logit (2K+1,)")
        if not max_radius > 0:
            raise ValueError(f"max_radius must be positive, got {max_radius!r}")
        if direction not in (1, -1):
            raise ValueError(f"direction must be +1 or -1, got {direction!r}")
        self.logit = FourierGait(logit[:, None])
        self.direction, self.max_radius = direction, float(max_radius)

    @property
    def device(self) -> torch.device:
        return self.center.device

    def _polar(self, phi: Tensor) -> tuple[Tensor, Tensor, Tensor]:
        rho = self.max_radius * torch.sigmoid(self.logit(phi)[..., 0])
        ang = self.direction * phi
        unit = torch.stack([torch.cos(ang), torch.sin(ang)], -1)
        return rho, unit, ang

    def __call__(self, phi: Tensor) -> Tensor:
        phi = torch.as_tensor(phi, dtype=torch.float64)
        rho, unit, _ = self._polar(phi)
        return self.center.to(dtype=phi.dtype, device=phi.device) + rho[..., None] * unit

    def velocity(self, phi: Tensor) -> Tensor:
        phi = torch.as_tensor(phi, dtype=torch.float64)
        rho, unit, _ = self._polar(phi)
        rho_dot = rho * (1 - rho / self.max_radius) * self.logit.velocity(phi)[..., 0]
        normal = self.direction * torch.stack([-unit[..., 1], unit[..., 0]], -1)
        return rho_dot[..., None] * unit + rho[..., None] * normal

    def __repr__(self) -> str:
        return (f"PolarGait(order={self.logit.order}, direction={self.direction:+d}, "
                f"max_radius={self.max_radius:g})")


class CallableGait:
    """A user's function ``phi -> r`` (torch ops, ``(...,) -> (..., d)``), differentiated by autograd."""

    def __init__(self, fn: Callable[[Tensor], Tensor], shape_dim: int | None = None):
        self.fn = fn
        if shape_dim is None:
            shape_dim = fn(torch.zeros((), dtype=torch.float64)).shape[-1]
        self.shape_dim = shape_dim

    def __call__(self, phi: Tensor) -> Tensor:
        return self.fn(phi)

    def velocity(self, phi: Tensor) -> Tensor:
        flat = phi.reshape(-1)
        vel = torch.func.vmap(torch.func.jacfwd(self.fn))(flat)
        return vel.reshape(phi.shape + (self.shape_dim,))


def as_gait(gait) -> Gait:
    """Accept a gait object or a plain callable ``phi -> r``."""
    if hasattr(gait, "velocity") and hasattr(gait, "shape_dim"):
        return gait
    if callable(gait):
        return CallableGait(gait)
    raise TypeError(f"gait must be a gait object or a callable phi -> r, got {type(gait).__name__}")
