"""Plots of a fitted local model: A, ∂A/∂r and M along the gait, with confidence bands."""

from __future__ import annotations

import math
from pathlib import Path

import torch
from matplotlib.figure import Figure

from .._output import save_figure
from .model import LocalConnectionModel

__all__ = ["plot_connection", "plot_metric", "plot_limit_cycle", "ROWS"]

ROWS = ("x", "y", "theta")
_Z95 = 1.96


def _grid(n: int = 200) -> torch.Tensor:
    return torch.linspace(0, 2 * math.pi, n, dtype=torch.float64)


def plot_connection(model: LocalConnectionModel, path: Path | str, truth=None) -> Path:
    """Each entry ``A^k_i(φ)``: the Fourier fit, per-bin estimates with 95% intervals, and
    optionally the true values ``truth(phi) -> (P, 3, d)`` (e.g. the simulator on the cycle)."""
    phi = _grid()
    d = model.shape_dim
    fit = model.connection(phi)
    bins = model.bins
    fig = Figure(figsize=(2.6 * d + 1, 6.5))
    axes = fig.subplots(3, d, squeeze=False, sharex=True)
    true = truth(phi) if truth is not None else None
    for k in range(3):
        for i in range(d):
            ax = axes[k, i]
            ax.plot(phi, fit[:, k, i], color="tab:green", label="data-driven (Fourier)")
            ax.errorbar(bins.phase, bins.A[:, k, i], yerr=_Z95 * bins.A_se[:, k, i], fmt="o",
                        ms=3, color="tab:green", alpha=0.7, label="per-bin ±95%")
            if true is not None:
                ax.plot(phi, true[:, k, i], "k--", lw=1, label="simulator")
            ax.set_title(f"A_{ROWS[k]},{i + 1}", fontsize=9)
            if k == 2:
                ax.set_xlabel("phase (rad)")
    axes[0, 0].legend(fontsize=7)
    return _save(fig, path)


def plot_metric(model: LocalConnectionModel, path: Path | str, truth=None) -> Path:
    """The metric along the gait with 95% intervals: first row ``M̂γ̇`` per joint and the
    on-cycle power ``γ̇ᵀM̂γ̇`` (what the gait itself identifies), then the diagonal and first
    off-diagonal entries of the full ``M̂`` (only as good as the off-cycle excitation: wide bands
    where the data do not excite a direction). ``truth(phi) -> (P, d, d)`` optionally draws the
    true metric on the fitted cycle."""
    phi = _grid()
    d = model.shape_dim
    fit = model.metric(phi)
    bins = model.bins
    pairs = [(i, i) for i in range(d)] + [(i, i + 1) for i in range(d - 1)]
    cols = min(max(len(pairs), d + 1), 4)
    top = math.ceil((d + 1) / cols)
    rows = top + math.ceil(len(pairs) / cols)
    fig = Figure(figsize=(3 * cols, 2.4 * rows))
    axes = fig.subplots(rows, cols, squeeze=False)
    true = truth(phi) if truth is not None else None
    gd = model.gamma_dot_at(phi)
    mgd = model.metric_gamma_dot(phi)
    gd_bins = bins.gamma_dot
    panels = [(f"(M γ̇)_{i + 1}", mgd[:, i], bins.M_gamma_dot, bins.M_gamma_dot_se, i,
               None if true is None else (true @ gd[..., None])[:, i, 0]) for i in range(d)]
    panels.append(("power on cycle γ̇ᵀMγ̇", model.power_on_cycle(phi), bins.power_on_cycle,
                   bins.power_on_cycle_se, None,
                   None if true is None else (gd[:, None, :] @ true @ gd[..., None])[:, 0, 0]))
    for ax, (title, curve, est, se, i, ref) in zip(axes[:top].flat, panels, strict=False):
        ax.plot(phi, curve, color="tab:purple")
        if est is not None and se is not None and gd_bins is not None:
            e, s = (est[:, i], se[:, i]) if i is not None else (est, se)
            ax.errorbar(bins.phase, e, yerr=_Z95 * s, fmt="o", ms=3, color="tab:purple",
                        alpha=0.7)
        if ref is not None:
            ax.plot(phi, ref, "k--", lw=1)
        ax.set_title(title, fontsize=9)
    for ax in list(axes[:top].flat)[len(panels):]:
        ax.axis("off")
    for ax, (i, j) in zip(axes[top:].flat, pairs, strict=False):
        ax.plot(phi, fit[:, i, j], color="tab:blue")
        ax.errorbar(bins.phase, bins.M[:, i, j], yerr=_Z95 * bins.M_se[:, i, j], fmt="o", ms=3,
                    color="tab:blue", alpha=0.7)
        if true is not None:
            ax.plot(phi, true[:, i, j], "k--", lw=1)
        ax.set_title(f"M_{i + 1}{j + 1} (full metric)", fontsize=9)
        ax.set_xlabel("phase (rad)", fontsize=8)
    for ax in list(axes[top:].flat)[len(pairs):]:
        ax.axis("off")
    return _save(fig, path)


def plot_limit_cycle(model: LocalConnectionModel, path: Path | str, r=None) -> Path:
    """The fitted cycle in its first two coordinates over the recorded shapes ``r (T, d)``."""
    phi = _grid()
    gamma = model.gamma_at(phi)
    fig = Figure(figsize=(4.5, 4.5))
    ax = fig.subplots()
    if r is not None:
        ax.plot(r[..., 0].reshape(-1), r[..., 1].reshape(-1), ".", ms=1, color="0.6",
                label="samples")
    ax.plot(gamma[:, 0], gamma[:, 1], color="tab:red", lw=2, label="limit cycle γ")
    ax.set_xlabel("r1")
    ax.set_ylabel("r2")
    ax.legend(fontsize=8)
    ax.set_aspect("equal", "datalim")
    return _save(fig, path)


def _save(fig, path) -> Path:
    fig.tight_layout()
    return save_figure(fig, path, dpi=100)
