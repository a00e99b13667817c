"""Figures of a sweep, mirroring the paper's Fig. 3B/C and 4A/B (bands over trials).

Each ``fig*`` function returns a :class:`matplotlib.figure.Figure` with a caption (None when the
tables hold nothing to show) and draws into the caller's axes when given (``axes=``, one per
experiment); :func:`make_figures` writes them. Sweeps are simulated: time is in the paper's
units, one cycle of the limit cycle lasting 2π.
"""

from __future__ import annotations

from collections import defaultdict
from pathlib import Path

import numpy as np
from matplotlib.figure import Figure

from .. import plotting as style

__all__ = ["make_figures", "fig3b", "fig3c", "fig4a", "fig4b", "COLORS", "TIME_UNIT"]

COLORS = {"ground_truth": style.PALETTE["black"], "data_driven": style.COLORS["model"],
          "analytic": style.PALETTE["vermillion"], "template": style.PALETTE["orange"],
          "observed": style.PALETTE["purple"]}
#: the sweep's time unit (the simulator's: one cycle lasts 2π of them)
TIME_UNIT = "time unit"
_X_VELOCITY = style.velocity_label("v_x", TIME_UNIT)


def _group(rows, key, value):
    out = defaultdict(list)
    for r in rows:
        out[key(r)].append(value(r))
    return out


def _panels(exps, draw, text: str, *, axes=None, fn: str, column: bool = False,
            legend_ncol: int = 1) -> Figure | None:
    """One panel per experiment, side by side (or stacked, ``column=True``): ``draw(ax, exp)``
    fills each, the first gets the legend, the figure the caption ``text``. ``axes``: one Axes
    per experiment to draw into (None: a new figure). Returns None when there is no
    experiment to show."""
    if not exps:
        return None
    n = len(exps)
    shape = (n, 1) if column else (1, n)
    fig, grid = style.figure_and_grid(axes, shape, (9, 2.9 * n + 0.6) if column
                                      else (5 * n, 4.0), fn=fn)
    grid = grid.ravel()
    for ax, exp in zip(grid, exps, strict=True):
        draw(ax, exp)
    grid[0].legend(ncol=legend_ncol)
    return style.caption(fig, text)


def _of_kind(experiments, noise_kind: str) -> list:
    return [e for e in experiments if e.noise_kind == noise_kind]


@style.styled
def fig3b(traces, *, axes=None) -> Figure | None:
    """Forward body velocity of trial 0 over a few cycles: the simulator (ground truth) and
    each model's prediction, one panel per experiment."""
    def draw(ax, exp):
        series = _group([r for r in traces if r["experiment"] == exp and r["component"] == "x"],
                        lambda r: r["model"], lambda r: (r["t"], r["value"]))
        for model in ("ground_truth", "data_driven", "analytic", "template"):
            if model in series:
                t, v = np.asarray(sorted(series[model])).T
                ax.plot(t / (2 * np.pi), v, color=COLORS[model], lw=1.2 if model != "ground_truth"
                        else 2.0, label=model.replace("_", "-"), alpha=0.9)
        ax.set_title(f"{exp}: forward body velocity, cycles 13-18 (trial 0)")
        ax.set_xlabel("gait cycle (t / 2π)")
        ax.set_ylabel(_X_VELOCITY)

    return _panels(sorted({r["experiment"] for r in traces}), draw, (
        "Forward body velocity of one simulated trial: the simulator's (ground truth, thick "
        "black) and each model's prediction from the same joint angles. Good: the data-driven "
        "line follows the ground truth cycle by cycle, as the analytic (true-connection) "
        "model does; the template repeats one average cycle."), axes=axes, fn="fig3b",
        column=True, legend_ncol=4)


