"""PNG figures of a sweep, mirroring the paper's Fig. 3B/C and 4A/B (bands over trials)."""

from __future__ import annotations

from collections import defaultdict
from pathlib import Path

import numpy as np
from matplotlib.figure import Figure

from .._output import save_figure

__all__ = ["make_figures", "COLORS"]

COLORS = {"ground_truth": "black", "data_driven": "tab:green", "analytic": "tab:red",
          "template": "tab:orange", "observed": "tab:purple"}


def _group(rows, key, value):
    out = defaultdict(list)
    for r in rows:
        out[key(r)].append(value(r))
    return out


def _panels(path: Path, exps, draw, *, column: bool = False, legend_ncol: int = 1) -> Path | None:
    """One panel per experiment, side by side (or stacked, ``column=True``): ``draw(ax, exp)``
    fills each, the first gets the legend, and the figure is saved to ``path``.
    Returns ``None`` (and writes nothing) when there is no experiment to show."""
    if not exps:
        return None
    n = len(exps)
    fig = Figure(figsize=(9, 2.8 * n) if column else (5 * n, 3.4))
    axes = fig.subplots(*((n, 1) if column else (1, n)), squeeze=False).ravel()
    for ax, exp in zip(axes, exps, strict=False):
        draw(ax, exp)
    axes[0].legend(ncol=legend_ncol, fontsize=8)
    return _save(fig, path)


def _of_kind(experiments, noise_kind: str) -> list:
    return [e for e in experiments if e.noise_kind == noise_kind]


def fig3b(traces, path: Path) -> Path | None:
    def draw(ax, exp):
        series = _group([r for r in traces if r["experiment"] == exp and r["component"] == "x"],
                        lambda r: r["model"], lambda r: (r["t"], r["value"]))
        for model in ("ground_truth", "data_driven", "analytic", "template"):
            if model in series:
                t, v = np.asarray(sorted(series[model])).T
                ax.plot(t / (2 * np.pi), v, color=COLORS[model], lw=1.2 if model != "ground_truth"
                        else 2.0, label=model.replace("_", "-"), alpha=0.9)
        ax.set_title(f"{exp}: forward body velocity, cycles 13-18 (trial 0)")
        ax.set_xlabel("cycle")
        ax.set_ylabel(r"$\xi_x$")

    return _panels(path, sorted({r["experiment"] for r in traces}), draw, column=True,
                   legend_ncol=4)


def fig3c(phase_errors, experiments, path: Path) -> Path | None:
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
        ax.set_xlabel("phase (rad)")
        ax.set_ylabel("error vs ground truth")

    return _panels(path, _of_kind(experiments, "system"), draw)


def _band(ax, results, exp, model, metric, color, label):
    rows = [r for r in results if r["experiment"] == exp.name and r["model"] == model
            and r["component"] == "x" and r["metric"] == metric]
    by_level = _group(rows, lambda r: r["level"], lambda r: r["value"])
    lv = np.asarray(sorted(by_level))
    vals = [np.asarray(by_level[v]) for v in lv]
    ax.plot(lv, [np.median(v) for v in vals], "o-", color=color, label=label)
    ax.fill_between(lv, [v.min() for v in vals], [v.max() for v in vals], color=color, alpha=0.2)


def fig4a(results, experiments, path: Path) -> Path | None:
    def draw(ax, exp):
        for model in ("data_driven", "analytic"):
            _band(ax, results, exp, model, "rms_vs_ground_truth", COLORS[model],
                  model.replace("_", "-"))
        ax.set_xscale("log")
        ax.set_yscale("log")
        ax.set_xticks(exp.levels, [f"{v:g}" for v in exp.levels], minor=False)
        ax.minorticks_off()
        ax.set_title(f"{exp.name}: x error vs system noise")
        ax.set_xlabel("system noise (multiples of eta)")
        ax.set_ylabel("RMS error vs ground truth")

    return _panels(path, _of_kind(experiments, "system"), draw)


def fig4b(results, experiments, path: Path) -> Path | None:
    def draw(ax, exp):
        _band(ax, results, exp, "data_driven", "rms_vs_ground_truth", "tab:orange",
              "vs ground truth")
        _band(ax, results, exp, "data_driven", "rms_vs_observed", "tab:purple",
              "vs observed data")
        ax.set_title(f"{exp.name}: data-driven x error vs observation noise")
        ax.set_xlabel(r"observation noise $\omega$")
        ax.set_ylabel("RMS error")

    return _panels(path, _of_kind(experiments, "observation"), draw)


def _save(fig, path: Path) -> Path:
    fig.tight_layout()
    return save_figure(fig, path, dpi=110)


def make_figures(out_dir: Path, results, phase_errors, traces, experiments) -> list[Path]:
    """Write every figure the tables support; returns their paths."""
    made = [
        fig3b(traces, out_dir / "fig3b_traces.png"),
        fig3c(phase_errors, experiments, out_dir / "fig3c_error_vs_phase.png"),
        fig4a(results, experiments, out_dir / "fig4a_system_noise.png"),
        fig4b(results, experiments, out_dir / "fig4b_observation_noise.png"),
    ]
    return [p for p in made if p is not None]
