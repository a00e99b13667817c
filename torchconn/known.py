"""Known conditions: registered effects whose parameters the experimenter knows.

A flow-tank recording is filmed in the tank's frame while the water moves; the swimmer's
physics holds relative to the water. ``--known ambient_flow:u_x=0.01,u_y=0`` states that,
and :func:`relative_to_known` rewrites the recording as it would look without the known
effects, so ``fit`` and ``discrepancy`` model it relative to the water. Any registered effect
(:mod:`torchconn.physics.effects`) can be given, through its hooks:

``body_velocity`` (ambient flow, body drift)
    the effect's world-frame velocity ``R(θ)·v`` is integrated over time (trapezoids) and
    subtracted from the pose; for a uniform flow this is exactly ``x − u·(t − t₀)``.
``true_shapes`` (joint bias, time lag)
    the shapes are replaced by the true ones (recorded shapes interpolated where needed).
``observe`` (marker offset)
    the tracked point is mapped back to the body-frame origin (fixed-point inversion).
``system_kwargs`` (drag ratio, link lengths)
    the nominal simulator changes (:func:`known_system`); the data-driven fit has no
    simulator, so ``fit`` refuses these.
"""

from __future__ import annotations

import math
import re
from collections.abc import Sequence
from dataclasses import dataclass

import torch
from torch import Tensor

from .physics.effects import Effect, cubic_interp, get_effect, swimmer_kwargs
from .physics.systems.swimmer import NLinkSwimmer
from .trajectory import Trajectory

__all__ = ["KnownEffect", "parse_known", "relative_to_known", "known_system", "changes_data"]

_SPEC = re.compile(r"^\s*([A-Za-z_][\w]*)\s*(?::\s*(.*))?$")


@dataclass(frozen=True)
class KnownEffect:
    """A registered effect with known parameters (physical units of its ``param_specs``).

    Attributes:
        name: the effect's registry name.
        params: parameter name -> value, every parameter of the effect (unstated ones 0).
    """

    name: str
    params: tuple[tuple[str, float], ...]

    @property
    def effect(self) -> Effect:
        return get_effect(self.name)

    def vector(self, dtype=torch.float64, device=None) -> Tensor:
        return torch.tensor([v for _, v in self.params], dtype=dtype, device=device)

    def to_dict(self) -> dict:
        return {"name": self.name, "params": dict(self.params)}


def parse_known(spec: str, system: NLinkSwimmer) -> KnownEffect:
    """Parse ``"name:p1=v1,p2=v2"`` (e.g. ``"ambient_flow:u_x=0.01,u_y=0"``).

    Parameters left out are 0 (absent); unknown effects or parameters raise ``ValueError``
    naming what is known.
    """
    m = _SPEC.match(spec)
    if m is None:
        raise ValueError(f"--known {spec!r}: expected EFFECT:param=value,... "
                         "(e.g. ambient_flow:u_x=0.01,u_y=0)")
    name, rest = m.group(1), m.group(2) or ""
    try:
        effect = get_effect(name)
    except (KeyError, ValueError) as err:
        raise ValueError(f"--known {spec!r}: {err}") from None
    names = [p.name for p in effect.param_specs(system)]
    values = dict.fromkeys(names, 0.0)
    for item in filter(None, (x.strip() for x in rest.split(","))):
        if "=" not in item:
            raise ValueError(f"--known {spec!r}: {item!r} is not param=value")
        key, text = (x.strip() for x in item.split("=", 1))
        if key not in values:
            raise ValueError(f"--known {spec!r}: {name} has no parameter {key!r}; its "
                             f"parameters are {', '.join(names)}")
        try:
            values[key] = float(text)
        except ValueError:
            raise ValueError(f"--known {spec!r}: {key}={text!r} is not a number") from None
        if not math.isfinite(values[key]):
            raise ValueError(f"--known {spec!r}: {key}={text!r} must be a finite number")
    return KnownEffect(name=name, params=tuple(values.items()))


def _overrides(effect: Effect, hook: str) -> bool:
    return getattr(type(effect), hook) is not getattr(Effect, hook)


def changes_data(known: KnownEffect) -> bool:
    """True when the effect acts on the recording (velocity, shapes, tracked point); False
    when it only changes the simulator's parameters."""
    e = known.effect
    return any(_overrides(e, h) for h in ("body_velocity", "true_shapes", "observe"))


def _fill(x: Tensor) -> Tensor:
    """``(B, T)`` with NaNs replaced by the previous valid value (the next one at the start)."""
    T = x.shape[-1]
    idx = torch.arange(T, device=x.device).expand_as(x)
    ok = torch.isfinite(x)
    prev = torch.cummax(torch.where(ok, idx, torch.zeros_like(idx)), -1).values
    nxt = torch.where(ok, idx, torch.full_like(idx, T)).flip(-1).cummin(-1).values.flip(-1)
    pick = torch.where(ok.gather(-1, prev), prev, nxt.clamp(max=T - 1))
    return x.gather(-1, pick)


def relative_to_known(traj: Trajectory, known: Sequence[KnownEffect],
                      system: NLinkSwimmer) -> Trajectory:
    """The recording without the known effects (see the module docstring).

    Args:
        traj: recordings ``pose (..., T, 3)``, ``r (..., T, d)``.
        known: effects with known parameters; effects that only change the simulator are
            skipped here (see :func:`known_system`).
        system: the nominal swimmer (parameter layout of the effects).
    Returns:
        a trajectory with the same fields, ``meta["known"]`` listing the effects removed.
    """
    if not known:
        return traj
    batch, T, d = traj.batch_shape, traj.n_samples, traj.shape_dim
    pose = traj.pose.reshape(-1, T, 3)
    r = traj.r.reshape(-1, T, d)
    dt = traj.dt
    t = (traj.t - traj.t[0]).to(pose.dtype)
    for k in known:
        e, p = k.effect, k.vector(pose.dtype, pose.device)
        if _overrides(e, "observe"):
            rec = pose
            for _ in range(5):  # origin = tracked point − offset(origin's heading)
                pose = rec - (e.observe(p, pose) - pose)
        if _overrides(e, "true_shapes"):
            def read(s: Tensor, r=r) -> Tensor:  # recorded shapes at times s (from t[0])
                return cubic_interp(r, s / dt)
            r = e.true_shapes(p, read, dt)(t)
        if _overrides(e, "body_velocity"):
            heading = _fill(pose[..., 2])
            v = e.body_velocity(p, heading)  # (B, T, 3) body frame
            c, s = torch.cos(heading), torch.sin(heading)
            w = torch.stack([c * v[..., 0] - s * v[..., 1], s * v[..., 0] + c * v[..., 1],
                             v[..., 2]], -1)
            steps = (w[:, 1:] + w[:, :-1]) / 2 * dt
            disp = torch.cat([torch.zeros_like(w[:, :1]), torch.cumsum(steps, 1)], 1)
            pose = pose - disp
    meta = dict(traj.meta)
    meta["known"] = [k.to_dict() for k in known]
    return traj.with_fields(pose=pose.reshape(batch + (T, 3)), r=r.reshape(batch + (T, d)),
                            meta=meta)


def known_system(system: NLinkSwimmer, known: Sequence[KnownEffect]) -> NLinkSwimmer:
    """The nominal swimmer with the known effects' simulator changes (drag ratio, lengths)."""
    kwargs = swimmer_kwargs(system)
    changed = False
    for k in known:
        if _overrides(k.effect, "system_kwargs"):
            kwargs = k.effect.system_kwargs(k.vector(), kwargs)
            changed = True
    return NLinkSwimmer(**kwargs) if changed else system
