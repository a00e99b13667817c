"""Figures of a fitted local model: held-out velocity, A, M and the limit cycle, with 95% bands.

Every function returns a :class:`matplotlib.figure.Figure` with a caption and draws into the
caller's axes when given (``ax=``/``axes=``); :func:`torchconn.plotting.save_figure` writes one.
Joint ``i`` joins links ``i`` and ``i + 1``, link 1 the tail (:mod:`torchconn.plotting`).
"""

from __future__ import annotations

import math

import numpy as np
import torch
from matplotlib.figure import Figure

from .. import plotting as style
from . import selection
from .model import ROWS, LocalConnectionModel

__all__ = ["plot_held_out_velocity", "plot_connection", "plot_metric", "plot_limit_cycle",
           "ROWS"]

_Z95 = 1.96


def _grid(n: int = 200) -> torch.Tensor:
    return torch.linspace(0, 2 * math.pi, n, dtype=torch.float64)


def _unbatched(model: LocalConnectionModel, fn: str) -> LocalConnectionModel:
    if not isinstance(model, LocalConnectionModel):
        raise TypeError(f"{fn}: model must be a LocalConnectionModel, got {type(model).__name__}")
    if model.batch_shape:
        raise ValueError(f"{fn} draws one model, got a batch {tuple(model.batch_shape)}: "
                         "pass model[i] for trial i")
    return model.to("cpu")