@style.styled
def fig3c(phase_errors, experiments, *, axes=None) -> Figure | None:
    """Forward-velocity error against phase at the paper's noise level, mean ± RMS over
    trials, per system-noise experiment."""
    def draw(ax, exp):
        level = min(exp.levels, key=lambda v: abs(v - 1.0))
        for model in ("data_driven", "analytic"):
            rows = [r for r in phase_errors if r["experiment"] == exp.name and r["level"] == level
                    and r["model"] == model and r["component"] == "x"]
            by_phase = _group(rows, lambda r: r["phase"], lambda r: (r["mean"], r["rms"]))
            ph = np.asarray(sorted(by_phase))
            mean = np.asarray([np.mean([m for m, _ in by_phase[p]]) for p in ph])
            spread = np.asarray([np.mean([s for _, s in by_phase[p]]) for p in ph])
            ax.plot(ph, mean, color=COLORS[model], lw=2, label=f"{model.replace('_', '-')} mean")
            ax.fill_between(ph, mean - spread, mean + spread, color=COLORS[model], alpha=0.2)
        ax.axhline(0, color="gray", lw=0.8)
        ax.set_title(f"{exp.name} at {level:g}x eta: x error vs phase")
        style.phase_axis(ax)
        ax.set_ylabel(style.velocity_label("v_x", TIME_UNIT, prefix="error of "))

    return _panels(_of_kind(experiments, "system"), draw, (
        "Error of the predicted forward velocity against the simulator's, by gait phase: the "
        "mean over trials (line) and the RMS spread (band). Good: the data-driven band is as "
        "narrow as the analytic model's and its mean stays near 0 at every phase."),
        axes=axes, fn="fig3c")


def _band(ax, results, exp, model, metric, color, label):
    rows = [r for r in results if r["experiment"] == exp.name and r["model"] == model
            and r["component"] == "x" and r["metric"] == metric]
    by_level = _group(rows, lambda r: r["level"], lambda r: r["value"])
    lv = np.asarray(sorted(by_level))
    vals = [np.asarray(by_level[v]) for v in lv]
    ax.plot(lv, [np.median(v) for v in vals], "o-", color=color, label=f"{label}: median")
    ax.fill_between(lv, [v.min() for v in vals], [v.max() for v in vals], color=color, alpha=0.2,
                    label=f"{label}: range over trials")


@style.styled
def fig4a(results, experiments, *, axes=None) -> Figure | None:
    """RMS forward-velocity error against system noise, median and range over trials."""
    def draw(ax, exp):
        for model in ("data_driven", "analytic"):
            _band(ax, results, exp, model, "rms_vs_ground_truth", COLORS[model],
                  model.replace("_", "-"))
        ax.set_xscale("log")
        ax.set_yscale("log")
        ax.set_xticks(exp.levels, [f"{v:g}" for v in exp.levels], minor=False)
        ax.minorticks_off()
        ax.set_title(f"{exp.name}: x error vs system noise")
        ax.set_xlabel("system noise (multiples of the paper's η)")
        ax.set_ylabel(style.velocity_label("v_x", TIME_UNIT, prefix="RMS error of "))

    return _panels(_of_kind(experiments, "system"), draw, (
        "RMS error of the predicted forward velocity against the simulator's, as the gait's "
        "cycle-to-cycle variation grows: median over trials (points) and range (band). Good: "
        "the data-driven error stays close to the analytic model's, which has the true "
        "connection, at every noise level."), axes=axes, fn="fig4a")


@style.styled
def fig4b(results, experiments, *, axes=None) -> Figure | None:
    """RMS forward-velocity error of the data-driven model against observation noise, against
    the simulator and against the noisy observations."""
    def draw(ax, exp):
        _band(ax, results, exp, "data_driven", "rms_vs_ground_truth", COLORS["template"],
              "vs ground truth")
        _band(ax, results, exp, "data_driven", "rms_vs_observed", COLORS["observed"],
              "vs observed data")
        ax.set_title(f"{exp.name}: data-driven x error vs observation noise")
        ax.set_xlabel("observation noise ω (BL, rad)")
        ax.set_ylabel(style.velocity_label("v_x", TIME_UNIT, prefix="RMS error of "))

    return _panels(_of_kind(experiments, "observation"), draw, (
        "RMS error of the data-driven forward velocity as the motion-capture noise grows, "
        "against the simulator's true velocity and against the noisy observed one. Good: the "
        "error against the truth stays well below the error against the observations (the "
        "model predicts the motion, not the noise)."), axes=axes, fn="fig4b")


def make_figures(out_dir: Path, results, phase_errors, traces, experiments) -> list[Path]:
    """Write every figure the tables support into ``out_dir``; returns their paths."""
    made = {"fig3b_traces.png": fig3b(traces),
            "fig3c_error_vs_phase.png": fig3c(phase_errors, experiments),
            "fig4a_system_noise.png": fig4a(results, experiments),
            "fig4b_observation_noise.png": fig4b(results, experiments)}
    return [style.save_figure(fig, out_dir / name) for name, fig in made.items()
            if fig is not None]
