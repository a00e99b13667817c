"""Figures of an improvement loop: the gaits over the curvature, the objective per round.

Each function returns a :class:`matplotlib.figure.Figure` with a caption and draws into the
caller's axes when given (``ax=``); :func:`torchconn.plotting.save_figure` writes one.
"""

from __future__ import annotations

import math

import matplotlib
import torch
from matplotlib.figure import Figure

from .. import _linalg
from .. import plotting as style
from ..physics.systems.base import LocomotionSystem
from .loop import LoopResult

__all__ = ["plot_gaits", "plot_rounds", "OBJECTIVE_LABELS"]

#: each objective (:data:`~torchconn.improve.propose.OBJECTIVES`) as an axis label with its unit
OBJECTIVE_LABELS = {"displacement": "displacement per cycle (BL)",
                    "efficiency": "efficiency: displacement per unit cost (BL/cost)",
                    "turning": "turning per cycle (rad)"}


@style.styled
def plot_gaits(result: LoopResult, system: LocomotionSystem, *, ax=None,
               n_phase: int = 200) -> Figure:
    """The recorded gaits of every recording and the next proposal: over the x-curvature
    ``DA_x`` (2 joints) or projected on the first two principal components of all their
    shapes (more joints). ``ax``: the Axes to draw into; None: a new figure."""
    phi = torch.linspace(0, 2 * math.pi, n_phase, dtype=torch.float64)
    loops = [r.gait(phi).detach() for r in result.rounds] + [result.rounds[-1].proposal(phi)]
    fig, ax = style.figure_and_axes(ax, (6, 5.4))
    d = system.shape_dim
    if d == 2:
        span = max(float(torch.cat(loops).abs().max()) * 1.15, 0.5)
        g = torch.linspace(-span, span, 121, dtype=torch.float64)
        grid = torch.stack(torch.meshgrid(g, g, indexing="xy"), -1)
        da = system.curvature(grid)[..., 0, 0].detach()
        lim = float(da.abs().max())
        im = ax.pcolormesh(g.numpy(), g.numpy(), da.numpy(), cmap="RdBu_r", vmin=-lim,
                           vmax=lim, shading="auto")
        fig.colorbar(im, ax=ax, label="curvature DA_x (BL/rad²)")
        ax.set_xlabel(style.joint_label(0, d))
        ax.set_ylabel(style.joint_label(1, d))
        proj = loops
        where = ("over the x-curvature (to first order a loop's forward displacement is the "
                 "curvature it encloses: red counts positive when circled counter-clockwise)")
    else:
        allr = torch.cat(loops)
        mean = allr.mean(0)
        _, _, v = _linalg.svd(allr - mean, "the recorded gaits' shapes")
        proj = [(r - mean) @ v[:2].T for r in loops]
        ax.set_xlabel("principal component 1 of the joint angles (rad)")
        ax.set_ylabel("principal component 2 of the joint angles (rad)")
        where = "in the plane of the two principal components of all their joint angles"
    cmap = matplotlib.colormaps["viridis"]
    for k, p in enumerate(proj):
        p = p.detach().cpu().numpy()
        last = k == len(proj) - 1
        ax.plot(p[:, 0], p[:, 1], color=style.COLORS["recorded"] if last
                else cmap(k / max(len(proj) - 1, 1)),
                ls="--" if last else "-", lw=1.5,
                label="next proposal" if last else f"{k}: {result.rounds[k].kind}")
    ax.set_aspect("equal")
    ax.legend(loc="upper right")
    ax.set_title("Recorded gaits and the next proposal")
    return style.caption(fig, (
        f"Each loop: one recording's gait (colour from first to last; start, proposal, "
        f"repeat or perturbed: excited) {where}; "
        "dashed: the gait proposed next. Good: the loops move steadily towards higher "
        "objective and settle; a proposal far from every recorded loop is an extrapolation "
        "the trust region should have kept small."))


@style.styled
def plot_rounds(result: LoopResult, *, ceiling: float | None = None, ax=None) -> Figure:
    """Objective against recorded cycles: observed and true of each recording, the kept
    gait's true value, predicted (interval) vs realised of each proposal the loop moved to,
    and the ceiling with the true connection. ``ax``: the Axes to draw into; None: a new
    figure."""
    rounds = result.rounds
    c = [r.cycles_used for r in rounds]
    fig, ax = style.figure_and_axes(ax, (7, 4.4))
    colors = style.PALETTE
    ax.errorbar(c, [r.observed for r in rounds], yerr=[1.96 * r.observed_se for r in rounds],
                fmt="o", color=colors["blue"], capsize=2,
                label="recording: observed ±95%")
    ax.plot(c, [r.true for r in rounds], "s", mfc="none", color=colors["black"],
            label="recording: true (simulator)")
    ax.step(c, [r.kept_true for r in rounds], where="post", color=colors["black"], lw=1.2,
            label="kept gait: true (simulator)")
    moved = [(r, n + r.cycles) for r, n in zip(rounds, c, strict=True) if r.moved]
    if moved:
        ax.errorbar([n for _, n in moved], [r.predicted for r, _ in moved],
                    yerr=[[r.predicted - r.predicted_low for r, _ in moved],
                          [r.predicted_high - r.predicted for r, _ in moved]],
                    fmt="^", color=colors["green"], capsize=3, label="proposal: predicted (95%)")
        ax.plot([n for _, n in moved], [r.realised for r, _ in moved], "x",
                color=colors["vermillion"], ms=8, label="proposal: realised (simulator)")
    if ceiling is not None:
        ax.axhline(ceiling, color="0.3", ls=":", label="optimiser, true connection")
    objective = result.settings.objective
    ax.set_xlabel("cycles recorded")
    ax.set_ylabel(OBJECTIVE_LABELS.get(objective, objective))
    ax.legend(loc="best")
    ax.set_title(f"The {objective} against the cycles recorded")
    return style.caption(fig, (
        "Per recording: its objective from its own cycles (with its 95% interval) and as the "
        "simulator has it; the line is the true objective of the gait the loop keeps. Each "
        "proposal the loop moved to: its predicted interval, at the cycles when it was "
        "recorded, against what it realised. Good: the realised values fall inside the "
        "predicted intervals and the kept gait rises towards the ceiling in few cycles."))
