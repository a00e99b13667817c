"""Checks shared by the figure tests: axis labels with units, legends."""

from __future__ import annotations


def legend_texts(ax) -> list[str]:
    """The entries of ``ax``'s legend ([] without one)."""
    legend = ax.get_legend()
    return [] if legend is None else [t.get_text() for t in legend.get_texts()]


def assert_units(label: str, *units: str) -> None:
    """``label`` names one of ``units`` in brackets, e.g. ``time (s)``."""
    assert any(f"({u})" in label for u in units), (label, units)


def assert_labelled(ax, x: tuple[str, ...], y: tuple[str, ...]) -> None:
    """``ax``'s x label names one of the units ``x``, its y label one of ``y``."""
    assert_units(ax.get_xlabel(), *x)
    assert_units(ax.get_ylabel(), *y)
