"""Shared set-up of the example notebooks: small-data flag, output directory, figures, timing.

Import it before ``matplotlib.pyplot``: run as a script (not in Jupyter), it selects the
off-screen Agg backend; in Jupyter the inline plots are kept. A notebook uses it as::

    from _notebook import Notebook

    nb = Notebook("01_quickstart")   # nb.small, nb.out
    ...
    nb.save(fig, "gait")             # nb.out/gait.png, listed in figures.txt
    ...
    nb.finish()                      # writes nb.out/figures.txt, prints the run time

The module is not a notebook itself: ``tests/test_notebooks.py`` runs only ``0*.py``.
"""

from __future__ import annotations

import os
import sys
import time
from pathlib import Path

import matplotlib

IN_JUPYTER = "ipykernel" in sys.modules
if not IN_JUPYTER:  # a script: draw off-screen; in Jupyter keep inline plots
    matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402  (after the backend switch)

__all__ = ["Notebook"]

#: where figures go unless ``TORCHCONN_NB_OUT`` says otherwise: ``notebooks/_output/<name>/``
DEFAULT_OUT = Path(__file__).resolve().parent / "_output"


class Notebook:
    """One notebook run: ``small`` (``TORCHCONN_SMALL``), the output directory ``out``
    (``$TORCHCONN_NB_OUT/<name>/``, created) and the ``figures`` written so far."""

    def __init__(self, name: str):
        self.name = name
        self.small = os.environ.get("TORCHCONN_SMALL", "0").strip() not in ("", "0")
        self.out = Path(os.environ.get("TORCHCONN_NB_OUT") or DEFAULT_OUT) / name
        self.out.mkdir(parents=True, exist_ok=True)
        self.figures: list[Path] = []
        self.t_start = time.perf_counter()
        print(f"small-data mode: {self.small}; output directory: {self.out}")

    def add(self, path: Path) -> Path:
        """List a figure written elsewhere (e.g. by :mod:`torchconn.regression.plots`) in figures.txt."""
        path = Path(path)
        self.figures.append(path)
        print(f"figure: {path}")
        return path

    def save(self, fig, name: str) -> Path:
        """Write a figure to ``out/name.png`` (and keep it open in Jupyter, where it is shown)."""
        path = self.out / f"{name}.png"
        fig.savefig(path, dpi=110, bbox_inches="tight")
        self.add(path)
        if not IN_JUPYTER:
            plt.close(fig)
        return path

    def finish(self) -> None:
        """Write ``out/figures.txt`` (one figure file name per line) and print the run time."""
        (self.out / "figures.txt").write_text("".join(f"{p.name}\n" for p in self.figures))
        print(f"{len(self.figures)} figures in {self.out}: "
              f"{', '.join(p.name for p in self.figures)}")
        print(f"total run time {time.perf_counter() - self.t_start:.1f} s")
