"""One look for every figure torchconn draws: palette, axis labels with units, captions, saving.

Every plot function of the package (:mod:`torchconn.regression.plots`,
:mod:`torchconn.discrepancy.figures`, :mod:`torchconn.improve.plots`,
:mod:`torchconn.sweep.figures`) draws with this module's helpers and returns a
:class:`matplotlib.figure.Figure`; writing it to a file is a separate step, :func:`save_figure`.

Units: lengths in body lengths (``BL``), angles in ``rad``, time in ``s`` (a function that draws
a time or a velocity takes ``time_unit`` for data in other units, e.g. the simulator's, where one
cycle lasts 2π time units). Joint ``i`` joins links ``i`` and ``i + 1``; link 1 is the tail, so
joint 1 is the joint nearest the tail and joint ``d`` the one nearest the head.

The palette is Okabe and Ito's, which readers with any common colour-vision deficiency tell
apart; each role (recorded, model, baseline, …) keeps its colour across figures.
"""

from __future__ import annotations

import functools
import io
import sys
import textwrap
from collections.abc import Callable
from pathlib import Path

import matplotlib
import numpy as np
from matplotlib.axes import Axes
from matplotlib.figure import Figure

from ._output import save_figure as _save_atomic

__all__ = ["PALETTE", "CYCLE", "COLORS", "COMPONENT_NAMES", "SYMBOLS", "TIME_UNIT", "styled",
           "velocity_unit", "velocity_label", "phase_label", "phase_axis", "time_label", "joint_name",
           "joint_label", "connection_unit", "new_figure", "figure_and_axes",
           "figure_and_grid", "caption", "caption_of", "save_figure", "render_png", "JOINT_ORDER"]

#: Okabe & Ito's colour-blind-safe palette
PALETTE = {"black": "#000000", "orange": "#E69F00", "sky_blue": "#56B4E9",
           "green": "#009E73", "yellow": "#F0E442", "blue": "#0072B2",
           "vermillion": "#D55E00", "purple": "#CC79A7"}
#: the colour cycle of series without a role (yellow last: faint on white)
CYCLE = tuple(PALETTE[k] for k in ("blue", "orange", "green", "vermillion", "purple",
                                   "sky_blue", "black", "yellow"))
#: one colour per role, the same in every figure
COLORS = {"recorded": PALETTE["black"], "model": PALETTE["blue"],
          "phase_average": PALETTE["orange"], "physics": PALETTE["green"],
          "truth": PALETTE["black"], "samples": "0.6", "before": PALETTE["vermillion"],
          "after": PALETTE["blue"], "reference": "0.88", "metric": PALETTE["purple"]}
#: the body-velocity components ``(v_x, v_y, ω)`` in words
COMPONENT_NAMES = {"v_x": "forward velocity v_x", "v_y": "lateral velocity v_y",
                   "omega": "turning rate ω"}
#: the body-velocity components as symbols
SYMBOLS = {"v_x": "v_x", "v_y": "v_y", "omega": "ω"}
#: the time unit figures state unless told otherwise
TIME_UNIT = "s"
#: how joints are numbered, as figures state it
JOINT_ORDER = "joint 1 is nearest the tail, the last joint nearest the head"

_RC = {"axes.prop_cycle": matplotlib.cycler(color=list(CYCLE)), "axes.titlesize": 9,
       "axes.labelsize": 8.5, "xtick.labelsize": 8, "ytick.labelsize": 8,
       "legend.fontsize": 7, "legend.framealpha": 0.85, "axes.grid": True,
       "grid.color": "0.92", "grid.linewidth": 0.6, "axes.axisbelow": True,
       "figure.titlesize": 10}
_CAPTION_GID = "caption"
_CAPTION_SIZE = 8


def styled(draw: Callable) -> Callable:
    """Decorator: run a plot function under the package's style (fonts, grid, colour cycle)."""
    @functools.wraps(draw)
    def wrapper(*args, **kwargs):
        with matplotlib.rc_context(_RC):
            return draw(*args, **kwargs)
    return wrapper


# ------------------------------------------------------------------ units and labels
def _component(component: str | int) -> str:
    names = tuple(COMPONENT_NAMES)
    if isinstance(component, int):
        return names[component]
    if component not in COMPONENT_NAMES:
        raise ValueError(f"component must be one of {', '.join(names)} (or 0-2), "
                         f"got {component!r}")
    return component


def velocity_unit(component: str | int, time_unit: str = TIME_UNIT) -> str:
    """``BL/s`` for ``v_x``/``v_y``, ``rad/s`` for ``omega`` (``s`` replaced by ``time_unit``)."""
    length = "rad" if _component(component) == "omega" else "BL"
    return f"{length}/{time_unit}"


def velocity_label(component: str | int, time_unit: str = TIME_UNIT, prefix: str = "") -> str:
    """Axis label of a body-velocity component, e.g. ``forward velocity v_x (BL/s)``;
    ``prefix`` goes before it (``"residual of "``)."""
    comp = _component(component)
    return f"{prefix}{COMPONENT_NAMES[comp]} ({velocity_unit(comp, time_unit)})"


def phase_label() -> str:
    """Axis label of the gait phase."""
    return "gait phase φ (rad)"


def phase_axis(ax: Axes, label: bool = True) -> None:
    """Set ``ax``'s x axis to one gait cycle, ``[0, 2π]`` rad, ticked at multiples of π/2,
    labelled :func:`phase_label` (``label=False``: no label, e.g. above a shared axis)."""
    ax.set_xlim(0, 2 * np.pi)
    ax.set_xticks([0, np.pi / 2, np.pi, 3 * np.pi / 2, 2 * np.pi], ["0", "π/2", "π", "3π/2", "2π"])
    ax.set_xlabel(phase_label() if label else "")


