"""Simulate recordings with effects switched on (for tests, the power study and users).

:func:`simulate_with_effects` wraps :func:`torchconn.simulation.rollout.simulate`: system effects change the
swimmer, velocity effects enter through the rollout's ``drift`` hook (vectorised, heading-only),
and the recording effects are applied to what is recorded -- the shape stream through each
effect's ``recorded_shapes`` (on a recording ``upsample`` times finer than the output, so a time
lag reads the true path between samples), the tracked point through ``observe`` -- before
:func:`torchconn.simulation.observe.observe` adds the observation noise.
"""

from __future__ import annotations

import math
from collections.abc import Mapping

import torch
from torch import Tensor

from ..physics import se2
from ..physics.effects import Effect, cubic_interp, get_effect, swimmer_kwargs
from ..physics.systems.base import LocomotionSystem
from ..physics.systems.swimmer import NLinkSwimmer
from ..simulation.observe import observe
from ..simulation.rollout import interval_power, simulate
from ..trajectory import GroundTruth, Trajectory

__all__ = ["simulate_with_effects", "effect_parameters", "EffectDrift", "LateralSlipSwimmer",
           "simulate_inertial_relaxation"]


def effect_parameters(effects: Mapping | None, system: LocomotionSystem, *,
                      device: torch.device | str | None = None) -> dict[str, Tensor]:
    """Normalise ``{name: values}`` to ``{name: (n_params,) float64 tensor}`` on ``device``
    (default: torch's default device, or a tensor's own).

    ``values`` is a mapping from the effect's parameter names (see
    :meth:`Effect.param_specs`) to numbers -- missing ones are 0 (absent) -- or a sequence /
    tensor in that order.
    """
    out: dict[str, Tensor] = {}
    for name, values in (effects or {}).items():
        effect = get_effect(name)
        specs = effect.param_specs(system)
        if isinstance(values, Mapping):
            names = [s.name for s in specs]
            unknown = set(values) - set(names)
            if unknown:
                raise ValueError(f"effect {effect.name!r} has parameters {names}, got "
                                 f"{sorted(unknown)}")
            p = torch.tensor([float(values.get(n, 0.0)) for n in names], dtype=torch.float64,
                             device=device)
        else:
            p = torch.as_tensor(values, dtype=torch.float64, device=device).reshape(-1)
            if p.numel() != len(specs):
                raise ValueError(f"effect {effect.name!r} takes {len(specs)} parameter(s) "
                                 f"{[s.name for s in specs]}, got {p.numel()}")
        out[effect.name] = p
    return out


class EffectDrift:
    """The rollout ``drift`` hook of a set of velocity effects (heading-only, vectorised)."""

    heading_only = True

    def __init__(self, params: dict[str, Tensor]):
        self.params = {n: p for n, p in params.items()
                       if type(get_effect(n)).body_velocity is not Effect.body_velocity}

    def __bool__(self) -> bool:
        return bool(self.params)

    def __call__(self, pose: Tensor, t) -> Tensor:
        heading = pose[..., 2]
        total = torch.zeros(heading.shape + (3,), dtype=heading.dtype, device=heading.device)
        for name, p in self.params.items():
            total = total + get_effect(name).body_velocity(p.to(heading), heading)
        return total

    def __repr__(self) -> str:
        return f"EffectDrift({ {n: p.tolist() for n, p in self.params.items()} })"


def augmented_system(system: LocomotionSystem, params: dict[str, Tensor]) -> LocomotionSystem:
    """``system`` with the system effects of ``params`` applied."""
    active = [n for n in params if type(get_effect(n)).system_kwargs is not Effect.system_kwargs]
    if not active:
        return system
    if not isinstance(system, NLinkSwimmer):
        raise ValueError(f"effects {active} change the swimmer and need an NLinkSwimmer")
    kwargs = swimmer_kwargs(system)
    for n in active:
        kwargs = get_effect(n).system_kwargs(params[n], kwargs)
    return NLinkSwimmer(**{k: (v.detach() if isinstance(v, Tensor) else v)
                           for k, v in kwargs.items()})


