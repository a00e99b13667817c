"""Physical effects: named, documented, parameterised changes to the nominal simulator.

An :class:`Effect` is one candidate explanation of a mismatch between a simulator and a
recording. It has a name, a one-line description and a few parameters in physical units whose
value ``0`` means "absent" (every parameter is a *change* from the nominal model, so the
nominal simulator is the point ``p = 0`` of every effect). It acts through up to four hooks,
each a no-op by default:

``system_kwargs(p, kwargs)``
    change the swimmer's constructor arguments (``drag_ratio``, ``link_lengths``); the physics
    is differentiable in them, so ``p`` may carry gradients.
``true_shapes(p, read, dt)`` (and its inverse ``recorded_shapes``)
    how the true shape path relates to the recorded one: ``read(s)`` returns the recorded
    shapes at times ``s``; the hook returns a new reader (``joint_bias``: ``r_true = r − b``;
    ``time_lag``: ``r_true(t) = r_rec(t + τ)``).
``body_velocity(p, heading)``
    an extra body-frame velocity ``(…, 3)`` added to ``A(r) ṙ`` (``ambient_flow``:
    ``R(θ)ᵀu``; ``body_drift``: a constant ``(v_x, v_y, ω)``). It may depend on the heading only.
``observe(p, pose)``
    what the tracker records instead of the body-frame origin (``marker_offset``).

An effect also declares the physical range of its values (:meth:`Effect.physical_range`: a time
lag is not negative, a length is positive); a fit outside it is reported as a look-alike of
something else, never as the effect.

Effects are looked up by name in :data:`REGISTRY`. A new effect is one small subclass and one
call to :func:`register`; the forward model, the fitting, the simulator wrapper and the CLI pick
it up from there. Example::

    class Buoyancy(Effect):
        name = "lateral_push"
        description = "a constant sideways push in the body frame"
        def param_specs(self, system):
            return (Param("f_y", "body lengths / time", 0.005),)
        def body_velocity(self, p, heading):
            z = torch.zeros_like(heading)
            return torch.stack([z, z + p[0], z], -1)

    register(Buoyancy())
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass

import torch
from torch import Tensor

from .systems.swimmer import NLinkSwimmer

__all__ = [
    "cubic_interp",
    "swimmer_kwargs",
    "Param",
    "Effect",
    "AmbientFlow",
    "DragRatio",
    "MarkerOffset",
    "JointBias",
    "TimeLag",
    "LinkLength",
    "BodyDrift",
    "REGISTRY",
    "register",
    "get_effect",
]

#: ``read(s) -> r``: recorded shapes at times ``s`` (``(..., N)`` -> ``(..., N, d)``)
ShapeReader = Callable[[Tensor], Tensor]


@dataclass(frozen=True)
class Param:
    """One parameter of an effect.

    Attributes:
        name: short name used in reports (``"u_x"``).
        unit: physical unit (``"body lengths / time"``).
        scale: a typical magnitude worth detecting; used to condition the fit and as the default
            magnitude of the power study. The absent value is always 0.
    """

    name: str
    unit: str
    scale: float


class Effect:
    """Base class of a physical effect (see the module docstring for the hooks).

    Subclasses set :attr:`name` and :attr:`description` and implement :meth:`param_specs` and
    whichever hooks they need. ``p`` is always a 1-D tensor of the effect's parameters in the
    order of :meth:`param_specs`, 0 meaning absent.
    """

    name: str = ""
    description: str = ""
    #: True when the effect changes how the body moves (system or velocity), False when it
    #: only changes what is recorded (shapes, tracked point)
    changes_motion: bool = True

    def param_specs(self, system) -> tuple[Param, ...]:
        """The parameters for a given nominal swimmer (some effects have one per joint)."""
        raise NotImplementedError

    def n_params(self, system) -> int:
        return len(self.param_specs(system))

    def absent(self, system, dtype=torch.float64, device=None) -> Tensor:
        """Parameters of the absent effect (zeros)."""
        return torch.zeros(self.n_params(system), dtype=dtype, device=device)

    # ------------------------------------------------------------------ hooks (no-ops)
    def system_kwargs(self, p: Tensor, kwargs: dict) -> dict:
        """Changed :class:`~torchconn.physics.systems.NLinkSwimmer` keyword arguments."""
        return kwargs

    def true_shapes(self, p: Tensor, read: ShapeReader, dt: float) -> ShapeReader:
        """A reader of the true shapes, given a reader of the recorded ones."""
        return read

    def recorded_shapes(self, p: Tensor, read: ShapeReader, dt: float) -> ShapeReader:
        """The inverse of :meth:`true_shapes`: a reader of the recorded shapes given the true
        ones (used to simulate the effect)."""
        return read

    def body_velocity(self, p: Tensor, heading: Tensor) -> Tensor | None:
        """Extra body-frame velocity ``(..., 3)`` at headings ``(...)``, or None."""
        return None

    def observe(self, p: Tensor, pose: Tensor) -> Tensor:
        """Recorded pose ``(..., 3)`` given the body frame's pose ``(..., 3)``."""
        return pose

    # ------------------------------------------------------------------ reporting
    def physical(self, p: Tensor, system) -> dict[str, Tensor]:
        """Named physical values for a report (default: the parameters themselves)."""
        return {spec.name: p[i] for i, spec in enumerate(self.param_specs(system))}

    def physical_units(self, system) -> dict[str, str]:
        return {spec.name: spec.unit for spec in self.param_specs(system)}

    def physical_range(self, system) -> dict[str, tuple[float, float]]:
        """Closed ranges ``(lo, hi)`` of the :meth:`physical` values that the effect can take
        (default: unbounded). A fit outside them is a look-alike of some other discrepancy,
        never this effect (a negative time lag, a negative length)."""
        return {}

    def out_of_range(self, p: Tensor, system) -> dict[str, float]:
        """The physical values of ``p`` outside :meth:`physical_range` (empty when in range)."""
        ranges = self.physical_range(system)
        values = {k: float(v) for k, v in self.physical(p.detach(), system).items()}
        return {k: v for k, v in values.items()
                if k in ranges and not ranges[k][0] <= v <= ranges[k][1]}

    def __repr__(self) -> str:
        return f"{type(self).__name__}(name={self.name!r})"


