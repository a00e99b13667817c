"""What the recordings themselves say a gait does: displacement and cost per cycle, model-free.

Each trial is cut into whole gait periods; a period's displacement is the relative pose
``g(t)⁻¹ g(t + T)`` of the recorded body frame, its cost ``∫√P dt`` from the ``power`` column
(``power`` at sample k belongs to ``[t_k, t_{k+1})``). Means over all periods of all trials and
their standard errors are the measurement the loop checks its predictions against, and the only
signal the model-free baseline sees.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch
from torch import Tensor

from ..physics import se2
from ..trajectory import Trajectory

__all__ = ["CycleMeasurement", "measure_cycles"]


@dataclass(frozen=True)
class CycleMeasurement:
    """Per-period statistics of recordings (means over every whole period of every trial).

    Attributes:
        displacement: ``(3,)`` mean displacement ``(x, y, θ)`` per period (body frame at its start).
        planar, planar_se: mean ``|(x, y)|`` per period and its standard error (long-run
            variance: consecutive periods of a trial are correlated).
        turning, turning_se: mean ``|θ|`` per period and its standard error.
        cost, cost_se: mean ``∫√P dt`` per period, or None without a power column.
        efficiency, efficiency_se: ``planar / cost`` (delta method), or None.
        n_cycles: periods used.
    """

    displacement: Tensor
    planar: float
    planar_se: float
    turning: float
    turning_se: float
    cost: float | None
    cost_se: float | None
    efficiency: float | None
    efficiency_se: float | None
    n_cycles: int

    def objective(self, name: str) -> tuple[float, float]:
        """``(value, standard error)`` of an objective (see :data:`torchconn.improve.OBJECTIVES`)."""
        key = {"displacement": "planar", "turning": "turning", "efficiency": "efficiency"}.get(name)
        if key is None:
            raise ValueError(f"unknown objective {name!r}")
        value = getattr(self, key)
        if value is None:
            raise ValueError(f"objective {name!r} needs a cost per cycle: the recordings have no "
                             "'power' column")
        return value, getattr(self, f"{key}_se")


def measure_cycles(traj: Trajectory, period: float = 2 * math.pi) -> CycleMeasurement:
    """Displacement (and cost) per gait period from the recorded poses (and power).

    Args:
        traj: recordings, poses ``(..., T, 3)``; periods containing a missing pose are skipped.
        period: the gait period in the unit of ``t`` (s for recorded data; the default 2π
            is one cycle on the simulations' clock).
    """
    s = round(period / traj.dt)
    if s < 2:
        raise ValueError(f"period {period} is shorter than two samples (dt = {traj.dt})")
    pose = traj.pose.reshape(-1, *traj.pose.shape[-2:])  # (B, T, 3)
    n = (pose.shape[-2] - 1) // s
    if n < 1:
        raise ValueError(f"the recordings ({pose.shape[-2]} samples) hold no whole period of "
                         f"{s} samples")
    starts = torch.arange(n, device=pose.device) * s
    rel = se2.relative(pose[:, starts], pose[:, starts + s])  # (B, n, 3)
    ok = torch.isfinite(rel).all(-1)
    cost = None
    if traj.power is not None:
        power = traj.power.reshape(-1, traj.power.shape[-1])
        steps = power[:, : n * s].reshape(power.shape[0], n, s)
        cost = (steps.clamp_min(0).sqrt() * traj.dt).sum(-1)  # (B, n)
        ok = ok & torch.isfinite(cost)
        cost = torch.where(ok, cost, 0)
    rel = torch.where(ok[..., None], rel, 0)
    count = int(ok.sum())
    if count < 2:
        raise ValueError(f"need at least two complete periods to measure, got {count}")
    planar = torch.linalg.vector_norm(rel[..., :2], dim=-1)  # (B, n)
    turning = rel[..., 2].abs()
    lags = min(n - 1, max(3, round(n / 4)))

    def mean_se(x: Tensor) -> tuple[float, float]:
        mean, var = _long_run_variance(x, ok, lags)
        return float(mean), math.sqrt(var / count)

    p, p_se = mean_se(planar)
    t, t_se = mean_se(turning)
    c = c_se = e = e_se = None
    if cost is not None:
        c, c_se = mean_se(cost)
        e = p / c
        # delta method for the ratio of two means: linearise, then the same long-run variance
        _, e_var = _long_run_variance(planar / p - cost / c, ok, lags)
        e_se = abs(e) * math.sqrt(e_var / count)
    return CycleMeasurement(
        displacement=rel[ok].mean(0), planar=p, planar_se=p_se, turning=t, turning_se=t_se,
        cost=c, cost_se=c_se, efficiency=e, efficiency_se=e_se, n_cycles=count,
    )


def _long_run_variance(x: Tensor, ok: Tensor, lags: int) -> tuple[Tensor, float]:
    """Mean of per-period values ``x (B, n)`` over the valid periods ``ok (B, n)``, and the
    variance ``var`` such that ``var / count`` is the squared standard error of that mean.

    Consecutive periods of one trial are correlated -- the shape offset relaxes at rate α, over
    about ``1/(2πα) ≈ 3`` periods for the paper's α -- so the naive ``std/√n`` understates the
    standard error. Trials are independent: with at least 3 of them the spread of the
    per-trial means is used; with fewer, Newey–West with Bartlett weights up to ``lags``.
    """
    w = ok.to(x.dtype)
    mean = (torch.where(ok, x, 0) * w).sum() / w.sum()
    dev = torch.where(ok, x - mean, 0)
    n = w.sum()
    per_trial = w.sum(-1)
    used = per_trial > 0
    if int(used.sum()) >= 3:
        # var(mean) = Σ_b n_b² var(trial mean b) / n², trial means exchangeable
        trial_mean = dev.sum(-1)[used] / per_trial[used]
        t_var = float(trial_mean.var())
        return mean, t_var * float((per_trial[used] ** 2).sum()) / float(n)
    var = float((dev * dev).sum() / n)
    for lag in range(1, lags + 1):
        both = w[:, lag:] * w[:, :-lag]
        cov = float((dev[:, lag:] * dev[:, :-lag] * both).sum() / n)
        var += 2 * (1 - lag / (lags + 1)) * cov
    return mean, max(var, 0.0)
