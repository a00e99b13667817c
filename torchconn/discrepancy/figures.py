"""Figures of the discrepancy workflow: residual against phase, and the terms' z-scores.

Each function returns a :class:`matplotlib.figure.Figure` with a caption and draws into the
caller's axes when given; :func:`torchconn.plotting.save_figure` writes one.
"""

from __future__ import annotations

import numpy as np
from matplotlib.figure import Figure
from matplotlib.patches import Patch

from .. import plotting as style
from .residuals import COMPONENTS

__all__ = ["plot_residual_profiles", "plot_terms"]

#: the local model's terms, in words (:func:`~torchconn.discrepancy.residuals.compare_terms`)
TERMS = {"c": "ĉ, velocity on the cycle", "b": "b̂, per joint-angle offset",
         "A": "Â, per joint rate", "dA": "∂Â/∂r, per rate × offset"}
_Z_AGREE = 3.0


def _closed(x: np.ndarray, k: int) -> np.ndarray:
    """Column ``k`` of ``x (M, 3)`` with its first value appended (a periodic curve closed
    at 2π)."""
    return np.append(x[:, k], x[0, k])


@style.styled
def plot_residual_profiles(report, *, axes=None, time_unit: str = style.TIME_UNIT) -> Figure:
    """Held-out residual (recorded minus simulated body velocity) against phase, per
    component, before and after the effects were added, each with its 95% cycle-bootstrap
    band, beside the noise floor (the RMS residual of a correct model).

    Args:
        report: a :class:`~torchconn.discrepancy.report.DiscrepancyReport`.
        axes: three Axes (``v_x``, ``v_y``, ``ω``); None: a new figure.
        time_unit: the unit of the recording's time (default ``s``).
    """
    fig, grid = style.figure_and_grid(axes, (1, 3), (13, 4.2), fn="plot_residual_profiles")
    after = ", ".join(e.name for e in report.effects) or "no effect added"
    # the nominal simulator is drawn last and dashed, so the other model never hides it
    styles = {"after": (style.COLORS["after"], "-", "o", 2, f"with {after}"),
              "before": (style.COLORS["before"], "--", "s", 3, "nominal simulator")}
    order = sorted(report.profiles, key=lambda lab: lab == "before")
    for k, comp in enumerate(COMPONENTS):
        ax = grid[0, k]
        handles = []
        for label in order:
            prof = report.profiles[label]
            color, ls, marker, z, text = styles[label]
            x = np.append(prof["centres"], 2 * np.pi)
            ax.fill_between(x, _closed(prof["lo"], k), _closed(prof["hi"], k), color=color,
                            alpha=0.18, lw=0, zorder=z - 0.5)
            line, = ax.plot(x, _closed(prof["mean"], k), color=color, ls=ls, lw=1.8,
                            marker=marker, ms=3.5, mfc="white" if label == "before" else color,
                            zorder=z, label=f"{text}: gap "
                            f"{getattr(report, 'gap_' + label)[comp]:.2g}")
            handles += [line, Patch(color=color, alpha=0.3, label=f"{text}: 95% band")]
        fl = report.noise_floor[comp]
        ax.axhline(0, color="0.3", lw=0.8)
        handles.append(ax.axhspan(-fl, fl, color=style.COLORS["reference"], zorder=0,
                                  label=f"± noise floor {fl:.2g}"))
        style.phase_axis(ax)
        ax.set_ylabel(style.velocity_label(comp, time_unit, prefix="residual of "))
        ax.legend(handles=handles, loc="best")
    fig.suptitle("Held-out residual against phase: recorded minus simulated body velocity "
                 f"(mean over cycles) -- verdict: {report.verdict}")
    return style.caption(fig, (
        "Each panel: the recorded body velocity minus the simulator's, averaged over held-out "
        "cycles at each phase, with its 95% band over cycles, for the nominal simulator "
        "(dashed) and with the effects found added (solid); the grey zone is the noise floor, "
        "the residual a correct model leaves. Good: after the effects are added, the curve "
        "and its band stay within the grey zone at every phase; a band clear of it marks "
        "the phases where the model still misses something."))


@style.styled
def plot_terms(terms: dict, *, axes=None) -> Figure:
    """z-scores of the local model's terms fitted to the data against the simulator's, per
    phase bin (:func:`~torchconn.discrepancy.residuals.compare_terms`): one panel per term
    (row) and body-velocity component (column), each summarising all entries of that row
    of the term -- their range over entries, their median and the one of largest ``|z|``.

    Args:
        terms: the dict :func:`~torchconn.discrepancy.residuals.compare_terms` returns.
        axes: ``n_terms × 3`` Axes; None: a new figure.
    """
    names = list(terms["terms"])
    phase = np.asarray(terms["phase"])
    fig, grid = style.figure_and_grid(axes, (len(names), 3), (11, 2.3 * len(names) + 0.8),
                                      fn="plot_terms", sharex=True)
    color = style.COLORS["model"]
    for row, name in enumerate(names):
        z = np.asarray(terms["terms"][name]["z"], dtype=float)
        z = z.reshape(z.shape[0], 3, -1)
        for k, comp in enumerate(COMPONENTS):
            ax = grid[row, k]
            zk = z[:, k]  # (M, entries)
            ax.axhspan(-_Z_AGREE, _Z_AGREE, color=style.COLORS["reference"], zorder=0,
                       label=f"|z| ≤ {_Z_AGREE:g}: agrees")
            ax.fill_between(phase, np.nanmin(zk, 1), np.nanmax(zk, 1), color=color, alpha=0.25,
                            lw=0, label=f"range over the {zk.shape[1]} entries")
            ax.plot(phase, np.nanmedian(zk, 1), color=color, lw=1.5, label="median entry")
            worst = int(np.nanargmax(np.nanmax(np.abs(zk), 0))) if np.isfinite(zk).any() else 0
            ax.plot(phase, zk[:, worst], color=style.PALETTE["vermillion"], lw=1, ls="--",
                    label="entry of largest |z|")
            ax.axhline(0, color="0.3", lw=0.6)
            style.phase_axis(ax, label=row == len(names) - 1)
            ax.set_title(f"{TERMS.get(name, name)}: {style.SYMBOLS[comp]} row", fontsize=8)
            if k == 0:
                ax.set_ylabel("z (data − simulator) / se")
    grid[0, 0].legend(loc="best")
    reference = "its own fit to a simulated twin" if terms.get("reference") == "twin" \
        else "the simulator's exact values"
    fig.suptitle(f"The data's local model against the simulator's, term by term "
                 f"(reference: {reference})")
    return style.caption(fig, (
        "Each panel: for one term of the local model (row) and one body-velocity component "
        "(column), the difference between the data's estimate and the simulator's in "
        "standard errors (z), per phase bin, summarised over the term's entries (joints): "
        "their range (band), median (line) and the entry that disagrees most (dashed). Good: "
        "everything inside the grey zone |z| ≤ 3; a term whose band leaves it points at the "
        "part of the physics the simulator gets wrong."))