def _rot(heading: Tensor, v: Tensor, transpose: bool = False) -> Tensor:
    """``R(θ) v`` (or ``R(θ)ᵀ v``) for planar vectors ``v (..., 2)``."""
    c, s = torch.cos(heading), torch.sin(heading)
    if transpose:
        s = -s
    return torch.stack([c * v[..., 0] - s * v[..., 1], s * v[..., 0] + c * v[..., 1]], -1)


class AmbientFlow(Effect):
    name = "ambient_flow"
    description = (
        "a uniform current (u_x, u_y) in the world frame; in Stokes flow it advects the whole "
        "body, adding R(θ)ᵀu to the body velocity"
    )

    def param_specs(self, system):
        return (Param("u_x", "body lengths / time", 0.01),
                Param("u_y", "body lengths / time", 0.01))

    def body_velocity(self, p, heading):
        u = p.to(heading).expand(heading.shape + (2,))
        return torch.cat([_rot(heading, u, transpose=True), torch.zeros_like(u[..., :1])], -1)


class BodyDrift(Effect):
    name = "body_drift"
    description = (
        "a constant body-frame velocity (v_x, v_y, ω) not explained by shape change "
        "(thrust, or a drift of the tracking)"
    )

    def param_specs(self, system):
        return (Param("v_x", "body lengths / time", 0.005),
                Param("v_y", "body lengths / time", 0.005),
                Param("omega", "rad / time", 0.005))

    def body_velocity(self, p, heading):
        return p.to(heading).expand(heading.shape + (3,))


class DragRatio(Effect):
    name = "drag_ratio"
    description = "the true lateral/longitudinal drag ratio k differs from the nominal one"

    def param_specs(self, system):
        return (Param("delta_k", "1 (change of the drag ratio)", 0.2),)

    def system_kwargs(self, p, kwargs):
        k0 = torch.as_tensor(kwargs["drag_ratio"], dtype=p.dtype, device=p.device)
        return {**kwargs, "drag_ratio": k0 + p[0]}

    def physical(self, p, system):
        return {"drag_ratio": float(system.drag_ratio) + p[0]}

    def physical_units(self, system):
        return {"drag_ratio": "1 (lateral / longitudinal drag per unit length)"}

    def physical_range(self, system):
        return {"drag_ratio": (0.0, math.inf)}


class LinkLength(Effect):
    name = "link_length"
    description = (
        "the link lengths differ from nominal: l_i = l_i0 (1 + a_0 + a_1 x_i + a_2 (3x_i² − 1)/2), "
        "x_i ∈ [−1, 1] the link's position from tail to head (scale, taper, middle)"
    )

    def param_specs(self, system):
        names = ("scale", "taper", "middle")[: min(3, system.n_links)]
        return tuple(Param(n, "1 (fraction of the nominal lengths)", 0.05) for n in names)

    def system_kwargs(self, p, kwargs):
        l0 = torch.as_tensor(kwargs["link_lengths"], dtype=p.dtype, device=p.device)
        basis = self._basis_n(l0.shape[0], p)
        return {**kwargs, "link_lengths": l0 * (1 + basis @ p)}

    @staticmethod
    def _basis_n(n: int, like: Tensor) -> Tensor:
        """``(N, m)`` modes: constant, linear and quadratic in the link's position, on
        ``like``'s dtype and device."""
        x = torch.linspace(-1.0, 1.0, n, dtype=like.dtype, device=like.device)
        return torch.stack([torch.ones_like(x), x, 0.5 * (3 * x * x - 1)][: min(3, n)], -1)

    def physical(self, p, system):
        l0 = system.link_lengths.detach().to(p)
        lengths = l0 * (1 + self._basis_n(l0.shape[0], p) @ p)
        return {f"l{i + 1}": lengths[i] for i in range(l0.shape[0])}

    def physical_units(self, system):
        return {f"l{i + 1}": "body lengths" for i in range(system.n_links)}

    def physical_range(self, system):
        return {f"l{i + 1}": (0.0, math.inf) for i in range(system.n_links)}


