"""Where simulation and measurement disagree: residual profiles and the term-by-term comparison.

:func:`phase_profile`
    The residual ``ξ_meas − ξ_pred`` per body-velocity component, averaged in phase bins, with
    bootstrap confidence bands from resampling whole cycles (the residual of one cycle is
    autocorrelated through the smoother, different cycles are nearly independent), so noise is
    not called disagreement: a bin disagrees when its band excludes zero.

:func:`compare_terms`
    The data-driven local model of Stage 4 (:class:`~torchconn.regression.estimator.ConnectionEstimator`:
    ``ĉ, b̂, Â, ∂Â/∂r`` along the gait, with standard errors) against the simulator's own values
    on the same cycle -- ``c = A(γ) γ̇``, ``b = ∂A/∂r γ̇``, ``A(γ)``, ``∂A/∂r(γ)`` -- as z-scores per
    phase bin. It shows *which* terms disagree. Like with like: the simulator's terms are
    estimated by the same estimator from the simulator's own "twin" recording of the same
    shapes (with noise of the recording's level), so the estimator's smoothing and truncation
    biases cancel; the exact values are kept for reference.
"""

from __future__ import annotations

import math

import numpy as np
import torch
from torch import Tensor

from ..physics.systems.base import LocomotionSystem
from ..regression.estimator import ConnectionEstimator
from ..regression.metric import TiedMetric
from ..regression.tube import TubeRegression
from ..trajectory import Trajectory
from .forward import Measurement

__all__ = ["COMPONENTS", "phase_profile", "compare_terms", "component_rms"]

#: body-velocity components in reports
COMPONENTS = ("v_x", "v_y", "omega")


def component_rms(residual: Tensor, mask: Tensor) -> Tensor:
    """RMS per component over usable samples: ``(B, T, 3), (B, T) -> (3,)``."""
    w = mask.to(residual.dtype)[..., None]
    return torch.sqrt((residual ** 2 * w).sum((0, 1)) / w.sum((0, 1)))


def phase_profile(
    residual: Tensor,
    m: Measurement,
    *,
    n_bins: int = 16,
    n_boot: int = 300,
    level: float = 0.95,
    seed: int = 0,
) -> dict:
    """Mean residual per phase bin with a cycle-bootstrap confidence band.

    Args:
        residual: ``(B, T, 3)`` residual in physical units.
        m: the measurement (phase, usable mask, cycle ids).
        n_bins: phase bins centred on ``2πk / n_bins``.
        n_boot: bootstrap resamples of whole cycles.
        level: confidence level of the band.
        seed: bootstrap seed.

    Returns:
        dict of numpy arrays: ``centres (M,)``, ``mean``, ``lo``, ``hi`` ``(M, 3)`` and
        ``disagrees (M, 3)`` (the band excludes 0).
    """
    mask = m.mask
    phase = torch.remainder(m.phase[mask], 2 * math.pi)
    width = 2 * math.pi / n_bins
    # a report's summary, bootstrapped in NumPy: one copy to the CPU
    idx = (torch.round(phase / width).long() % n_bins).cpu().numpy()
    cyc = m.cycle[mask].cpu().numpy()
    res = residual[mask].detach().cpu().numpy()  # (N, 3)
    C = m.n_cycles
    sums = np.zeros((C, n_bins, 3))
    counts = np.zeros((C, n_bins))
    np.add.at(sums, (cyc, idx), res)
    np.add.at(counts, (cyc, idx), 1.0)
    mean = sums.sum(0) / np.maximum(counts.sum(0), 1)[:, None]
    rng = np.random.default_rng(seed)
    draws = rng.integers(0, C, size=(n_boot, C))
    w = np.zeros((n_boot, C))
    np.add.at(w, (np.arange(n_boot)[:, None], draws), 1.0)
    boot = np.einsum("bc,cmk->bmk", w, sums) / np.maximum(
        np.einsum("bc,cm->bm", w, counts), 1)[..., None]
    a = (1 - level) / 2
    lo, hi = np.quantile(boot, a, axis=0), np.quantile(boot, 1 - a, axis=0)
    return {
        "centres": np.arange(n_bins) * width,
        "mean": mean,
        "lo": lo,
        "hi": hi,
        "disagrees": (lo > 0) | (hi < 0),
    }


