"""Figures of the discrepancy workflow (matplotlib, Agg backend, PNG files)."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from .._output import save_figure
from .residuals import COMPONENTS

__all__ = ["plot_residual_profiles", "plot_terms"]

_LABELS = {"v_x": r"$v_x$ residual (body lengths / time)",
           "v_y": r"$v_y$ residual (body lengths / time)",
           "omega": r"$\omega$ residual (rad / time)"}


def _pyplot():
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def plot_residual_profiles(report, path: str | Path) -> Path:
    """Before/after residual versus phase, per component, with cycle-bootstrap bands and the
    noise floor (the RMS residual of a correct model) as a reference scale."""
    plt = _pyplot()
    fig, axes = plt.subplots(1, 3, figsize=(13, 3.8), constrained_layout=True)
    styles = {"before": ("tab:red", "nominal simulator"),
              "after": ("tab:blue", "with " + (", ".join(e.name for e in report.effects)
                                              or "no effect added"))}
    for k, comp in enumerate(COMPONENTS):
        ax = axes[k]
        for label, prof in report.profiles.items():
            color, text = styles[label]
            x = np.append(prof["centres"], 2 * np.pi)

            def wrap(a, k=k):  # close the periodic curve at 2π
                return np.append(a[:, k], a[0, k])
            ax.fill_between(x, wrap(prof["lo"]), wrap(prof["hi"]), color=color, alpha=0.25,
                            lw=0)
            ax.plot(x, wrap(prof["mean"]), color=color, lw=1.6, marker="o", ms=3,
                    label=f"{text}: gap {getattr(report, 'gap_' + label)[comp]:.2g}")
        fl = report.noise_floor[comp]
        ax.axhline(0, color="k", lw=0.8)
        ax.axhspan(-fl, fl, color="0.85", zorder=0, label=f"± noise floor {fl:.2g}")
        ax.set_xlim(0, 2 * np.pi)
        ax.set_xlabel("gait phase (rad)")
        ax.set_ylabel(_LABELS[comp])
        ax.legend(fontsize=7, loc="best")
    fig.suptitle(f"Held-out residual vs phase (mean over cycles, 95% bootstrap band) -- "
                 f"verdict: {report.verdict}", fontsize=10)
    path = save_figure(fig, path, dpi=110)
    plt.close(fig)
    return path


def plot_terms(terms: dict, path: str | Path) -> Path:
    """z-scores of Stage 4's local-model terms against the simulator's, per phase bin."""
    plt = _pyplot()
    names = list(terms["terms"])
    fig, axes = plt.subplots(1, len(names), figsize=(3.4 * len(names), 3.4),
                             constrained_layout=True)
    phase = np.asarray(terms["phase"])
    for ax, name in zip(np.atleast_1d(axes), names, strict=True):
        z = np.asarray(terms["terms"][name]["z"])
        z = z.reshape(z.shape[0], 3, -1)
        for k, comp in enumerate(COMPONENTS):
            for j in range(z.shape[2]):
                ax.plot(phase, z[:, k, j], lw=1, color=f"C{k}",
                        label=comp if j == 0 else None, alpha=0.8)
        ax.axhspan(-3, 3, color="0.9", zorder=0)
        ax.set_title(f"{name}: (data - simulator) / se", fontsize=9)
        ax.set_xlabel("phase (rad)")
        ax.legend(fontsize=7)
    path = save_figure(fig, path, dpi=100)
    plt.close(fig)
    return path
