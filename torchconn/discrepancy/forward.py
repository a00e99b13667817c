"""The differentiable forward model: recorded shapes + swimmer + effects -> body-velocity residual.

Comparing like with like
    The recorded body velocity is not ``g⁻¹ġ`` itself but what a smoother makes of noisy poses:
    ``ξ_meas = body(S_d y)``, with ``y (T, 3)`` the recorded world poses and ``S_d`` the
    smoothing differentiator. The simulator's prediction goes through the *same* ``S_d``:
    the swimmer is driven by the recorded shapes, its predicted poses ``y_pred`` are integrated
    on the recording grid, and ``ξ_pred = body(S_d y_pred)``. The residual
    ``ρ = ξ_meas − ξ_pred = body(S_d (y − y_pred))`` is then zero up to smoothed observation
    noise when the model is right, whatever the smoother's bias (filter lag, attenuated
    harmonics) -- so filter bias is never named as physics.

The smoother
    ``S_d`` is the steady-state Rauch–Tung–Striebel smoother of :mod:`torchconn.phase.smoothing`
    (constant-velocity model) with the noise ratio its generalised cross-validation picks for
    the recorded channels; in the interior of a record it is a fixed convolution, which is how
    it is applied here (:func:`derivative_kernel`), and the samples within the kernel's reach
    of either end are left out. ``x`` and ``y`` share one kernel (the geometric mean of their
    two GCV ratios), so a rotation of the world frame rotates the residual's input and nothing
    else; the heading has its own. Both kernels annihilate constants and differentiate lines
    exactly, so the unknown start pose of ``y_pred`` does not matter.

The prediction
    The recorded shapes are interpolated (Catmull–Rom cubic) onto a grid ``upsample`` times
    finer than the recording -- shape effects act here (``joint_bias``, ``time_lag``) -- and
    the body twist of each fine step is ``½(A(r_n) + A(r_{n+1})) Δr_n`` plus any extra body
    velocity (``ambient_flow``, ``body_drift``). It is carried into the world frame with the
    recorded (smoothed) heading, not an integrated one, so a wrong model does not rotate its own
    prediction away from the data over a long record, and summed. Observation effects
    (``marker_offset``) change the predicted recorded pose last.

Everything is torch, batched over trials, and differentiable in the effects' parameters, which
is how :mod:`torchconn.discrepancy.fitting` gets its Jacobians (forward-mode autograd).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, fields, replace

import torch
from torch import Tensor

from ..cycles import present_cycles
from ..io.preflight import CYCLE_RULES
from ..phase.phaser import Phaser, estimate_phase
from ..phase.smoothing import (
    RTSSmoother,
    noise_parameters,
    rts_smooth,
    smooth_trajectory,
    unwrap,
)
from ..physics import se2
from ..physics.effects import Effect, cubic_interp, get_effect, swimmer_kwargs
from ..physics.systems.base import LocomotionSystem
from ..physics.systems.swimmer import NLinkSwimmer
from ..trajectory import Trajectory, span_bounds

__all__ = [
    "Measurement",
    "ForwardModel",
    "prepare_measurement",
    "measurement_from_clean",
    "derivative_kernel",
    "cubic_interp",
    "MIN_CYCLES",
]

#: fewest whole gait cycles (over all trials) the discrepancy workflow accepts, and per trial
#: (phase estimation needs a few): the ``discrepancy`` rule of the one table of cycle rules
MIN_CYCLES = CYCLE_RULES["discrepancy"].total
MIN_CYCLES_PER_TRIAL = CYCLE_RULES["discrepancy"].per_trial
#: relative size below which the smoothing kernel is cut
_KERNEL_TOL = 1e-10
#: extra samples left out at each end beyond the kernel's reach (room for shape shifts)
_EDGE_EXTRA = 8
#: smoothing kernels at least this half-width are applied by FFT (faster than the direct
#: correlation from there on)
_FFT_HALF_WIDTH = 20


# ============================================================================ helpers
def derivative_kernel(ratio: Tensor, dt: float, *, max_half_width: int = 400) -> Tensor:
    """Interior rows of the smoothing differentiator for noise ratios ``q / R``.

    Args:
        ratio: ``(K,)`` noise ratios of the order-2 (white-acceleration) RTS smoother.
        dt: sampling interval.
        max_half_width: longest kernel half-width considered.

    Returns:
        ``(K, 2W + 1)`` weights ``w`` with ``(S_d y)_i = Σ_j w[j] y_{i + j − W}`` in the interior
        (``W`` the common half-width at which every kernel has decayed below 1e-10 of its
        peak). ``Σ_j w[j] = 0`` and ``Σ_j (j − W) dt w[j] = 1``.
    """
    L = 2 * max_half_width + 1
    imp = torch.zeros(ratio.shape[0], L, 1, dtype=ratio.dtype, device=ratio.device)
    imp[:, max_half_width, 0] = 1.0
    _, der = rts_smooth(imp, dt, process_noise=ratio[:, None], measurement_noise=1.0)
    h = der[..., 0]  # response at i to an impulse at the centre: S_d[i, c]
    mag = h.abs() / h.abs().amax(-1, keepdim=True)
    big = (mag > _KERNEL_TOL).any(0).nonzero().flatten()
    W = int(max(max_half_width - int(big.min()), int(big.max()) - max_half_width, 1))
    W = min(W, max_half_width - 1)
    # S_d[i, i + o] = h(centre - o) -> weight for offset o = j - W is h[centre - o]
    seg = h[:, max_half_width - W: max_half_width + W + 1]
    return seg.flip(-1).contiguous()


def _rotate(theta: Tensor, v: Tensor, transpose: bool = False) -> Tensor:
    c, s = torch.cos(theta), torch.sin(theta)
    if transpose:
        s = -s
    return torch.stack([c * v[..., 0] - s * v[..., 1], s * v[..., 0] + c * v[..., 1]], -1)


# ============================================================================ measurement
@dataclass(frozen=True, eq=False)
class Measurement:
    """A recording prepared for the discrepancy stage (trials flattened to ``B``).

    Attributes:
        dt: sampling interval; t: ``(T,)`` sample times.
        pose: ``(B, T, 3)`` recorded poses, heading unwrapped, gaps filled by the smoother.
        r: ``(B, T, d)`` recorded shapes, gaps filled by the smoother.
        heading: ``(B, T)`` smoothed heading (rotates between world and body frames).
        phase: ``(B, T)`` gait phase (Phaser on the smoothed shapes, or supplied).
        kernel: ``(B, 3, 2W+1)`` smoothing differentiators of the ``x, y, θ`` channels.
        mask: ``(B, T)`` samples whose residual is used (interior, originally recorded).
        cycle: ``(B, T)`` integer id of the gait cycle a sample is in (unique over trials;
            −1 outside the mask).
        cycle_trial: ``(n_cycles,)`` trial of each cycle; cycle_index: position in its trial.
        xi: ``(B, T, 3)`` recorded body velocity ``body(S_d y)``.
        batch_shape: the original trajectory's batch shape.
    """

    dt: float
    t: Tensor
    pose: Tensor
    r: Tensor
    heading: Tensor
    phase: Tensor
    kernel: Tensor
    mask: Tensor
    cycle: Tensor
    cycle_trial: Tensor
    cycle_index: Tensor
    xi: Tensor
    batch_shape: tuple[int, ...]

    @property
    def n_trials(self) -> int:
        return self.pose.shape[0]

    @property
    def device(self) -> torch.device:
        """The device of the recording's tensors (everything derived from it follows)."""
        return self.pose.device

    @property
    def n_samples(self) -> int:
        return self.pose.shape[1]

    @property
    def shape_dim(self) -> int:
        return self.r.shape[-1]

    @property
    def n_cycles(self) -> int:
        return int(self.cycle_trial.shape[0])

    @property
    def half_width(self) -> int:
        return (self.kernel.shape[-1] - 1) // 2

    def smooth_velocity(self, poses: Tensor) -> Tensor:
        """``body(S_d poses)``: world poses ``(B, T, 3)`` -> body velocities ``(B, T, 3)``.

        Long kernels (dense sampling) are applied by FFT, short ones directly; both are the
        same zero-padded correlation."""
        B, T, _ = poses.shape
        W = self.half_width
        x = poses.transpose(1, 2)  # (B, 3, T)
        kernel = self.kernel.to(device=poses.device, dtype=poses.dtype)
        if W >= _FFT_HALF_WIDTH:
            n = T + 2 * W
            spec = torch.fft.rfft(x, n=n) * torch.fft.rfft(kernel.flip(-1), n=n)
            out = torch.fft.irfft(spec, n=n)[..., W: W + T]
        else:
            out = torch.nn.functional.conv1d(
                x.reshape(1, B * 3, T), kernel.reshape(B * 3, 1, -1), padding=W, groups=B * 3,
            ).reshape(B, 3, T)
        out = out.transpose(1, 2)
        v = _rotate(self.heading.to(poses.dtype), out[..., :2], transpose=True)
        return torch.cat([v, out[..., 2:]], -1)