def time_label(time_unit: str = TIME_UNIT) -> str:
    """Axis label of time."""
    return f"time ({time_unit})"


def joint_name(i: int, d: int) -> str:
    """Joint ``i`` (0-based) of ``d`` in words, numbered from 1, the ends named:
    ``joint 1 (tail)``, ``joint 3``, ``joint 4 (head)``."""
    end = " (tail)" if i == 0 else " (head)" if i == d - 1 else ""
    if d == 1:
        end = ""
    return f"joint {i + 1}{end}"


def joint_label(i: int, d: int) -> str:
    """Axis label of joint angle ``r_{i+1}``: ``joint 1 (tail) angle r1 (rad)``."""
    return f"{joint_name(i, d)} angle r{i + 1} (rad)"


def connection_unit(component: str | int) -> str:
    """Unit of a row of the connection ``A`` (body velocity per joint rate): ``BL/rad`` for
    ``v_x``/``v_y``, ``rad/rad`` for ``omega`` (time cancels)."""
    return "rad/rad" if _component(component) == "omega" else "BL/rad"


# ------------------------------------------------------------------ figures and axes
def new_figure(figsize: tuple[float, float]) -> Figure:
    """A figure outside pyplot (nothing global, nothing shown twice in Jupyter), laid out
    by matplotlib's constrained layout."""
    return Figure(figsize=figsize, layout="constrained")


def figure_and_axes(ax: Axes | None, figsize: tuple[float, float]) -> tuple[Figure, Axes]:
    """The figure of ``ax``, or a new figure with one axes when ``ax`` is None."""
    if ax is None:
        fig = new_figure(figsize)
        return fig, fig.subplots()
    if not isinstance(ax, Axes):
        raise TypeError(f"ax must be a matplotlib Axes or None, got {type(ax).__name__}")
    return _root(ax), ax


def figure_and_grid(axes, shape: tuple[int, int], figsize: tuple[float, float], *,
                    fn: str, **subplots) -> tuple[Figure, np.ndarray]:
    """``(figure, axes (rows, cols))``: a new figure with that grid when ``axes`` is None, else
    the caller's ``axes`` (any nesting of exactly ``rows × cols`` Axes of one figure).

    Raises:
        ValueError: ``axes`` does not hold ``rows × cols`` Axes (``fn`` names the function).
    """
    if axes is None:
        fig = new_figure(figsize)
        return fig, fig.subplots(*shape, squeeze=False, **subplots)
    grid = np.asarray(axes, dtype=object)
    if grid.size != shape[0] * shape[1] or not all(isinstance(a, Axes) for a in grid.flat):
        raise ValueError(f"{fn}: axes must hold {shape[0]} x {shape[1]} matplotlib Axes "
                         f"(rows x columns), got {grid.size} object(s) of shape {grid.shape}")
    grid = grid.reshape(shape)
    return _root(grid.flat[0]), grid


def _root(ax: Axes) -> Figure:
    """The figure that holds ``ax`` (the top one where ``ax`` is in a subfigure)."""
    return ax.figure.figure  # a Figure's own ``figure`` is itself, a SubFigure's its root


# ------------------------------------------------------------------ captions and saving
def caption(fig: Figure, text: str) -> Figure:
    """Set the caption of ``fig``: a paragraph below the axes that says what the figure shows
    and what a good result looks like (replacing an earlier one). :func:`save_figure`
    includes it; returns ``fig``."""
    for old in [t for t in fig.texts if t.get_gid() == _CAPTION_GID]:
        old.remove()
    width = fig.get_figwidth() * 72 / (0.52 * _CAPTION_SIZE)  # characters per line
    wrapped = "\n".join(textwrap.wrap(" ".join(text.split()), max(int(width), 40)))
    fig.text(0.01, -0.01, wrapped, ha="left", va="top", fontsize=_CAPTION_SIZE,
             gid=_CAPTION_GID, color="0.15")
    return fig


def caption_of(fig: Figure) -> str | None:
    """The caption :func:`caption` set on ``fig`` (one paragraph), or None."""
    texts = [t.get_text() for t in fig.texts if t.get_gid() == _CAPTION_GID]
    return " ".join(texts[-1].split()) if texts else None


def save_figure(fig: Figure, path: str | Path, *, dpi: int = 110) -> Path:
    """Write ``fig`` to ``path`` (all or nothing; the format its suffix names, default PNG),
    caption included, then close it. Returns the path."""
    try:
        return _save_atomic(fig, path, dpi=dpi, bbox_inches="tight", pad_inches=0.12)
    finally:
        fig.clf()
        _close(fig)


def render_png(fig: Figure, *, dpi: int = 110) -> tuple[bytes, str | None]:
    """``fig`` rendered as :func:`save_figure` writes it (PNG, caption included) and its
    caption (:func:`caption_of`), then closed (released from pyplot where it manages it; the
    figure itself is left as drawn): one rendering for a file and a report."""
    try:
        caption = caption_of(fig)
        buffer = io.BytesIO()
        fig.savefig(buffer, format="png", dpi=dpi, bbox_inches="tight", pad_inches=0.12)
        return buffer.getvalue(), caption
    finally:
        _close(fig)


def _close(fig: Figure) -> None:
    """Release ``fig`` from pyplot where pyplot manages it (it never does for the package's
    own figures)."""
    pyplot = sys.modules.get("matplotlib.pyplot")
    if pyplot is not None:
        pyplot.close(fig)
