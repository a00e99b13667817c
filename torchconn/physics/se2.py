"""SE(2), batched over any leading dimensions.

Poses are ``g = (x, y, theta)`` with shape ``(..., 3)``; Lie-algebra elements (body
velocities, twists) are ``xi = (v_x, v_y, omega)`` with shape ``(..., 3)``. Matrices are
the homogeneous 3x3 form ``[[R, p], [0, 1]]``. Every function follows the dtype and
device of its inputs and is differentiable by autograd.
"""

from __future__ import annotations

import torch
from torch import Tensor

from .._checks import last_dim

__all__ = [
    "hat",
    "vee",
    "to_matrix",
    "from_matrix",
    "exp",
    "log",
    "compose",
    "inverse",
    "adjoint",
    "bracket",
    "relative",
    "integrate",
    "accumulate",
    "wrap_angle",
]

_SMALL = 1e-4  # below this |omega| the series forms of exp/log are used


def wrap_angle(a: Tensor) -> Tensor:
    """Wrap angles to [-pi, pi)."""
    return torch.remainder(a + torch.pi, 2 * torch.pi) - torch.pi


def hat(xi: Tensor) -> Tensor:
    """se(2) vector ``(..., 3)`` -> matrix ``(..., 3, 3)``."""
    last_dim(xi, 3, "xi")
    vx, vy, w = xi.unbind(-1)
    z = torch.zeros_like(w)
    return torch.stack(
        [
            torch.stack([z, -w, vx], -1),
            torch.stack([w, z, vy], -1),
            torch.stack([z, z, z], -1),
        ],
        -2,
    )


def vee(X: Tensor) -> Tensor:
    """se(2) matrix ``(..., 3, 3)`` -> vector ``(..., 3)``."""
    if X.shape[-2:] != (3, 3):
        raise ValueError(f"X must have shape (..., 3, 3), got {tuple(X.shape)}")
    return torch.stack([X[..., 0, 2], X[..., 1, 2], X[..., 1, 0]], -1)


def to_matrix(g: Tensor) -> Tensor:
    """Pose ``(..., 3)`` -> homogeneous matrix ``(..., 3, 3)``."""
    last_dim(g, 3, "g")
    x, y, th = g.unbind(-1)
    c, s = torch.cos(th), torch.sin(th)
    z, o = torch.zeros_like(x), torch.ones_like(x)
    return torch.stack(
        [torch.stack([c, -s, x], -1), torch.stack([s, c, y], -1), torch.stack([z, z, o], -1)],
        -2,
    )


def from_matrix(G: Tensor) -> Tensor:
    """Homogeneous matrix ``(..., 3, 3)`` -> pose ``(..., 3)`` (theta in [-pi, pi])."""
    return torch.stack([G[..., 0, 2], G[..., 1, 2], torch.atan2(G[..., 1, 0], G[..., 0, 0])], -1)


def _v_coeffs(w: Tensor) -> tuple[Tensor, Tensor]:
    """Coefficients a = sin(w)/w and b = (1 - cos w)/w of the SE(2) left Jacobian V."""
    small = w.abs() < _SMALL
    ws = torch.where(small, torch.ones_like(w), w)
    w2 = w * w
    a = torch.where(small, 1 - w2 / 6 + w2 * w2 / 120, torch.sin(ws) / ws)
    b = torch.where(small, w / 2 - w * w2 / 24 + w * w2 * w2 / 720, (1 - torch.cos(ws)) / ws)
    return a, b


def exp(xi: Tensor) -> Tensor:
    """Group exponential: twist ``(..., 3)`` -> pose ``(..., 3)``.

    ``exp(xi)`` is the pose reached after unit time at constant body velocity ``xi``.
    """
    last_dim(xi, 3, "xi")
    vx, vy, w = xi.unbind(-1)
    a, b = _v_coeffs(w)
    return torch.stack([a * vx - b * vy, b * vx + a * vy, w], -1)


def log(g: Tensor) -> Tensor:
    """Group logarithm: pose ``(..., 3)`` -> twist ``(..., 3)``; theta is wrapped to (-pi, pi]."""
    last_dim(g, 3, "g")
    x, y, th = g.unbind(-1)
    th = torch.atan2(torch.sin(th), torch.cos(th))
    a, b = _v_coeffs(th)
    det = a * a + b * b
    return torch.stack([(a * x + b * y) / det, (-b * x + a * y) / det, th], -1)