class MarkerOffset(Effect):
    name = "marker_offset"
    description = (
        "the tracked point is offset by (o_x, o_y) from the body-frame origin, in the body frame"
    )
    changes_motion = False

    def param_specs(self, system):
        return (Param("o_x", "body lengths", 0.02), Param("o_y", "body lengths", 0.02))

    def observe(self, p, pose):
        off = _rot(pose[..., 2], p.to(pose).expand(pose.shape[:-1] + (2,)))
        return torch.cat([pose[..., :2] + off, pose[..., 2:]], -1)


class JointBias(Effect):
    name = "joint_bias"
    description = "the joint-angle sensors read r + b (a constant offset per joint)"
    changes_motion = False

    def param_specs(self, system):
        return tuple(Param(f"b{i + 1}", "rad", 0.05) for i in range(system.shape_dim))

    def true_shapes(self, p, read, dt):
        return lambda s: read(s) - p.to(s)

    def recorded_shapes(self, p, read, dt):
        return lambda s: read(s) + p.to(s)


class TimeLag(Effect):
    name = "time_lag"
    description = (
        "the shape stream lags the pose stream by τ: the shapes recorded at t were taken at t − τ"
    )
    changes_motion = False

    def param_specs(self, system):
        return (Param("tau", "time units", 0.05),)

    def true_shapes(self, p, read, dt):
        return lambda s: read(s + p[0].to(s))

    def recorded_shapes(self, p, read, dt):
        return lambda s: read(s - p[0].to(s))

    def physical_range(self, system):
        # a lag, not a lead: the shapes cannot be recorded before they happen
        return {"tau": (0.0, math.inf)}


REGISTRY: dict[str, Effect] = {}


def register(effect: Effect, *, replace: bool = False) -> Effect:
    """Add an effect to :data:`REGISTRY` (its ``name`` is the key); returns it.

    Raises:
        ValueError: no name, a name already registered (unless ``replace``), or no description.
    """
    if not isinstance(effect, Effect):
        raise TypeError(f"effect must be an Effect instance, got {type(effect).__name__}")
    if not effect.name or not effect.name.isidentifier():
        raise ValueError(f"an effect needs a name that is an identifier, got {effect.name!r}")
    if not effect.description:
        raise ValueError(f"effect {effect.name!r} needs a one-line description")
    if effect.name in REGISTRY and not replace:
        raise ValueError(f"an effect named {effect.name!r} is already registered; pass "
                         "replace=True to override it")
    REGISTRY[effect.name] = effect
    return effect


def get_effect(name: str | Effect) -> Effect:
    """Look an effect up by name (an :class:`Effect` passes through)."""
    if isinstance(name, Effect):
        return name
    try:
        return REGISTRY[name]
    except KeyError:
        raise ValueError(f"unknown effect {name!r}; registered: {', '.join(REGISTRY)}") from None


for _effect in (AmbientFlow(), DragRatio(), MarkerOffset(), JointBias(), TimeLag(), LinkLength(),
                BodyDrift()):
    register(_effect)


# ============================================================================ helpers of the hooks
def cubic_interp(x: Tensor, s: Tensor) -> Tensor:
    """Catmull–Rom cubic interpolation of uniform samples.

    Args:
        x: ``(B, T, C)`` samples at integer positions ``0 … T−1``.
        s: ``(N,)`` or ``(B, N)`` fractional sample positions (clamped to the record).

    Returns:
        ``(B, N, C)``; differentiable in ``x`` and in ``s``.
    """
    B, T, C = x.shape
    s = s.clamp(0, T - 1)
    i = torch.floor(s.detach()).clamp(0, T - 2).long()
    f = (s - i.to(s.dtype))[..., None]
    if s.ndim == 1:
        def take(k):
            return x[:, (i + k).clamp(0, T - 1), :]
    else:
        def take(k):
            idx = (i + k).clamp(0, T - 1)
            return x.gather(1, idx[..., None].expand(B, idx.shape[1], C))
    p0, p1, p2, p3 = take(-1), take(0), take(1), take(2)
    return p1 + 0.5 * f * (
        (p2 - p0) + f * ((2 * p0 - 5 * p1 + 4 * p2 - p3) + f * (-p0 + 3 * p1 - 3 * p2 + p3))
    )


def swimmer_kwargs(system: NLinkSwimmer) -> dict:
    """The keyword arguments that rebuild ``system`` as an :class:`NLinkSwimmer` (links, drag
    ratio, frame, link lengths, drag coefficient)."""
    return dict(n_links=system.n_links, drag_ratio=system.drag_ratio, frame=system.frame,
                link_lengths=system.link_lengths, drag_coefficient=system.drag_coefficient)