def prepare_measurement(
    traj: Trajectory,
    system: LocomotionSystem,
    *,
    phase: Tensor | None = None,
    min_cycles: float = MIN_CYCLES,
) -> Measurement:
    """Check a recording against a swimmer and prepare it for the residuals.

    Args:
        traj: recorded trials (any batch shape), NaN for drop-outs.
        system: the nominal simulator; its number of joints must match the data.
        phase: optional ``(..., T)`` phase (otherwise ``traj.phase`` or Phaser's estimate).
        min_cycles: fewest whole gait cycles over all trials.

    Raises:
        ValueError: wrong number of joints, too few samples or cycles, a trial without data.
    """
    _check_joints(traj, system)
    batch_shape = tuple(traj.batch_shape)
    T = traj.n_samples
    pose, r, finite = _flat_recording(traj)
    B = pose.shape[0]
    dt = traj.dt

    # trials of different lengths on one grid: each is smoothed and phased over its own span,
    # the time outside it (never recorded) filled with the span's edge values
    start, stop = span_bounds(finite)
    padded = bool(((start > 0) | (stop < T)).any())
    sm = (_smooth_spans(pose, r, dt, start, stop) if padded
          else smooth_trajectory(pose, r, dt))
    pose_f = torch.where(torch.isfinite(pose), pose, sm.pose)
    r_f = torch.where(torch.isfinite(r), r, sm.r)
    if phase is None and traj.phase is not None:
        phase = traj.phase
    if phase is None:
        phase = _estimated_phase(sm.r, start, stop, padded, min_cycles)
    else:
        phase = torch.as_tensor(phase, dtype=torch.float64, device=pose.device).reshape(B, T)

    kernel = _smoothing_kernels(pose, dt)
    mask = _usable_mask(finite, (kernel.shape[-1] - 1) // 2)
    # cycles of fewer than 4 usable samples are dropped from mask
    cycle, trials, index = present_cycles(phase, mask, origin="mask", min_samples=4)
    _check_whole_cycles(phase, mask, min_cycles)

    heading = sm.pose[..., 2]
    m = Measurement(
        dt=dt, t=traj.t.to(torch.float64), pose=pose_f, r=r_f, heading=heading, phase=phase,
        kernel=kernel, mask=mask, cycle=cycle,
        cycle_trial=torch.tensor(trials, dtype=torch.long, device=pose.device),
        cycle_index=torch.tensor(index, dtype=torch.long, device=pose.device),
        xi=torch.zeros_like(pose_f), batch_shape=batch_shape,
    )
    return _with_xi(m)


def _check_joints(traj: Trajectory, system: LocomotionSystem) -> None:
    """Refuse inputs of the wrong type, and a system whose number of joints is not the data's."""
    if not isinstance(traj, Trajectory):
        raise TypeError(f"traj must be a torchconn.Trajectory, got {type(traj).__name__}")
    if not isinstance(system, LocomotionSystem):
        raise TypeError(f"system must be a LocomotionSystem, got {type(system).__name__}")
    d = traj.shape_dim
    if system.shape_dim != d:
        n_links = getattr(system, "n_links", None)
        what = f"a {n_links}-link swimmer has {system.shape_dim}" if n_links else \
            f"the system has {system.shape_dim}"
        raise ValueError(
            f"the data have {d} joint angle(s) (r1..r{d}), but {what} joints; pass the model "
            f"that recorded them (--links {d + 1} for an N-link swimmer with N − 1 = {d} joints)"
        )


def _flat_recording(traj: Trajectory) -> tuple[Tensor, Tensor, Tensor]:
    """The trials flattened to one batch dim, in float64: poses ``(B, T, 3)`` with the heading
    unwrapped, shapes ``(B, T, d)`` and which samples are complete ``(B, T)``. Raises
    ``ValueError`` when a trial has fewer than 64 complete samples."""
    T, d = traj.n_samples, traj.shape_dim
    pose = traj.pose.reshape(-1, T, 3).to(torch.float64)
    r = traj.r.reshape(-1, T, d).to(torch.float64)
    pose = torch.cat([pose[..., :2], unwrap(pose[..., 2], dim=-1)[..., None]], -1)
    finite = torch.isfinite(pose).all(-1) & torch.isfinite(r).all(-1)  # (B, T)
    n_finite = finite.sum(-1)
    if int(n_finite.min()) < 64:
        b = int(n_finite.argmin())
        raise ValueError(f"trial {b} has only {int(n_finite[b])} complete samples; the "
                         "discrepancy workflow needs whole gait cycles of data per trial")
    return pose, r, finite


def _estimated_phase(r: Tensor, start: Tensor, stop: Tensor, padded: bool,
                     min_cycles: float) -> Tensor:
    """Phaser's phase ``(B, T)`` of the smoothed shapes ``r (B, T, d)``, each trial phased over
    its span ``start:stop`` (edge-filled outside) when the trials differ in length. Too few
    cycles per trial raise ``ValueError`` naming the workflow's minimum."""
    try:
        return (_edge_filled(Phaser(min_cycles=MIN_CYCLES_PER_TRIAL).fit(
            _outside_nan(r, start, stop)).phase_.unsqueeze(-1), start, stop)[..., 0]
            if padded else estimate_phase(r, min_cycles=MIN_CYCLES_PER_TRIAL))
    except ValueError as err:
        if "cycles" in str(err):
            raise ValueError(
                f"too few cycles: {err}. The discrepancy workflow needs at least "
                f"{MIN_CYCLES_PER_TRIAL:g} gait cycles per trial and {min_cycles:g} in all"
            ) from None
        raise


def _smoothing_kernels(pose: Tensor, dt: float) -> Tensor:
    """Derivative kernels ``(B, 3, 2W+1)`` per trial and pose channel, from the GCV noise
    ratios of the recorded channels; x and y share one (the geometric mean of their ratios)."""
    B = pose.shape[0]
    q, R = noise_parameters(pose, dt)
    lam = q / R  # (B, 3)
    lam_xy = torch.sqrt(lam[:, 0] * lam[:, 1])
    ratios = torch.stack([lam_xy, lam_xy, lam[:, 2]], -1).reshape(-1)
    return derivative_kernel(ratios, dt).reshape(B, 3, -1)


def _usable_mask(finite: Tensor, half_width: int) -> Tensor:
    """Usable samples ``(B, T)``: complete, inside each trial's recorded span and clear of the
    kernel's reach (``half_width`` plus a few samples) from its ends."""
    T = finite.shape[-1]
    idx = torch.arange(T, device=finite.device)
    first = torch.where(finite, idx, T).amin(-1)
    last = torch.where(finite, idx, -1).amax(-1)
    margin = half_width + _EDGE_EXTRA
    return finite & (idx >= (first + margin)[:, None]) & (idx <= (last - margin)[:, None])


def _check_whole_cycles(phase: Tensor, mask: Tensor, min_cycles: float) -> None:
    """Refuse a recording whose usable samples span fewer than ``min_cycles`` whole cycles in
    total (partial ones at the ends still serve as data)."""
    B = phase.shape[0]
    span = torch.stack([(phase[b][mask[b]].max() - phase[b][mask[b]].min()) / (2 * math.pi)
                        if mask[b].any() else phase.new_zeros(())
                        for b in range(B)])
    total = float(torch.floor(span).sum())
    if total < min_cycles:
        raise ValueError(
            f"too few cycles: the usable part of the recording holds about {total:.0f} whole "
            f"gait cycle(s) over {B} trial(s); the discrepancy workflow needs at least "
            f"{min_cycles:g} (it cross-validates over whole cycles) -- record longer or more trials"
        )


def _outside_nan(x: Tensor, start: Tensor, stop: Tensor) -> Tensor:
    """``x (B, T, C)`` with NaN outside each row's span ``start:stop``."""
    idx = torch.arange(x.shape[-2], device=x.device)
    inside = (idx >= start[:, None]) & (idx < stop[:, None])
    return torch.where(inside[..., None], x, float("nan"))


def _edge_filled(x: Tensor, start: Tensor, stop: Tensor) -> Tensor:
    """``x (B, T, C)`` with each row's values outside its span ``start:stop`` replaced by the
    span's first and last values."""
    idx = torch.arange(x.shape[-2], device=x.device)
    take = torch.minimum(torch.maximum(idx, start[:, None]), stop[:, None] - 1)  # (B, T)
    return torch.gather(x, -2, take[..., None].expand(x.shape))


def _smooth_spans(pose: Tensor, r: Tensor, dt: float, start: Tensor, stop: Tensor):
    """:func:`smooth_trajectory` of each trial ``(B, T, ·)`` over its own span, edge-filled."""
    traj = Trajectory(t=torch.arange(pose.shape[-2], dtype=pose.dtype, device=pose.device) * dt,
                      pose=_outside_nan(pose, start, stop), r=_outside_nan(r, start, stop))
    sm = RTSSmoother().smooth(traj).smoothed
    return type(sm)(**{f.name: _edge_filled(getattr(sm, f.name), start, stop)
                       for f in fields(sm)})


def measurement_from_clean(t: Tensor, pose: Tensor, r: Tensor, phase: Tensor, kernel: Tensor,
                           dt: float, *, heading: Tensor | None = None) -> Measurement:
    """A :class:`Measurement` of simulated data smoothed with a given kernel.

    Used to compute effects' signatures under alternative experiments with the recording's own
    smoother, and for the simulated twins behind the intervals. ``pose (B, T, 3)``,
    ``r (B, T, d)``, ``phase (B, T)``, ``kernel (3, 2W+1)``; ``heading (B, T)`` rotates between
    world and body frames (default the poses' own heading, right for noise-free poses).
    """
    B, T, _ = pose.shape
    W = (kernel.shape[-1] - 1) // 2
    idx = torch.arange(T, device=pose.device)
    margin = W + _EDGE_EXTRA
    if T <= 2 * margin + 8:
        raise ValueError(f"a simulated experiment of {T} samples is too short for the smoothing "
                         f"kernel (half-width {W})")
    mask = ((idx >= margin) & (idx < T - margin)).expand(B, T).clone()
    cycle, trials, index = present_cycles(phase, mask)
    pose = torch.cat([pose[..., :2], unwrap(pose[..., 2], dim=-1)[..., None]], -1)
    heading = pose[..., 2] if heading is None else heading.expand(B, T)
    m = Measurement(
        dt=float(dt), t=t.to(torch.float64), pose=pose.to(torch.float64),
        r=r.to(torch.float64), heading=heading.to(torch.float64),
        phase=phase.to(torch.float64), kernel=kernel.expand(B, 3, -1).clone(), mask=mask,
        cycle=cycle, cycle_trial=torch.tensor(trials, dtype=torch.long, device=pose.device),
        cycle_index=torch.tensor(index, dtype=torch.long, device=pose.device),
        xi=torch.zeros_like(pose, dtype=torch.float64), batch_shape=(B,),
    )
    return _with_xi(m)


def _with_xi(m: Measurement) -> Measurement:
    return replace(m, xi=m.smooth_velocity(m.pose))


# ============================================================================ forward model
class ForwardModel:
    """Residuals of a nominal swimmer augmented by effects, on one prepared measurement.

    Args:
        measurement: a :class:`Measurement`.
        system: the nominal simulator (an :class:`~torchconn.physics.systems.NLinkSwimmer` for effects
            that change the swimmer; any :class:`LocomotionSystem` otherwise).
        upsample: fine integration steps per recording interval.

    Parameters are passed as a dict ``{effect name: (n_params,) tensor}``; a missing effect is
    absent. :meth:`residual` is differentiable in them.
    """

    def __init__(self, measurement: Measurement, system: LocomotionSystem, *, upsample: int = 4,
                 min_relative_floor: float = 1e-3):
        if not isinstance(upsample, int) or upsample < 1:
            raise ValueError(f"upsample must be a positive integer, got {upsample!r}")
        self.m = measurement
        self.system = system
        self.upsample = upsample
        T, U = measurement.n_samples, upsample
        kw = dict(dtype=torch.float64, device=measurement.device)
        self._s_fine = torch.arange((T - 1) * U + 1, **kw) / U
        self._s_mid = (torch.arange((T - 1) * U, **kw) + 0.5) / U
        self._heading_mid = cubic_interp(measurement.heading[..., None], self._s_mid)[..., 0]
        self._nominal_twist = None
        self.min_relative_floor = float(min_relative_floor)
        self.noise_variance, self.floor = self.noise_floor()

    # ------------------------------------------------------------------ building blocks
    def effect_system(self, params: dict[str, Tensor]) -> LocomotionSystem:
        """The swimmer with the system effects in ``params`` applied."""
        active = [(get_effect(n), p) for n, p in params.items()
                  if type(get_effect(n)).system_kwargs is not Effect.system_kwargs]
        if not active:
            return self.system
        if not isinstance(self.system, NLinkSwimmer):
            raise ValueError(
                f"effects {[e.name for e, _ in active]} change the swimmer, which needs an "
                f"NLinkSwimmer nominal model, got {type(self.system).__name__}"
            )
        kwargs = swimmer_kwargs(self.system)
        for effect, p in active:
            kwargs = effect.system_kwargs(p, kwargs)
        return NLinkSwimmer(**kwargs)

    def _twist(self, params: dict[str, Tensor]) -> Tensor:
        """Body twists of the fine steps ``(B, (T−1)U, 3)`` from the shapes (no extra velocity)."""
        shape_effects = [(get_effect(n), p) for n, p in params.items()
                         if type(get_effect(n)).true_shapes is not Effect.true_shapes]
        system_effects = [n for n in params
                          if type(get_effect(n)).system_kwargs is not Effect.system_kwargs]
        cacheable = not shape_effects and not system_effects
        if cacheable and self._nominal_twist is not None:
            return self._nominal_twist
        m, dt = self.m, self.m.dt

        def read(t: Tensor) -> Tensor:  # recorded shapes at times t (time units from t[0])
            return cubic_interp(m.r, t / dt)

        for effect, p in shape_effects:
            read = effect.true_shapes(p, read, dt)
        r = read(self._s_fine * dt)  # (B, N, d)
        system = self.effect_system(params)
        A = system.connection(r)  # (B, N, 3, d)
        dr = r[:, 1:] - r[:, :-1]
        twist = 0.5 * ((A[:, 1:] + A[:, :-1]) * dr[..., None, :]).sum(-1)
        if cacheable:
            self._nominal_twist = twist.detach()
        return twist

    def predict_poses(self, params: dict[str, Tensor] | None = None,
                      twist: Tensor | None = None) -> Tensor:
        """Predicted recorded poses ``(B, T, 3)`` (up to a constant per trial).

        ``twist`` optionally supplies the fine steps' shape-driven twists (:meth:`_twist` of
        the same parameters), which the Jacobian passes of the velocity and observation effects
        share.
        """
        params = params or {}
        m, U = self.m, self.upsample
        h = m.dt / U
        if twist is None:
            twist = self._twist(params)
        extra = None
        for name, p in params.items():
            v = get_effect(name).body_velocity(p, self._heading_mid)
            if v is not None:
                extra = v if extra is None else extra + v
        if extra is not None:
            twist = twist + extra * h
        dxy = _rotate(self._heading_mid, twist[..., :2])
        steps = torch.cat([dxy, twist[..., 2:]], -1)
        cum = torch.cat([torch.zeros_like(steps[:, :1]), torch.cumsum(steps, 1)], 1)
        poses = cum[:, ::U]
        for name, p in params.items():
            effect = get_effect(name)
            if type(effect).observe is not Effect.observe:
                observed = effect.observe(p, torch.cat([poses[..., :2], m.heading[..., None]],
                                                       -1))
                poses = torch.cat([observed[..., :2], poses[..., 2:]], -1)
        return poses

    def integrate_poses(self, params: dict[str, Tensor] | None = None) -> Tensor:
        """A self-consistent recording of the (augmented) simulator driven by the recorded
        shapes: the fine steps' twists composed on SE(2) from the first recorded pose, its own
        heading included (unlike :meth:`predict_poses`, which borrows the recorded heading).
        Velocity effects are evaluated at the integrated heading; observation effects are not
        applied. Returns ``(B, T, 3)``."""
        params = {k: v.detach() for k, v in (params or {}).items()}
        m, U = self.m, self.upsample
        h = m.dt / U
        twist = self._twist(params).detach()
        extra = [get_effect(n) for n in params
                 if type(get_effect(n)).body_velocity is not Effect.body_velocity]
        if not extra:
            poses = se2.accumulate(se2.exp(twist), m.pose[:, 0])
        else:
            # headings first (velocity effects may not turn the body with the heading)
            w = torch.zeros_like(twist[..., 2])
            for e in extra:
                w = w + e.body_velocity(params[e.name], torch.zeros_like(w))[..., 2] * h
            th = m.pose[:, :1, 2] + torch.cat([torch.zeros_like(w[:, :1]),
                                               torch.cumsum(twist[..., 2] + w, 1)], 1)
            mid = 0.5 * (th[:, 1:] + th[:, :-1])
            for e in extra:
                twist = twist + e.body_velocity(params[e.name], mid) * h
            poses = se2.accumulate(se2.exp(twist), m.pose[:, 0])
        return poses[:, ::U]

    def residual(self, params: dict[str, Tensor] | None = None) -> Tensor:
        """``ξ_meas − ξ_pred``: ``(B, T, 3)`` (meaningful where ``measurement.mask``)."""
        return self.m.xi - self.m.smooth_velocity(self.predict_poses(params))

    def residual_from_twist(self, twist: Tensor, params: dict[str, Tensor]) -> Tensor:
        """:meth:`residual` with the fine steps' shape-driven twists given."""
        return self.m.xi - self.m.smooth_velocity(self.predict_poses(params, twist))

    # ------------------------------------------------------------------ noise floor
    def noise_floor(self, params: dict[str, Tensor] | None = None) -> tuple[Tensor, Tensor]:
        """White-noise variance of ``y − y_pred`` per trial and channel, and the noise floor.

        The difference between the recorded and the nominal predicted poses is observation
        noise (of the poses, and of the shapes carried through ``A``) plus a slowly varying
        model error; fourth differences keep the first and cancel the second (and the rough
        swimming path itself, which the prediction shares). The median absolute deviation of
        the fourth differences gives the variance; pushed through the smoothing kernels it is
        the residual a correct model would leave, per body-frame component. ``params`` selects
        the model whose prediction is subtracted (default nominal; the final model's removes
        the little that a strong effect leaves in the fourth differences).

        A recording without observation noise still leaves the forward model's own error (the
        swimming path between samples is not recorded): the floor is at least
        ``min_relative_floor`` times the RMS of the recorded body velocity, per component.

        Returns:
            ``(variance (B, 3), floor (3,))`` -- the floor is the RMS over usable samples.
        """
        m = self.m
        with torch.no_grad():
            e = m.pose - self.predict_poses({k: v.detach() for k, v in (params or {}).items()})
            d4 = torch.diff(e, n=4, dim=1)  # (B, T-4, 3)
            ok = m.mask[:, 2:-2]
            var = []
            for b in range(m.n_trials):
                x = d4[b][ok[b]]
                med = x.median(0).values
                mad = (x - med).abs().median(0).values
                var.append((1.4826 * mad) ** 2 / math.comb(8, 4))
            var = torch.stack(var)  # (B, 3)
            k2 = (m.kernel ** 2).sum(-1)  # (B, 3)
            c2, s2 = torch.cos(m.heading) ** 2, torch.sin(m.heading) ** 2
            vx = k2[:, :1] * (c2 * var[:, :1] + s2 * var[:, 1:2])
            vy = k2[:, :1] * (s2 * var[:, :1] + c2 * var[:, 1:2])
            vw = (k2[:, 2:3] * var[:, 2:3]).expand_as(vx)
            per_sample = torch.stack([vx, vy, vw], -1)  # (B, T, 3)
            w = m.mask.to(per_sample.dtype)[..., None]
            floor2 = (per_sample * w).sum((0, 1)) / w.sum((0, 1))
            xi_ms = ((m.xi ** 2) * w).sum((0, 1)) / w.sum((0, 1))
            floor2 = torch.maximum(floor2, self.min_relative_floor ** 2 * xi_ms)
        return var, floor2.sqrt()

