"""Figures of an improvement loop: the gaits over the curvature, the objective per round."""

from __future__ import annotations

import math
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import torch  # noqa: E402

from .. import _linalg  # noqa: E402
from .._output import save_figure  # noqa: E402
from ..physics.systems.base import LocomotionSystem  # noqa: E402
from .loop import LoopResult  # noqa: E402

__all__ = ["plot_gaits", "plot_rounds"]


def plot_gaits(result: LoopResult, system: LocomotionSystem, path: str | Path,
               n_phase: int = 200) -> Path:
    """The recorded gaits of every round: over the x-curvature ``DA_x`` (2 joints) or projected
    on the first two principal components of all their shapes (more joints)."""
    phi = torch.linspace(0, 2 * math.pi, n_phase, dtype=torch.float64)
    loops = [r.gait(phi).detach() for r in result.rounds] + [result.rounds[-1].proposal(phi)]
    fig, ax = plt.subplots(figsize=(5.5, 5))
    if system.shape_dim == 2:
        span = max(float(torch.cat(loops).abs().max()) * 1.15, 0.5)
        g = torch.linspace(-span, span, 121, dtype=torch.float64)
        grid = torch.stack(torch.meshgrid(g, g, indexing="xy"), -1)
        da = system.curvature(grid)[..., 0, 0].detach()
        lim = float(da.abs().max())
        im = ax.pcolormesh(g, g, da, cmap="RdBu_r", vmin=-lim, vmax=lim, shading="auto")
        fig.colorbar(im, ax=ax, label="curvature DA_x")
        ax.set_xlabel("r1 (rad)")
        ax.set_ylabel("r2 (rad)")
        proj = loops
    else:
        allr = torch.cat(loops)
        mean = allr.mean(0)
        _, _, v = _linalg.svd(allr - mean, "the recorded gaits' shapes")
        proj = [(r - mean) @ v[:2].T for r in loops]
        ax.set_xlabel("principal component 1 (rad)")
        ax.set_ylabel("principal component 2 (rad)")
    cmap = plt.get_cmap("viridis")
    for k, p in enumerate(proj):
        last = k == len(proj) - 1
        ax.plot(p[:, 0], p[:, 1], color="k" if last else cmap(k / max(len(proj) - 1, 1)),
                ls="--" if last else "-", lw=1.5, label="next proposal" if last else f"round {k}")
    ax.set_aspect("equal")
    ax.legend(fontsize=7, loc="upper right")
    ax.set_title("recorded gaits per round")
    fig.tight_layout()
    path = save_figure(fig, path, dpi=120)
    plt.close(fig)
    return path


def plot_rounds(result: LoopResult, path: str | Path, ceiling: float | None = None) -> Path:
    """Objective per round: observed and true of each recorded gait, predicted (interval) vs
    realised of each proposal, and the ceiling with the true connection."""
    rounds = result.rounds
    k = [r.index for r in rounds]
    fig, ax = plt.subplots(figsize=(6.5, 4))
    ax.errorbar(k, [r.observed for r in rounds], yerr=[1.96 * r.observed_se for r in rounds],
                fmt="o-", label="recorded gait: observed")
    ax.plot(k, [r.true for r in rounds], "s", mfc="none", label="recorded gait: true")
    kp = [i + 1 for i in k]
    pred = [r.predicted for r in rounds]
    ax.errorbar(kp, pred, yerr=[[r.predicted - r.predicted_low for r in rounds],
                                [r.predicted_high - r.predicted for r in rounds]],
                fmt="^", color="C2", capsize=3, label="proposal: predicted (95%)")
    ax.plot(kp, [r.realised for r in rounds], "x", color="C3", ms=8, label="proposal: realised")
    if ceiling is not None:
        ax.axhline(ceiling, color="k", ls=":", label="optimiser, true connection")
    ax.set_xlabel("round")
    ax.set_ylabel(result.settings.objective + " per cycle")
    ax.legend(fontsize=7)
    fig.tight_layout()
    path = save_figure(fig, path, dpi=120)
    plt.close(fig)
    return path
