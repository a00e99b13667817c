"""The motion-capture observation model: measurement noise and marker drop-outs.

docs/conventions.md ("Phase and noise"): i.i.d. Gaussian noise of standard deviation ω is added to
every recorded ``x, y`` (body lengths), ``θ`` (rad) and ``r_i`` (rad) sample. The power
channel is left as recorded. Drop-outs blank whole samples -- pose, shape and power of a row
become NaN -- the way a lost marker loses the frame. The hidden ``truth`` is kept.

Every batch cell draws from its own ``torch.Generator`` seeded from ``(seed, "observe")``
(:func:`torchconn.simulation.rollout.cell_generators`): first ``(T, 3 + d)`` standard normals, then, only
when ``dropout > 0``, ``T`` uniforms. A cell's noise therefore does not depend on the batch,
and the same seeds used for :func:`torchconn.simulation.rollout.simulate` still give independent noise.
"""

from __future__ import annotations

import torch

from ..trajectory import Trajectory
from .rollout import cell_generators, meta_value, per_cell, seed_array

__all__ = ["observe"]


def observe(traj: Trajectory, omega, *, dropout: float = 0.0, seeds) -> Trajectory:
    """Add motion-capture noise (and optional drop-outs) to a trajectory.

    Args:
        traj: recorded trajectory, ``pose (..., T, 3)``, ``r (..., T, d)``.
        omega: noise standard deviation ω ≥ 0, a float or a tensor broadcastable to the batch
            shape ``(...)`` (e.g. ``(L, 1)`` for ``L`` levels × trials).
        dropout: probability in ``[0, 1)`` that a sample (a whole row) is lost.
        seeds: non-negative integers of the batch shape (see
            :func:`torchconn.simulation.rollout.cell_generators`).

    Returns:
        A copy with noisy ``pose`` and ``r``, NaN rows where samples dropped out (``power``
        too), ``truth`` unchanged and ``meta`` recording ``omega``, ``dropout`` and
        ``observe_seeds``. Samples that were already NaN stay NaN.
    """
    if not isinstance(traj, Trajectory):
        raise TypeError(f"traj must be a Trajectory, got {type(traj).__name__}")
    if isinstance(dropout, bool) or not isinstance(dropout, (int, float)) or not (
        0.0 <= dropout < 1.0
    ):
        raise ValueError(f"dropout must be a probability in [0, 1), got {dropout!r}")
    batch = tuple(traj.batch_shape)
    seed_arr = seed_array(seeds)
    if tuple(seed_arr.shape) != batch:
        raise ValueError(
            f"seeds must have the trajectory's batch shape {batch}, got {tuple(seed_arr.shape)}"
        )
    pose, r = traj.pose, traj.r
    T, d = traj.n_samples, traj.shape_dim
    gens, _ = cell_generators(seed_arr, "observe", pose.device)
    omega_c = per_cell(omega, "omega", batch, pose.dtype, pose.device)
    if (omega_c < 0).any():
        raise ValueError("omega must be finite and >= 0")

    kw = dict(dtype=pose.dtype, device=pose.device)
    z = torch.stack([torch.randn(T, 3 + d, generator=g, **kw) for g in gens])  # (B, T, 3 + d)
    noise = (z * omega_c[:, None, None]).reshape(batch + (T, 3 + d))
    new_pose = pose + noise[..., :3]
    new_r = r + noise[..., 3:].to(r.dtype)
    power = traj.power
    if dropout > 0:
        u = torch.stack([torch.rand(T, generator=g, **kw) for g in gens]).reshape(batch + (T,))
        lost = u < dropout
        nan = torch.tensor(float("nan"), **kw)
        new_pose = torch.where(lost[..., None], nan, new_pose)
        new_r = torch.where(lost[..., None], nan.to(r.dtype), new_r)
        if power is not None:
            power = torch.where(lost, nan.to(power.dtype), power)

    meta = dict(traj.meta)
    meta.update(omega=meta_value(omega), dropout=float(dropout),
                observe_seeds=seed_arr.tolist())
    return traj.with_fields(pose=new_pose, r=new_r, power=power, meta=meta)