def simulate_with_effects(
    system: LocomotionSystem,
    gait,
    effects: Mapping | None = None,
    *,
    eta,
    alpha=0.05,
    n_cycles: int = 20,
    samples_per_cycle: int = 64,
    substeps: int = 8,
    seeds,
    omega: float = 0.0,
    dropout: float = 0.0,
    phase0=0.0,
) -> Trajectory:
    """Noisy gait-following trials of ``system`` with physical effects switched on.

    Args:
        system: the nominal swimmer.
        gait: reference gait.
        effects: ``{effect name: parameter values}`` (see :func:`effect_parameters`), e.g.
            ``{"ambient_flow": {"u_x": 0.01}}``; None or ``{}`` for the nominal model.
        eta, alpha, n_cycles, samples_per_cycle, substeps, seeds, phase0: as in
            :func:`torchconn.simulation.rollout.simulate` (``substeps`` even; the rollout records every
            other fine step so recording effects can read between samples); everything is
            made on ``eta``'s device when it is a tensor (CPU otherwise).
        omega: observation-noise standard deviation (:func:`torchconn.simulation.observe.observe`).
        dropout: probability of a lost sample.

    Returns:
        A :class:`~torchconn.trajectory.Trajectory` of the recorded data, with ``truth`` holding the
        true (noise-free, effect-free recording) pose, shapes and body velocity, and
        ``meta["effects"]`` the effects' parameters.
    """
    # on the rollout's device: eta's, as in simulate()
    like = isinstance(eta, Tensor) and eta.is_floating_point()
    device = eta.device if like else torch.device("cpu")
    params = effect_parameters(effects, system, device=device)
    if substeps % 2 or substeps < 2:
        raise ValueError(f"substeps must be even and >= 2, got {substeps}")
    U = substeps // 2  # recorded fine samples per output sample
    sys_eff = augmented_system(system, params)
    drift = EffectDrift(params)
    shifts = any(type(get_effect(n)).recorded_shapes is not Effect.recorded_shapes
                 for n in params)
    pad = 1 if shifts else 0  # a cycle either side, for reading shapes at t - τ
    fine = simulate(
        sys_eff, gait, eta=eta, alpha=alpha, n_cycles=n_cycles + 2 * pad,
        samples_per_cycle=samples_per_cycle * U, substeps=2, seeds=seeds, phase0=phase0,
        drift=drift if drift else None,
    )
    batch = tuple(fine.batch_shape)
    T = n_cycles * samples_per_cycle
    start = pad * samples_per_cycle * U
    device = fine.pose.device
    rows = start + U * torch.arange(T, device=device)
    dt = 2 * math.pi / samples_per_cycle

    def fine_flat(x: Tensor) -> Tensor:
        return x.reshape((-1,) + tuple(x.shape[len(batch):]))

    r_true_fine = fine_flat(fine.r)
    dtf = dt / U

    def read_true(s: Tensor) -> Tensor:  # s: time from the fine record's first sample
        return cubic_interp(r_true_fine, s / dtf)

    read = read_true
    for name in reversed(list(params)):
        read = get_effect(name).recorded_shapes(params[name], read, dt)
    r_rec = read(rows.to(torch.float64) * dtf).reshape(batch + (T, system.shape_dim))

    pose_true = fine.pose[..., rows, :]
    pose_rec = pose_true
    for name, p in params.items():
        effect = get_effect(name)
        if type(effect).observe is not Effect.observe:
            pose_rec = effect.observe(p, pose_rec)

    # the truth per output sample: means over its recording interval (half fine cells at ends)
    w = torch.ones(U + 1, dtype=torch.float64, device=device)
    w[0] = w[-1] = 0.5
    w = w / U
    win = rows[:, None] + torch.arange(-(U // 2), U // 2 + 1, device=device)  # (T, U+1) for even U

    def interval_mean(x: Tensor) -> Tensor:  # (..., T_fine, C) -> (..., T, C)
        if U == 1:
            return x[..., rows, :]
        return (x[..., win, :] * w[:, None]).sum(-2)

    xi = fine.truth.xi[..., rows, :] if U % 2 else interval_mean(fine.truth.xi)
    # power on the output samples' intervals (docs/conventions.md), from the true shapes at those samples
    power = interval_power(sys_eff, fine.r[..., rows, :], dt)
    half = U // 2
    r_dot = (fine.r[..., rows + half, :] - fine.r[..., rows - half, :]) / dt if U > 1 and \
        not U % 2 else fine.truth.r_dot[..., rows, :]
    t = rows.to(torch.float64) * dtf - start * dtf
    truth = GroundTruth(phase=fine.truth.phase[..., rows], pose=pose_true, r=fine.r[..., rows, :],
                        xi=xi, r_dot=r_dot, power=power, delta=fine.truth.delta[..., rows, :])
    meta = dict(fine.meta)
    meta.update(
        source="torchconn.discrepancy.simulate_with_effects",
        system=repr(system), effects={n: p.tolist() for n, p in params.items()},
        n_cycles=int(n_cycles), samples_per_cycle=int(samples_per_cycle), substeps=int(substeps),
        dt=dt,
    )
    traj = Trajectory(t=t, pose=pose_rec, r=r_rec, power=power, truth=truth, meta=meta)
    if omega or dropout:
        traj = observe(traj, omega, dropout=dropout, seeds=fine.meta["seeds"])
    return traj


class LateralSlipSwimmer(NLinkSwimmer):
    """A 3-link swimmer with a physical effect that is NOT in the registry, for validation.

    An unmodelled, shape-dependent lateral slip ``ΔA_vy = ε (r2, r1)``: naming any registered
    effect for data simulated with it is wrong (the workflow should say ``unexplained``).
    """

    def __init__(self, eps: float):
        super().__init__(3)
        self.eps = eps

    def _slip(self, r: Tensor) -> Tensor:
        z = torch.zeros_like(r[..., 0])
        zeros = torch.stack([z, z], -1)
        return torch.stack([zeros, self.eps * r.flip(-1), zeros], -2)  # (..., 3, 2)

    def _connection(self, r: Tensor) -> Tensor:
        return super()._connection(r) + self._slip(r)

    def _connection_and_metric(self, r: Tensor) -> tuple[Tensor, Tensor]:
        a, m = super()._connection_and_metric(r)
        return a + self._slip(r), m


def simulate_inertial_relaxation(
    system: LocomotionSystem,
    gait,
    tau: float,
    *,
    eta,
    alpha=0.05,
    n_cycles: int = 20,
    samples_per_cycle: int = 64,
    upsample: int = 4,
    seeds,
    omega: float = 0.0,
) -> Trajectory:
    """Recordings with a physical effect that is NOT in the registry, for validation: the body
    velocity follows ``A(r)ṙ`` through a first-order relaxation of time constant ``tau``
    (inertia), ``τ ξ̇ = A(r)ṙ − ξ``. A short ``tau`` looks partly like a negative time lag.

    The rollout runs ``upsample`` times finer than the output; the relaxed velocity (exact
    recursion for a piecewise-constant input) is integrated on SE(2) and sampled.
    Returns the recording ``(len(seeds), T, ...)`` with observation noise ``omega``.
    """
    from scipy.signal import lfilter

    fine = simulate(system, gait, eta=eta, alpha=alpha, n_cycles=n_cycles,
                    samples_per_cycle=samples_per_cycle * upsample, substeps=2, seeds=list(seeds))
    xi, dtf = fine.truth.xi, fine.dt
    a = 1 - math.exp(-dtf / tau)
    x = xi.detach().cpu().numpy()
    lagged = lfilter([a], [1.0, a - 1.0], x, axis=-2, zi=(1 - a) * x[..., :1, :])[0]
    lagged = torch.as_tensor(lagged, dtype=xi.dtype, device=xi.device)
    pose = se2.integrate(lagged, dtf, method="exp")[..., :-1, :]
    rows = torch.arange(0, xi.shape[-2], upsample, device=xi.device)
    rec = Trajectory(t=fine.t[rows], pose=pose[..., rows, :], r=fine.r[..., rows, :],
                     meta={"source": "torchconn.discrepancy.simulate_inertial_relaxation",
                           "tau": float(tau)})
    return observe(rec, omega, seeds=list(seeds)) if omega else rec