@style.styled
def plot_held_out_velocity(estimator, *, trial: int = 0, axes=None,
                           time_unit: str = style.TIME_UNIT) -> Figure:
    """Recorded body velocity against the model's prediction and the phase average, on the
    cycles the fit did not see: the last block of cycles of the held-out check (the forward
    split of :meth:`~torchconn.regression.estimator.ConnectionEstimator.cross_validate`),
    predicted by the forecasting model and the phase average fitted to the earlier cycles.

    Args:
        estimator: a fitted :class:`~torchconn.regression.estimator.ConnectionEstimator`.
        trial: which trial to draw (flat index over the batch dims; all trials are
            predicted, one is drawn). Default 0.
        axes: three Axes (``v_x``, ``v_y``, ``ω``) to draw into; None: a new figure.
        time_unit: the unit of the recording's time (default ``s``).

    Returns:
        The figure (the forecasts as delivered: blended with the physics reference where
        the prior acts); its panel titles give the held-out ``R²`` of the forward check
        (``estimator.forward_skill_``, over all trials) where the fit ran it.

    Raises:
        ValueError: the estimator is not fitted, or ``trial`` is out of range.
    """
    fn = "plot_held_out_velocity"
    if not hasattr(estimator, "forecast_model_"):
        raise ValueError(f"{fn}: the estimator is not fitted; call estimator.fit(trajectory) "
                         "first")
    model = estimator.forecast_model_
    choice = estimator.complexity_
    masks = ((None, None) if choice is None else
             (choice.phase_average_mask(model.device), choice.connection_only_mask(model.device)))
    n_folds = estimator.held_out_folds or 3
    reference = estimator.reference_  # the prior's family and frame, where it was fitted
    pred = selection.forward_prediction(
        estimator.trajectory_, estimator.limit_cycle_, estimator.regression_, model,
        pool=estimator.pool, n_folds=n_folds, phase_averaged=masks[0],
        connection_only=masks[1],
        connection_regressed=getattr(choice, "connection_regressed", False),
        prior_weight=estimator.prior_weight_,
        family=reference.family if reference is not None else "swimmer",
        frame=reference.frame if reference is not None else None)
    n_trials = math.prod(pred.held_out.shape[:-1])
    if isinstance(trial, bool) or not isinstance(trial, int) or not 0 <= trial < n_trials:
        raise ValueError(f"{fn}: trial must be an integer in [0, {n_trials}), got {trial!r}")

    def one(x):
        return x.reshape(n_trials, *x.shape[pred.held_out.ndim - 1:])[trial].cpu().numpy()

    held = one(pred.held_out)
    recorded, predicted, average = one(pred.view.xi), one(pred.predicted), one(pred.phase_average)
    dt = estimator.trajectory_.dt
    t = np.arange(held.shape[0]) * dt + float(estimator.trajectory_.t.reshape(-1)[0])
    if held.any():  # the held-out block, with a margin of the cycles before it
        idx = np.flatnonzero(held)
        keep = slice(max(idx[0] - (idx[-1] - idx[0]) // 8, 0), idx[-1] + 1)
    else:
        keep = slice(0, 0)
    skill = estimator.forward_skill_
    fig, grid = style.figure_and_grid(axes, (3, 1), (8, 6.2), fn=fn, sharex=True)
    for k, (ax, comp) in enumerate(zip(grid[:, 0], selection.COMPONENTS, strict=True)):
        ax.plot(t[keep], recorded[keep, k], color=style.COLORS["recorded"], lw=1.8,
                label="recorded")
        ax.plot(t[keep], predicted[keep, k], color=style.COLORS["model"], lw=1.3,
                label="model, fitted without these cycles")
        ax.plot(t[keep], average[keep, k], color=style.COLORS["phase_average"], lw=1.3,
                ls="--", label="phase average of the earlier cycles")
        if held.any():
            ax.axvspan(t[idx[0]], t[idx[-1]], color=style.COLORS["reference"], zorder=0,
                       label="held-out cycles")
        ax.set_ylabel(style.velocity_label(comp, time_unit), fontsize=8)
        if skill is not None:
            ax.set_title(f"{style.COMPONENT_NAMES[comp]}: held-out R² model "
                         f"{float(skill.r2.reshape(-1, 3)[:, k].mean()):.2f}, phase average "
                         f"{float(skill.r2_phase_average.reshape(-1, 3)[:, k].mean()):.2f}",
                         fontsize=8.5)
    grid[-1, 0].set_xlabel(style.time_label(time_unit))
    grid[0, 0].legend(loc="upper right", ncol=2)
    if not held.any():
        grid[0, 0].text(0.5, 0.5, "no held-out samples in this trial", ha="center",
                        transform=grid[0, 0].transAxes)
    fig.suptitle(f"Held-out check, trial {trial}: the last {_block(n_folds)} of the recording "
                 "predicted by the fit to the cycles before it")
    return style.caption(fig, (
        "Body velocity on cycles the fit did not see (shaded), as recorded (black) and as "
        "predicted from the joint angles by the model fitted to the earlier cycles (blue); "
        "the phase average (dashed) predicts the same velocity at every visit of a phase. "
        "Good: the model follows the recorded wiggles from cycle to cycle and its held-out "
        "R² (closer to 1 is better) is above the phase average's; where it is not, the "
        "shape terms add nothing the average gait does not already say."))


def _block(n_folds: int) -> str:
    return {2: "half", 3: "third", 4: "quarter", 5: "fifth"}.get(n_folds, f"1/{n_folds}")


@style.styled
def plot_connection(model: LocalConnectionModel, *, truth=None, axes=None) -> Figure:
    """Each entry ``A^k_i(φ)`` of the local connection (body velocity ``k`` per unit rate of
    joint ``i``) along the gait: the Fourier fit, the per-bin estimates with 95% intervals
    and optionally the true values.

    Args:
        model: an unbatched fitted model.
        truth: optional ``truth(phi) -> (P, 3, d)``, e.g. the simulator on the cycle.
        axes: ``3 × d`` Axes (rows ``v_x, v_y, ω``, columns joints 1…d); None: a new figure.
    """
    model = _unbatched(model, "plot_connection")
    phi = _grid()
    d = model.shape_dim
    fit = model.connection(phi)
    bins = model.bins
    fig, grid = style.figure_and_grid(axes, (3, d), (2.7 * d + 1.2, 6.8), fn="plot_connection",
                                      sharex=True)
    true = truth(phi) if truth is not None else None
    color = style.COLORS["model"]
    for k, comp in enumerate(selection.COMPONENTS):
        for i in range(d):
            ax = grid[k, i]
            ax.axhline(0, color="0.5", lw=0.6)
            ax.errorbar(bins.phase, bins.A[:, k, i], yerr=_Z95 * bins.A_se[:, k, i], fmt="o",
                        ms=3, color=color, alpha=0.55, elinewidth=0.8,
                        label="per-bin estimate ±95%")
            ax.plot(phi, fit[:, k, i], color=color, lw=1.6, label="fit (Fourier in phase)")
            if true is not None:
                ax.plot(phi, true[:, k, i], color=style.COLORS["truth"], ls="--", lw=1.1,
                        label="true (simulator)")
            ax.set_title(f"{style.SYMBOLS[comp]} per {style.joint_name(i, d)} rate "
                         f"({style.connection_unit(comp)})", fontsize=8)
            style.phase_axis(ax, label=k == 2)
        grid[k, 0].set_ylabel(f"Â, {style.SYMBOLS[comp]} row ({style.connection_unit(comp)})")
    grid[0, 0].legend(loc="best")
    fig.suptitle("Local connection Â(φ): body velocity per unit joint rate along the gait\n"
                 f"({style.JOINT_ORDER})")
    return style.caption(fig, (
        "Each panel: how much body velocity (row: forward v_x, lateral v_y, turning ω) one "
        "unit of joint angular rate (column) produces at each phase of the gait; body "
        "velocity = Â · joint rates. Points: estimates per phase bin with 95% intervals; line: "
        "the smooth fit. Good: the line passes through the intervals and the intervals are "
        "narrow against the curve's swing; an entry whose intervals straddle 0 all along is "
        "not determined by this recording."))


@style.styled
def plot_metric(model: LocalConnectionModel, *, truth=None, axes=None,
                time_unit: str = style.TIME_UNIT) -> Figure:
    """The dissipation metric along the gait with 95% intervals: first row ``M̂γ̇`` per joint
    and the on-cycle power ``γ̇ᵀM̂γ̇`` (what the gait itself identifies), then the diagonal and
    first off-diagonal entries of the full ``M̂`` (only as good as the off-cycle excitation:
    wide bands where the data do not excite a direction).

    Args:
        model: an unbatched fitted model with a metric (a recording with power).
        truth: optional ``truth(phi) -> (P, d, d)``, the true metric on the fitted cycle.
        axes: a grid of Axes of the figure's shape (``rows × cols``: ``cols = min(max(2d − 1,
            d + 1), 4)``, rows ``⌈(d + 1)/cols⌉ + ⌈(2d − 1)/cols⌉``); None: a new figure.
        time_unit: the unit of the recording's time (default ``s``).

    Raises:
        ValueError: the model has no metric.
    """
    model = _unbatched(model, "plot_metric")
    if model.M is None:
        raise ValueError("plot_metric: the model has no metric (fit a recording with a power "
                         "column)")
    phi = _grid()
    d = model.shape_dim
    fit = model.metric(phi)
    bins = model.bins
    pairs = [(i, i) for i in range(d)] + [(i, i + 1) for i in range(d - 1)]
    cols = min(max(len(pairs), d + 1), 4)
    top = math.ceil((d + 1) / cols)
    rows = top + math.ceil(len(pairs) / cols)
    fig, grid = style.figure_and_grid(axes, (rows, cols), (3 * cols, 2.5 * rows + 0.6),
                                      fn="plot_metric")
    true = truth(phi) if truth is not None else None
    gd = model.gamma_dot_at(phi)
    mgd = model.metric_gamma_dot(phi)
    gd_bins = bins.gamma_dot
    power = "power unit"
    panels = [(f"(M̂γ̇) at {style.joint_name(i, d)} ({power}·{time_unit}/rad)", mgd[:, i],
               bins.M_gamma_dot, bins.M_gamma_dot_se, i,
               None if true is None else (true @ gd[..., None])[:, i, 0]) for i in range(d)]
    panels.append((f"power on the cycle γ̇ᵀM̂γ̇ ({power})", model.power_on_cycle(phi),
                   bins.power_on_cycle, bins.power_on_cycle_se, None,
                   None if true is None else (gd[:, None, :] @ true @ gd[..., None])[:, 0, 0]))
    on_cycle, full = style.COLORS["metric"], style.COLORS["model"]
    for ax, (title, curve, est, se, i, ref) in zip(grid[:top].flat, panels, strict=False):
        if est is not None and se is not None and gd_bins is not None:
            e, s = (est[:, i], se[:, i]) if i is not None else (est, se)
            ax.errorbar(bins.phase, e, yerr=_Z95 * s, fmt="o", ms=3, color=on_cycle,
                        alpha=0.55, elinewidth=0.8, label="per-bin estimate ±95%")
        ax.plot(phi, curve, color=on_cycle, lw=1.6, label="fit")
        if ref is not None:
            ax.plot(phi, ref, color=style.COLORS["truth"], ls="--", lw=1.1, label="true")
        ax.set_title(title, fontsize=8)
        style.phase_axis(ax)
    for ax in list(grid[:top].flat)[len(panels):]:
        ax.axis("off")
    for ax, (i, j) in zip(grid[top:].flat, pairs, strict=False):
        ax.errorbar(bins.phase, bins.M[:, i, j], yerr=_Z95 * bins.M_se[:, i, j], fmt="o", ms=3,
                    color=full, alpha=0.55, elinewidth=0.8, label="per-bin estimate ±95%")
        ax.plot(phi, fit[:, i, j], color=full, lw=1.6, label="fit")
        if true is not None:
            ax.plot(phi, true[:, i, j], color=style.COLORS["truth"], ls="--", lw=1.1,
                    label="true")
        ax.set_title(f"M̂_{i + 1}{j + 1}, full metric ({power}·{time_unit}²/rad²)", fontsize=8)
        style.phase_axis(ax)
    for ax in list(grid[top:].flat)[len(pairs):]:
        ax.axis("off")
    grid[0, 0].legend(loc="best")
    grid[top, 0].legend(loc="best")
    fig.suptitle("Dissipation metric M̂ along the gait; power = joint rates · M̂ · joint rates\n"
                 f"({style.JOINT_ORDER})")
    return style.caption(fig, (
        "Top: what the gait itself determines, the metric times the gait's joint rates per "
        "joint and the power dissipated on the cycle (in the unit of the recording's power "
        "column). Below: entries of the full metric, determined only as far as the recording "
        "strays from the average gait. Good: the line passes through the per-bin 95% "
        "intervals and the intervals are narrow against the curve; wide intervals on the full "
        "metric mean the recording does not excite that direction, not that it is zero."))


@style.styled
def plot_limit_cycle(model: LocalConnectionModel, r=None, phase=None, *, axes=None) -> Figure:
    """Every joint's angle against the gait phase: the fitted limit cycle ``γ(φ)`` over the
    recorded samples.

    Args:
        model: an unbatched fitted model.
        r: optional recorded joint angles ``(..., T, d)`` in rad, drawn with ``phase``.
        phase: their phase ``(..., T)`` in rad (unwrapped or not); needed with ``r``.
        axes: a grid of ``rows × cols`` Axes, ``cols = min(d, 4)``, ``rows = ⌈d/cols⌉``;
            None: a new figure.

    Raises:
        ValueError: ``r`` without ``phase``, or shapes that do not match.
    """
    model = _unbatched(model, "plot_limit_cycle")
    d = model.shape_dim
    if (r is None) != (phase is None):
        raise ValueError("plot_limit_cycle: pass r and phase together (phase: the samples' "
                         "gait phase in rad, e.g. trajectory.phase)")
    if r is not None:
        r = torch.as_tensor(r).detach().cpu()
        phase = torch.as_tensor(phase).detach().cpu()
        if r.shape[-1] != d or r.shape[:-1] != phase.shape:
            raise ValueError(f"plot_limit_cycle: r must be (..., T, {d}) and phase (..., T) "
                             f"for this {d}-joint model, got r {tuple(r.shape)} and phase "
                             f"{tuple(phase.shape)}")
        phase = torch.remainder(phase.reshape(-1), 2 * math.pi)
        r = r.reshape(-1, d)
    phi = _grid()
    gamma = model.gamma_at(phi)
    cols = min(d, 4)
    rows = math.ceil(d / cols)
    fig, grid = style.figure_and_grid(axes, (rows, cols), (3.1 * cols, 2.6 * rows + 0.7),
                                      fn="plot_limit_cycle", sharex=True)
    for i, ax in enumerate(grid.flat):
        if i >= d:
            ax.axis("off")
            continue
        if r is not None:
            ax.plot(phase, r[:, i], ".", ms=1.5, color=style.COLORS["samples"], alpha=0.5,
                    rasterized=True, label="recorded samples")
        ax.plot(phi, gamma[:, i], color=style.PALETTE["vermillion"], lw=2,
                label="limit cycle γ(φ)")
        ax.set_title(style.joint_name(i, d), fontsize=8.5)
        ax.set_ylabel(f"angle r{i + 1} (rad)")
        style.phase_axis(ax, label=i >= d - cols)
    grid.flat[0].legend(loc="best", markerscale=6)
    fig.suptitle(f"The gait: each joint's angle against phase\n({style.JOINT_ORDER})")
    return style.caption(fig, (
        "Each panel: one joint's angle over a gait cycle, the recorded samples (grey) and the "
        "fitted average gait, the limit cycle (line). Good: the line runs through the middle "
        "of the samples at every phase. The spread around it is the cycle-to-cycle variation "
        "the model uses; a spread that is large against the swing, or a line off the cloud, "
        "means the phase was not found well (check that the recording is a steady gait)."))