def compare_terms(
    traj: Trajectory,
    system: LocomotionSystem,
    *,
    twin: Trajectory | None = None,
    phase: Tensor | None = None,
    n_bins: int = 16,
    fourier_order: int = 4,
) -> dict:
    """Stage 4's local model of the data against the simulator's terms along the gait.

    Args:
        traj: the recording (any batch shape; the trials are pooled into one model).
        system: the simulator to compare with.
        twin: the simulator's own recording of the same shapes with the same noise level (see
            :func:`torchconn.discrepancy.workflow.diagnose`). When given, the simulator's terms
            are *estimated* from it by the same pipeline, so the comparison is like with like:
            z = (data − twin) / √(se_data² + se_twin²). Otherwise the exact simulator values at
            the estimated cycle are used (and the estimator's own bias shows in the z-scores).
        phase: ``(..., T)`` phase of ``traj`` (and of ``twin``) to use (else Phaser's).

    Returns:
        JSON-ready dict: per term (``c, b, A, dA``) the per-bin estimates with standard errors,
        the simulator's values (exact and, with a twin, estimated) and the z-scores, with
        ``max_abs_z``, ``rms_z`` and ``frac_abs_z_gt_3`` per body-velocity component.
    """
    def fit(recording):
        est = ConnectionEstimator(
            regression=TubeRegression(n_bins=n_bins, fourier_order=fourier_order),
            metric=TiedMetric(enabled=False),
            pool=True, complexity="fixed", held_out_folds=0,  # the workflow cross-validates
        )
        return est.fit(recording, phase=phase).model_.bins

    bins = fit(traj)
    gamma, gamma_dot = bins.gamma, bins.gamma_dot  # (M, d)
    A = system.connection(gamma)
    dA = system.connection_jacobian(gamma)  # [m, k, i, j] = ∂A^k_i/∂r_j
    exact = {
        "c": (A @ gamma_dot[..., None])[..., 0],
        "b": torch.einsum("mkij,mi->mkj", dA, gamma_dot),
        "A": A,
        "dA": dA,
    }
    twin_bins = fit(twin) if twin is not None else None
    out = {"phase": bins.phase.tolist(), "reference": "twin" if twin is not None else "exact",
           "terms": {}}
    for name in ("c", "b", "A", "dA"):
        value, se = getattr(bins, name), getattr(bins, f"{name}_se")
        entry = {"estimate": value.tolist(), "se": se.tolist(),
                 "simulator": exact[name].detach().tolist()}
        if twin_bins is not None:
            ref = getattr(twin_bins, name)
            se = torch.sqrt(se ** 2 + getattr(twin_bins, f"{name}_se") ** 2)
            entry["simulator_estimated"] = ref.tolist()
        else:
            ref = exact[name].detach()
        z = (value - ref) / se.clamp_min(1e-300)
        zc = z.reshape(z.shape[0], 3, -1)  # (M, 3, ·)
        summary = {}
        for k, comp in enumerate(COMPONENTS):
            zk = zc[:, k].reshape(-1)
            zk = zk[torch.isfinite(zk)]
            summary[comp] = {
                "max_abs_z": float(zk.abs().max()) if zk.numel() else float("nan"),
                "rms_z": float(zk.pow(2).mean().sqrt()) if zk.numel() else float("nan"),
                "frac_abs_z_gt_3": float((zk.abs() > 3).double().mean()) if zk.numel() else 0.0,
            }
        entry["z"] = z.tolist()
        entry["summary"] = summary
        out["terms"][name] = entry
    return out