def compose(g: Tensor, h: Tensor) -> Tensor:
    """Group product ``g h`` of poses ``(..., 3)`` (broadcasting); theta is not wrapped."""
    last_dim(g, 3, "g")
    last_dim(h, 3, "h")
    x, y, th = g.unbind(-1)
    hx, hy, hth = h.unbind(-1)
    c, s = torch.cos(th), torch.sin(th)
    return torch.stack([x + c * hx - s * hy, y + s * hx + c * hy, th + hth], -1)


def inverse(g: Tensor) -> Tensor:
    """Group inverse of poses ``(..., 3)``."""
    last_dim(g, 3, "g")
    x, y, th = g.unbind(-1)
    c, s = torch.cos(th), torch.sin(th)
    return torch.stack([-c * x - s * y, s * x - c * y, -th], -1)


def relative(g: Tensor, h: Tensor) -> Tensor:
    """``g^{-1} h``: pose of ``h`` seen from ``g``."""
    return compose(inverse(g), h)


def adjoint(g: Tensor) -> Tensor:
    """Adjoint matrix ``Ad_g`` ``(..., 3, 3)``, so that ``g hat(xi) g^-1 = hat(Ad_g xi)``."""
    last_dim(g, 3, "g")
    x, y, th = g.unbind(-1)
    c, s = torch.cos(th), torch.sin(th)
    z, o = torch.zeros_like(x), torch.ones_like(x)
    return torch.stack(
        [torch.stack([c, -s, y], -1), torch.stack([s, c, -x], -1), torch.stack([z, z, o], -1)],
        -2,
    )


def bracket(a: Tensor, b: Tensor) -> Tensor:
    """se(2) commutator ``[a, b] = vee(hat(a) hat(b) - hat(b) hat(a))`` for ``(..., 3)`` twists."""
    last_dim(a, 3, "a")
    last_dim(b, 3, "b")
    ax, ay, aw = a.unbind(-1)
    bx, by, bw = b.unbind(-1)
    return torch.stack([ay * bw - by * aw, bx * aw - ax * bw, torch.zeros_like(aw)], -1)


def integrate(
    xi: Tensor, dt: float | Tensor, g0: Tensor | None = None, method: str = "exp"
) -> Tensor:
    """Integrate a body-velocity sequence into poses.

    Args:
        xi: body velocities ``(..., T, 3)`` sampled at the start of each of the ``T`` intervals
            (``method="exp"``), or at the ``T`` sample times (``method="midpoint"``).
        dt: sampling interval.
        g0: initial pose ``(..., 3)``; identity if omitted.
        method: ``"exp"`` -- piecewise-constant ``g_{n+1} = g_n exp(xi_n dt)`` (first order);
            ``"midpoint"`` -- ``g_{n+1} = g_n exp((xi_n + xi_{n+1}) dt / 2)``, second order and
            the form consistent with a Stratonovich (midpoint) reading of ``dg = g xi dt``.

    Returns:
        poses ``(..., T + 1, 3)`` for ``"exp"`` (g0 included) or ``(..., T, 3)`` for
        ``"midpoint"`` (poses at the sample times, the first one g0). Heading is unwrapped.
    """
    last_dim(xi, 3, "xi")
    if xi.ndim < 2:
        raise ValueError(f"xi must have shape (..., T, 3), got {tuple(xi.shape)}")
    if method == "exp":
        steps = exp(xi * dt)
    elif method == "midpoint":
        steps = exp(0.5 * (xi[..., 1:, :] + xi[..., :-1, :]) * dt)
    else:
        raise ValueError(f"method must be 'exp' or 'midpoint', got {method!r}")
    if g0 is None:
        g0 = torch.zeros(xi.shape[:-2] + (3,), dtype=xi.dtype, device=xi.device)
    return accumulate(steps, g0)


def accumulate(steps: Tensor, g0: Tensor) -> Tensor:
    """Poses ``g0, g0 s_0, g0 s_0 s_1, ...`` for relative steps ``(..., K, 3)`` -> ``(..., K+1, 3)``.

    Headings add, so they are cumulated exactly; positions are the cumulative sum of each step's
    translation rotated by the heading before it.
    """
    g0 = g0.expand(steps.shape[:-2] + (3,))
    th = torch.cat([g0[..., None, 2], g0[..., None, 2] + torch.cumsum(steps[..., 2], -1)], -1)
    c, s = torch.cos(th[..., :-1]), torch.sin(th[..., :-1])
    dx = c * steps[..., 0] - s * steps[..., 1]
    dy = s * steps[..., 0] + c * steps[..., 1]
    x = torch.cat([g0[..., None, 0], g0[..., None, 0] + torch.cumsum(dx, -1)], -1)
    y = torch.cat([g0[..., None, 1], g0[..., None, 1] + torch.cumsum(dy, -1)], -1)
    return torch.stack([x, y, th], -1)
